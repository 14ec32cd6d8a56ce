#!/usr/bin/env bash
# The GPU measurements of the rally kernel in a few minutes, for a machine lent for a short time
# (one NVIDIA GPU, no network); one call per step where a call is limited to 600 s (below):
#
#   OUT=/some/folder bash benchmarks/gpu_session.sh
#
# 1. peers.py, flight + table at 262,144 / 1,048,576 balls: the kernel (reference path),
#    kernel_fused, numba_cuda (full geometry) and numba_cuda_lean (the lean loop); one JSON and its plot.
# 2. env_throughput.py: env-steps/s of the default ReturnBall task at 65,536 and 262,144 environments
#    (262,144 was its best batch on an H100: 20.5 M env-steps/s at 61ba2cf, 14.8 M at be0ffe5).
# 3. ttsim train ppo on the default config for 40 s (checked after each chunk, compilation included):
#    env-steps per second of training.
#
# Every step runs under its own `timeout` with its log in OUT, and a step whose imports fail in the
# check before is skipped with the reason in session.log, so one failure does not cost the others. OUT receives at
# most 8 files, flat: session.log, peers.log, peers_gpu.json, peers_gpu.png, env_throughput.log,
# env_throughput_gpu.json, ppo.log, ppo_metrics.json. The time limits add up to 580 s, inside a lent
# machine's 600 s per command, and that is not enough for all three: on an H100 at be0ffe5 the
# reference kernel compiled in 56 s and the fused path in 34 s per batch, the environment's step in
# 65-75 s per batch and PPO's update in more than a minute, so every step hit its limit. Give each
# step a call of its own on the same warm machine: GPU_SESSION_STEPS picks them (default
# "peers env ppo"), e.g. GPU_SESSION_STEPS=env OUT=... bash benchmarks/gpu_session.sh.
#
# The package is used from this checkout (PYTHONPATH), nothing is installed. Pure-Python packages the
# machine's interpreter lacks (gymnasium and jaxopt were missing on a lent H100) are taken from
# .gpu_deps/ when it exists (gitignored; fill it on a machine that has them and carry it along):
#   for m in gymnasium farama_notifications cloudpickle jaxopt; do
#       cp -r "$(python -c "import $m, os; print(os.path.dirname($m.__file__))")" .gpu_deps/; done PYTHON picks the
# interpreter (default /opt/torch/.venv/bin/python3 where it exists, else python3).
# GPU_SESSION_QUICK=1 shrinks every size, for a dry run on a CPU (the CUDA peers are skipped there).
set -u
cd "$(dirname "$0")/.."
: "${OUT:?set OUT to the folder for the results}"
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
[ -d "$PWD/.gpu_deps" ] && export PYTHONPATH="$PYTHONPATH:$PWD/.gpu_deps"
PY="${PYTHON:-}"
if [ -z "$PY" ]; then
    if [ -x /opt/torch/.venv/bin/python3 ]; then PY=/opt/torch/.venv/bin/python3; else PY=python3; fi
fi
LOG="$OUT/session.log"

if [ "${GPU_SESSION_QUICK:-0}" = 1 ]; then
    PEERS_ARGS=(--batches 256,1024 --budget 2e4 --repeats 1 --agree-balls 64 --max-batch-numba 1024)
    ENV_ARGS=(--envs 64 --steps 5 --repeats 1)
    PPO_SECONDS=10
    T_CHECK=120 T_PEERS=600 T_ENV=300 T_PPO=600
else
    # the GPU peers only (the numba CPU loops and the plain scan add minutes of compilation and
    # nothing to the GPU's ratios); 65,536 balls was neither side's best batch on an H100 before
    PEERS_ARGS=(--batches 262144,1048576 --budget 2e8 --repeats 3 --max-batch-numba 0 --max-batch-plain 0
                --agree-balls 64)
    ENV_ARGS=(--envs 65536 262144 --steps 50 --repeats 3)
    PPO_SECONDS=40
    T_CHECK=30 T_PEERS=250 T_ENV=170 T_PPO=130
fi

say() { echo "[$(date +%T)] $*" | tee -a "$LOG"; }

# step NAME LIMIT_S LOGFILE CMD...: runs CMD under `timeout`, its output in LOGFILE; notes the outcome
step() {
    local name=$1 limit=$2 log=$3
    shift 3
    say "$name: start (limit ${limit} s): $*"
    local t0=$SECONDS
    timeout --kill-after=10 "$limit" "$@" >"$log" 2>&1
    local rc=$?
    local how="ok"
    [ $rc -eq 124 ] || [ $rc -eq 137 ] && how="TIMED OUT"
    [ $rc -ne 0 ] && [ "$how" = ok ] && how="FAILED (exit $rc)"
    say "$name: $how after $((SECONDS - t0)) s; last lines of $(basename "$log"):"
    tail -n 25 "$log" | sed 's/^/    /' | tee -a "$LOG" >/dev/null
}

say "gpu_session.sh: python $PY, quick=${GPU_SESSION_QUICK:-0}, $(nproc) CPUs, $(uptime)"
git log -1 --format='commit %H %s' 2>/dev/null | tee -a "$LOG" >/dev/null
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 | tee -a "$LOG" >/dev/null

# Which steps can run: each step's imports, tried apart (a missing optional package skips only its step).
timeout "$T_CHECK" "$PY" - >>"$LOG" 2>&1 <<'EOF'
import importlib
import platform

print("python", platform.python_version())
for name in ("jax", "jaxlib", "flax", "optax", "jaxopt", "numpy", "numba", "gymnasium", "pyarrow", "h5py",
             "matplotlib", "tqdm"):
    try:
        mod = importlib.import_module(name)
        print(f"  {name} {getattr(mod, '__version__', '?')}")
    except Exception as e:
        print(f"  {name} MISSING ({type(e).__name__}: {e})")
try:
    import jax

    print("jax backend", jax.default_backend(), "devices", jax.devices())
except Exception as e:
    print("jax devices: FAILED", type(e).__name__, e)
try:
    from numba import cuda

    print("numba sees a CUDA GPU:", cuda.is_available())
except Exception as e:
    print("numba.cuda: FAILED", type(e).__name__, e)
for step, modules in (("peers", ("benchmarks.peers",)), ("env", ("benchmarks.env_throughput",)),
                      ("ppo", ("optax", "gymnasium", "ttsim_jax.cli"))):
    try:
        for m in modules:
            importlib.import_module(m)
        print(f"STEP_OK {step}")
    except Exception as e:
        print(f"STEP_SKIP {step}: cannot import ({type(e).__name__}: {e})")
EOF
say "import check: exit $?"
# a step is skipped only where the check found it cannot import (a check cut short skips nothing)
STEPS=" ${GPU_SESSION_STEPS:-peers env ppo} "
ok() { [[ "$STEPS" == *" $1 "* ]] && ! grep -q "^STEP_SKIP $1:" "$LOG"; }

if ok peers; then
    step peers "$T_PEERS" "$OUT/peers.log" "$PY" benchmarks/peers.py --configs table "${PEERS_ARGS[@]}" \
        --out "$OUT/peers_gpu.json" --plot "$OUT/peers_gpu.png"
else
    say "peers: skipped (not in GPU_SESSION_STEPS, or see the import check above)"
fi

if ok env; then
    step env_throughput "$T_ENV" "$OUT/env_throughput.log" "$PY" benchmarks/env_throughput.py "${ENV_ARGS[@]}" \
        --out "$OUT/env_throughput_gpu.json"
else
    say "env_throughput: skipped (not in GPU_SESSION_STEPS, or see the import check above)"
fi

if ok ppo; then
    run_dir="$(mktemp -d)"
    step ppo "$T_PPO" "$OUT/ppo.log" "$PY" -m ttsim_jax.cli train ppo --out "$run_dir/ppo" --time-limit "$PPO_SECONDS"
    if [ -f "$run_dir/ppo/metrics.json" ]; then cp "$run_dir/ppo/metrics.json" "$OUT/ppo_metrics.json"; fi
    rm -rf "$run_dir"
else
    say "ppo: skipped (not in GPU_SESSION_STEPS, or see the import check above)"
fi

say "done in $SECONDS s; files: $(cd "$OUT" && ls | tr '\n' ' ')"
