"""Memory and compile time of the rally kernel.

Reports, in JSON:

* bytes per ball of the rally state, of one event-log slot and of one recorded step;
* the kernel's working memory per ball for a forward rollout (XLA's own buffer assignment of the
  compiled program: arguments, outputs and temporaries), hence the largest batch per GiB, of the
  reference path and of the fused path;
* the memory of a reverse-mode gradient of a landing point over 1,000 steps for 1,024 balls, with
  rematerialisation on (the default) and off;
* first-call compile time of each model family with two rackets.

Memory figures come from ``compiled.memory_analysis()``: they are what XLA allocates for the
program, measured without running it.

    python benchmarks/kernel_memory.py --out benchmarks/results/kernel_memory.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax import Execution, Record, init_state, load_model, rollout
from ttsim_jax.kernel.eventlog import EventLog
from ttsim_jax.kernel.rollout import _rollout
from ttsim_jax.policies import tracking_rackets
from ttsim_jax.shots import sample_shots

REPO = Path(__file__).resolve().parents[1]


def nbytes(tree) -> int:
    return int(sum(np.prod(x.shape) * x.dtype.itemsize for x in jax.tree.leaves(tree)))


def shots(n, dtype):
    balls, _ = sample_shots(n, seed=0)
    return jax.tree.map(lambda a: jnp.asarray(a, dtype), balls)


def program_bytes(compiled) -> dict:
    m = compiled.memory_analysis()
    fields = ("argument_size_in_bytes", "output_size_in_bytes", "temp_size_in_bytes", "alias_size_in_bytes")
    out = {f: int(getattr(m, f)) for f in fields}
    out["total_bytes"] = out["argument_size_in_bytes"] + out["output_size_in_bytes"] + out["temp_size_in_bytes"] \
        - out["alias_size_in_bytes"]
    return out


def forward_bytes(model, batch, n_steps, dtype, fused=False):
    """The program of a forward rollout: the reference path (``fused=False``) or the fused one."""
    state = init_state(shots(batch, dtype))
    lowered = jax.jit(lambda m, s: rollout(m, s, n_steps, 1e-3, record=Record(max_events=8),
                                           execution=Execution(fused=fused))).lower(model, state)
    return program_bytes(lowered.compile())


def gradient_bytes(model, batch, n_steps, dtype, remat):
    balls = shots(batch, dtype)

    def landing_x(m):
        s, out = rollout(m, init_state(balls), n_steps, 1e-3, record=Record(max_events=2),
                         execution=Execution(remat=remat))
        return jnp.sum(jnp.where(out.events.count > 0, out.events.pre.pos[:, 0, 0], 0.0))

    lowered = jax.jit(jax.grad(landing_x)).lower(model)
    return program_bytes(lowered.compile())


def compile_seconds(name, dtype, batch=1024, n_steps=1000):
    """First call minus second call of a two-racket rollout, in wall and in process CPU seconds.

    CPU time is the steadier figure on a shared machine (load stretches wall time, not CPU
    time); wall time is what a user waits for on an idle one.
    """
    model = load_model(name, dtype=dtype)
    balls = shots(batch, dtype)
    policy = jax.tree.map(lambda a: jnp.asarray(a, dtype), tracking_rackets())
    _rollout.clear_cache()
    times = []
    for _ in range(2):
        t0, c0 = time.perf_counter(), time.process_time()
        s, _ = rollout(model, init_state(balls), n_steps, 1e-3, policy)
        jax.block_until_ready(s.ball.pos)
        times.append((time.perf_counter() - t0, time.process_time() - c0))
    return {"wall_s": times[0][0] - times[1][0], "cpu_s": times[0][1] - times[1][1]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=REPO / "benchmarks/results/kernel_memory.json",
                   help="JSON file to write (default: %(default)s)")
    p.add_argument("--skip-compile", action="store_true", help="leave out the compile-time measurements")
    args = p.parse_args(argv)
    dtype = jnp.float32
    model = load_model("conti2026", dtype=dtype)
    b = 1024
    state = init_state(shots(b, dtype))
    per_ball = {
        "state": nbytes(state.replace(step=jnp.zeros(()), t0=jnp.zeros(()), dt=jnp.zeros(()))) // b,
        "event_slot": nbytes(EventLog.empty(b, 1, dtype).replace(count=jnp.zeros(()))) // b,
        "recorded_step": 9 * np.dtype(dtype).itemsize,
    }
    print("bytes per ball:", per_ball, flush=True)
    fwd = {str(n): forward_bytes(model, n, 1000, dtype) for n in (4096, 65536)}
    slope = (fwd["65536"]["total_bytes"] - fwd["4096"]["total_bytes"]) / (65536 - 4096)
    print("forward program bytes:", fwd, f"-> {slope:.0f} bytes per ball", flush=True)
    # the fused path ("auto" takes it from 1,024 balls on a CPU, always on a GPU)
    fused = {str(n): forward_bytes(model, n, 1000, dtype, fused=True) for n in (4096, 65536)}
    fused_slope = (fused["65536"]["total_bytes"] - fused["4096"]["total_bytes"]) / (65536 - 4096)
    print("fused forward program bytes:", fused, f"-> {fused_slope:.0f} bytes per ball", flush=True)
    grad = {"remat": gradient_bytes(model, b, 1000, dtype, True), "no_remat": gradient_bytes(model, b, 1000, dtype, False)}
    for k, v in grad.items():
        v["bytes_per_ball_step"] = v["total_bytes"] / (b * 1000)
    print("gradient over 1000 steps, 1024 balls:", grad, flush=True)
    compile_s = {}
    if not args.skip_compile:
        for name in ("nakashima2011", "durr2026", "conti2026"):
            compile_s[name] = compile_seconds(name, dtype)
            print(f"first-call compile {name}, two rackets: {compile_s[name]['wall_s']:.1f} s wall, "
                  f"{compile_s[name]['cpu_s']:.1f} s CPU", flush=True)
    result = dict(
        device=str(jax.devices()[0]), platform=platform.platform(), jax=jax.__version__, dtype="float32",
        bytes_per_ball=per_ball, forward_rollout_1000_steps=fwd, forward_bytes_per_ball=slope,
        largest_batch_per_gib=int(2**30 // slope), fused_forward_rollout_1000_steps=fused,
        fused_forward_bytes_per_ball=fused_slope, fused_largest_batch_per_gib=int(2**30 // fused_slope),
        gradient_1000_steps_1024_balls=grad,
        compile_seconds_two_rackets=compile_s)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
