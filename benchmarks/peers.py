"""The rally kernel against its peers: same shots, same physics, ball-steps per second.

Peers, each timed on the same shots (``ttsim_jax.shots.sample_shots``) at dt = 1 ms in float32:

- ``kernel``: the rally kernel (``ttsim_jax.rollout``; called only in :func:`kernel_rollout`).
- ``kernel_fused``: the same with ``fused=True`` (``ttsim_jax.kernel.fused``: a kernel flies the
  balls many steps per launch); a Pallas kernel compiled by Triton on a GPU, its body as plain XLA
  over the whole batch on a CPU. With the tracking rackets it stops balls at the policy's reach
  (``RacketPolicy.reach``). Where ``fused="auto"`` takes the fused path (flight + table: a GPU; a
  CPU from 1,024 balls; not with a racket policy), ``kernel`` runs it too.
- ``plain_scan``: a straightforward ``lax.scan`` over steps of ``jax.vmap`` of a single-ball step
  calling the project's stages (``aero.flight_step``, ``table.table_contact``,
  ``racket.racket_contact``) with an end-of-step penetration check: no event log, no gathering,
  no time of impact.
- ``numba``: the same physics written by hand, ``@njit(parallel=True)`` with ``prange`` over balls
  (``benchmarks/peers_numba.py``).
- ``numba_cuda``: the same hand-written loop, one CUDA thread per ball (only with a GPU).
- ``numba_lean``, ``numba_cuda_lean``: a lean hand-written loop of flight + table only, as one
  writes it for speed (``peers_numba.make_lean_physics``): the same RK4, tables and bounce, the
  table as the plane z = r with a linear time of impact, the tables read by bracketing; no
  Hermite time of impact, table edges, net or event log. Flight + table only (``table``).
- ``mujoco``: a free sphere (r = 0.02 m, 2.7 g) with MuJoCo's ellipsoid fluid model and a box
  table, flight + table only: similar physics, not the same (``benchmarks/peers_mujoco.py``).
- ``mjx``: the same MuJoCo model under MJX on the JAX device, if it runs.

Three configurations: ``table`` (flight + table, no rackets), ``rackets`` (plus the two tracking
rackets of ``ttsim_jax.policies``, the "updated" racket model; kernel, plain scan and numba) and
``network`` (the same with conti2026's racket residual network evaluated at every racket contact,
untrained, of the bundled size, so of the same cost as a trained one; only the kernel has it, so
only the kernel runs). ``targets`` in the JSON divides the kernel of each
configuration by numba's flight + table of the same run and batch, ``targets_lean`` by the lean
loop's (``kernel_fused``, where it ran, as ``table_fused``).
Before timing, the peers' first table bounces are compared with the kernel's on the same shots:
a benchmark of wrong physics is worthless.

    python benchmarks/peers.py --quick
    python benchmarks/peers.py --batches 1024,4096,16384,65536 --repeats 3

numba and mujoco are the ``bench`` extra: ``pip install -e .[bench]``; a missing one is skipped
with its reason in the JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

REPO = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):  # run as a script: make ``benchmarks`` importable
    sys.path.insert(0, str(REPO))

from ttsim_jax import Execution, Record, init_state, load_model, rollout  # noqa: E402
from ttsim_jax.physics import aero as aero_stage  # noqa: E402
from ttsim_jax.physics import events as ev  # noqa: E402
from ttsim_jax.physics import racket as racket_stage  # noqa: E402
from ttsim_jax.physics import table as table_stage  # noqa: E402
from ttsim_jax.policies import tracking_rackets  # noqa: E402
from ttsim_jax.shots import sample_shots  # noqa: E402
from ttsim_jax.state import Ball  # noqa: E402

DT = 1e-3
MODEL = "conti2026"
CONFIGS = ("table", "rackets", "network")
TITLES = {"table": "flight + table", "rackets": "flight + table + 2 rackets",
          "network": "+ 2 rackets + residual network"}
JAX_PEERS = ("kernel", "kernel_fused", "plain_scan")  # they take the shots as JAX arrays
NUMBA_PEERS = ("numba", "numba_cuda", "numba_lean", "numba_cuda_lean")
DEFAULT_OUT = REPO / "benchmarks" / "results" / "peers_cpu.json"


# --------------------------------------------------------------------------- the kernel
def kernel_rollout(model, balls: Ball, n_steps: int, dt: float, policy, fused: bool = False):
    """The rally kernel on a batch (``init_state`` then ``rollout``); the only place it is called.
    ``fused`` takes the fused flight path.

    Returns:
        (final positions (B, 3), first table bounce (B, 3), NaN where none) as JAX arrays.
    """
    state, out = rollout(model, init_state(balls), n_steps, dt, policy, record=Record(max_events=8),
                         execution=Execution(fused=fused))
    ev_log = out.events
    is_table = ev_log.kind == ev.TABLE
    first = jnp.argmax(is_table, axis=1)
    pos = jnp.take_along_axis(ev_log.pre.pos, first[:, None, None], axis=1)[:, 0]
    return state.ball.pos, jnp.where(jnp.any(is_table, axis=1)[:, None], pos, jnp.nan)


# --------------------------------------------------------------------------- the plain scan
def plain_step(model, ball: Ball, first, rackets, dt):
    """One step of one ball: RK4 flight, then an end-of-step penetration check and bounce.

    Arguments:
        model: a :class:`ttsim_jax.Model`; ball: (3,) fields; rackets: (R, ...) or None.
        first: (4,) the first table bounce so far (x, y, z, found) (diagnostic only: a linear
            interpolation of the step's end points, not used by the physics).

    Returns:
        (ball, first) after the step; a ball below the floor stays where it is.
    """
    r, m = model.ball.radius, model.ball.mass
    p0, v0, w0 = ball.pos, ball.vel, ball.spin
    p1, v1, w1 = aero_stage.flight_step(model.aero, r, m, p0, v0, w0, 0.0, dt)
    g0, g1 = p0[2] - r, p1[2] - r  # the plane of the playing surface
    over = (jnp.abs(p1[0]) <= 0.5 * model.table.length) & (jnp.abs(p1[1]) <= 0.5 * model.table.width)
    on_table = (g1 < 0.0) & (v1[2] < 0.0) & over
    tp, tv, tw = table_stage.table_contact(model.table, r, p1, v1, w1)
    nxt = Ball(*(jnp.where(on_table, a, b) for a, b in zip((tp, tv, tw), (p1, v1, w1))))
    if rackets is not None:
        for j in range(rackets.pos.shape[0]):
            rk = jax.tree.map(lambda a: a[j], rackets)
            rk = rk.replace(pos=rk.pos + dt * rk.vel)  # the racket at the end of the step
            n = rk.rot[:, 0]
            inside = jnp.sum(((rk.rot.T @ (p1 - rk.pos))[1:3] / rk.face) ** 2) <= 1.0
            side = jnp.where(jnp.dot(n, p0 - rk.pos) >= 0.0, 1.0, -1.0)
            hit = (side * jnp.dot(n, p1 - rk.pos) < r) & (side * jnp.dot(n, v1 - rk.vel) < 0.0) & inside
            # the face is the one the ball started the step in front of
            rv, rw, _ = racket_stage.racket_contact(model.racket, rk, r, m, p0, v1, w1)
            nxt = Ball(nxt.pos, jnp.where(hit, rv, nxt.vel), jnp.where(hit, rw, nxt.spin))
    stopped = p1[2] - r < model.table.floor_z
    nxt = jax.tree.map(lambda a, b: jnp.where(stopped, b, a), nxt, ball)
    tau = jnp.clip(g0 / jnp.where(g0 != g1, g0 - g1, 1.0), 0.0, 1.0)
    land = jnp.append(p0 + tau * (p1 - p0), 1.0)
    first = jnp.where(on_table & (first[3] == 0.0), land, first)
    return nxt, first


@partial(jax.jit, static_argnames=("n_steps",))
def _plain_rollout(model, balls: Ball, policy, dt, n_steps: int):
    def body(carry, _):
        ball, first, t = carry
        rackets = None
        if policy is not None:
            rackets = jax.vmap(policy.fn, in_axes=(None, 0, None))(policy.params, ball, t)
        step = jax.vmap(plain_step, in_axes=(None, 0, 0, None if rackets is None else 0, None))
        ball, first = step(model, ball, first, rackets, dt)
        return (ball, first, t + dt), None

    first = jnp.zeros((balls.pos.shape[0], 4), balls.pos.dtype)
    (ball, first, _), _ = jax.lax.scan(body, (balls, first, jnp.zeros((), balls.pos.dtype)), None, length=n_steps)
    return ball.pos, jnp.where(first[:, 3:] > 0.0, first[:, :3], jnp.nan)


def plain_rollout(model, balls: Ball, n_steps: int, dt: float, policy):
    """The plain scan on a batch: (final positions (B, 3), first table bounce (B, 3), NaN where none)."""
    return _plain_rollout(model, balls, policy, jnp.asarray(dt, balls.pos.dtype), n_steps)


# --------------------------------------------------------------------------- peers
def _optional(name):
    """(module, None) or (None, reason) for an optional peer module."""
    try:
        if name == "numba":
            from benchmarks import peers_numba as mod
        else:
            from benchmarks import peers_mujoco as mod
        return mod, None
    except ImportError as e:
        return None, f"{name} not installed ({e}); pip install -e .[bench]"


class Peers:
    """The runnable peers of one configuration: name -> (prepare(shots), run(prepared), compile_s)."""

    def __init__(self, model, config: str, mujoco_chunk: int, try_mjx: bool, log=print):
        self.skipped: dict[str, str] = {}
        if config == "network":
            from ttsim_jax.fit.network_config import load_residual_config
            from ttsim_jax.physics.network import init_model

            net = init_model(load_residual_config(REPO / "configs" / "residual" / f"{MODEL}.toml"), jax.random.PRNGKey(0))
            model = load_model(MODEL, dtype=jnp.float32, residual=net)
            self.skipped["plain_scan"] = "no residual network in the plain scan"
            for n in NUMBA_PEERS:
                self.skipped[n] = "no residual network in the numba loops"
        self.model, self.config = model, config
        self.policy = tracking_rackets() if config != "table" else None
        self.runs: dict = {}
        self.compile_s: dict[str, float] = {}
        self.runs["kernel"] = lambda b, n: kernel_rollout(model, b, n, DT, self.policy)
        self.runs["kernel_fused"] = lambda b, n: kernel_rollout(model, b, n, DT, self.policy, fused=True)
        if jax.default_backend() == "gpu":  # a Triton compilation that fails is recorded, not fatal
            try:
                jax.block_until_ready(self.runs["kernel_fused"](_shots(8)[0], 2))
            except Exception as e:
                del self.runs["kernel_fused"]
                self.skipped["kernel_fused"] = f"{type(e).__name__}: {str(e)[:300]}"
        if "plain_scan" not in self.skipped:
            self.runs["plain_scan"] = lambda b, n: plain_rollout(model, b, n, DT, self.policy)
        numba_mod, why = (None, None) if "numba" in self.skipped else _optional("numba")
        if why:
            for n in NUMBA_PEERS:
                self.skipped[n] = why
        elif numba_mod is not None:
            params = numba_mod.pack_params(model, tracking_rackets().params)
            on = self.policy is not None
            cuda = numba_mod.cuda_available()
            self.runs["numba"] = lambda b, n: numba_mod.rollout_cpu(params, b, n, DT, on)[::2]
            if cuda:
                self.runs["numba_cuda"] = lambda b, n: numba_mod.rollout_cuda(params, b, n, DT, on)[::2]
            if on:
                self.skipped["numba_lean"] = self.skipped["numba_cuda_lean"] = "flight + table only (no rackets)"
            else:
                self.runs["numba_lean"] = lambda b, n: numba_mod.rollout_cpu(params, b, n, DT, False, lean=True)[::2]
                if cuda:
                    self.runs["numba_cuda_lean"] = \
                        lambda b, n: numba_mod.rollout_cuda(params, b, n, DT, False, lean=True)[::2]
            for n in ("numba_cuda", "numba_cuda_lean"):
                if n not in self.runs:
                    self.skipped.setdefault(n, "no CUDA GPU visible to numba")
        if config != "table":
            self.skipped["mujoco"] = self.skipped["mjx"] = "flight + table only (no rackets)"
            return
        mj, why = _optional("mujoco")
        if mj is None:
            self.skipped["mujoco"] = self.skipped["mjx"] = why
            return
        peer = mj.MujocoPeer(chunk=mujoco_chunk)
        self.runs["mujoco"] = lambda b, n: peer.rollout(b, n)
        self.mujoco_peer = peer
        if not try_mjx:
            self.skipped["mjx"] = "not run: opt in with --mjx (on CPU it compiles for minutes and is far slower "\
                                  "than MuJoCo; see benchmarks/README.md)"
            return
        try:
            fn = mj.mjx_rollout_fn(1)
            quat = np.array([1.0, 0.0, 0.0, 0.0])

            def run_mjx(b, n):
                qpos = jnp.concatenate([jnp.asarray(b.pos), jnp.broadcast_to(quat, (b.pos.shape[0], 4))], -1)
                qvel = jnp.concatenate([jnp.asarray(b.vel), jnp.asarray(b.spin)], -1)
                return fn(qpos, qvel, n)

            t0 = time.perf_counter()
            jax.block_until_ready(run_mjx(_shots(4)[0], 2))
            log(f"  mjx runs (test compile {time.perf_counter() - t0:.1f} s)")
            self.runs["mjx"] = run_mjx
        except Exception as e:  # MJX refusing the model (fluid model, version) is recorded, not fatal
            self.skipped["mjx"] = f"{type(e).__name__}: {str(e)[:300]}"


def _shots(batch: int, seed: int = 0):
    """(JAX Ball, numpy shots) of ``batch`` sampled shots."""
    shots, _ = sample_shots(batch, seed=seed)
    return Ball(*(jnp.asarray(a) for a in (shots.pos, shots.vel, shots.spin))), shots


def _call(run, balls, n_steps):
    t0 = time.perf_counter()
    jax.block_until_ready(run(balls, n_steps))
    return time.perf_counter() - t0


# --------------------------------------------------------------------------- agreement
def agreement(peers: Peers, n_balls: int, n_steps: int, seed: int = 12345) -> dict:
    """First-table-bounce disagreement of each peer with the kernel on the same shots [m].

    Returns:
        dict peer -> {median_m, max_m, p90_m, compared, kernel_bounces, peer_bounces}.
    """
    balls, shots = _shots(n_balls, seed)
    _, k_first = (np.asarray(a) for a in peers.runs["kernel"](balls, n_steps))
    out = {}
    for name, run in peers.runs.items():
        if name == "kernel":
            continue
        if name == "mujoco":
            _, first = peers.mujoco_peer.rollout(shots, n_steps, track_bounce=True)
        elif name == "mjx":  # final state only: compared with MuJoCo on a few shots (it is slow)
            m_balls, m_shots = _shots(64, seed)
            mj_final, _ = peers.mujoco_peer.rollout(m_shots, 300)
            d = np.linalg.norm(np.asarray(run(m_balls, 300))[:, :3] - mj_final, axis=-1)
            out[name] = dict(against="mujoco", what="final position after 300 steps, 64 shots",
                             median_m=float(np.median(d)), max_m=float(np.max(d)), compared=64)
            continue
        else:
            _, first = run(balls if name in JAX_PEERS else shots, n_steps)
        first = np.asarray(first, np.float64)
        both = np.isfinite(first[:, 0]) & np.isfinite(k_first[:, 0])
        d = np.linalg.norm(first[both] - k_first[both], axis=-1)
        out[name] = dict(median_m=float(np.median(d)) if d.size else None, max_m=float(np.max(d)) if d.size else None,
                         p90_m=float(np.quantile(d, 0.9)) if d.size else None, compared=int(both.sum()),
                         kernel_bounces=int(np.isfinite(k_first[:, 0]).sum()),
                         peer_bounces=int(np.isfinite(first[:, 0]).sum()))
    return out


# --------------------------------------------------------------------------- timing
def steps_for(batch: int, budget: float, lo: int = 100, hi: int = 1000) -> int:
    """Steps per run so that a run is about ``budget`` ball-steps, within [lo, hi]."""
    return int(min(hi, max(lo, budget // batch)))


def time_batch(peers: Peers, batch: int, n_steps: int, repeats: int, max_batch: dict, log=print) -> dict:
    """Median ball-steps/s of every peer on one batch; repeats interleaved across peers.

    The first call of each peer compiles (JAX) or is a warm-up; its excess over the median is
    reported as ``compile_s`` (numba's compilation is timed apart, see :func:`compile_numba`).
    """
    balls, shots = _shots(batch, seed=batch)
    names = [n for n in peers.runs if batch <= max_batch.get(n, batch)]
    arg = {n: balls if n in JAX_PEERS + ("mjx",) else shots for n in names}
    first = {n: _call(peers.runs[n], arg[n], n_steps) for n in names}
    times = {n: [] for n in names}
    for r in range(repeats):
        for n in names:
            times[n].append(_call(peers.runs[n], arg[n], n_steps))
        log(f"    batch {batch}: repeat {r + 1}/{repeats} done")
    out = {}
    for n in names:
        med = statistics.median(times[n])
        out[n] = dict(ball_steps_per_s=batch * n_steps / med, median_s=med, run_s=times[n],
                      first_call_s=first[n], compile_s=max(0.0, first[n] - med))
    for n in peers.runs:
        if n not in names:
            flag = {"kernel_fused": "fused", "plain_scan": "plain", "numba_lean": "numba"}.get(n, n)
            out[n] = dict(skipped=f"batch above --max-batch-{flag} ({max_batch[n]})")
    return out


def compile_numba(peers: Peers) -> dict:
    """Seconds of numba's first call (compilation) on one ball and one step, per numba peer."""
    out = {}
    _, shots = _shots(1)
    for n in NUMBA_PEERS:
        if n in peers.runs:
            out[n] = _call(peers.runs[n], shots, 1)
    return out


def plot(report: dict, path: Path) -> None:
    """Log-log throughput against batch size, one panel per configuration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    configs = list(report["configs"])
    colours = {n: f"C{i}" for i, n in enumerate(("kernel", "plain_scan", "numba", "numba_cuda", "mujoco", "mjx",
                                                  "kernel_fused", "numba_lean", "numba_cuda_lean"))}
    fig, axes = plt.subplots(1, len(configs), figsize=(6 * len(configs), 4.5), squeeze=False)
    for ax, cfg in zip(axes[0], configs):
        rows = report["configs"][cfg]["results"]
        names = sorted({n for row in rows for n, r in row["peers"].items() if "ball_steps_per_s" in r})
        for n in names:
            pts = [(row["batch"], row["peers"][n]["ball_steps_per_s"]) for row in rows
                   if "ball_steps_per_s" in row["peers"].get(n, {})]
            ax.plot(*zip(*pts), marker="o", color=colours.get(n), label=n + (" (similar physics)" if n in ("mujoco", "mjx") else ""))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks([row["batch"] for row in rows], [f"{row['batch']:,}" for row in rows])
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        ax.set_xlabel("batch (balls)")
        ax.set_ylabel("ball-steps / s")
        ax.set_title(f"{cfg}: {TITLES[cfg]}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"conti2026, RK4, dt = 1 ms, float32; {report['device']}", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def targets(report: dict, base_peer: str = "numba") -> list[dict]:
    """Per batch: each configuration's kernel throughput over ``base_peer``'s flight + table in the
    same run (the ratios the kernel is held to: >= 0.5 for ``table``, >= 0.35 for ``network``); the
    fused kernel's, where it ran, as ``table_fused``."""
    rows = {}
    base = {r["batch"]: r["peers"].get(base_peer, {}).get("ball_steps_per_s")
            for r in report["configs"].get("table", {}).get("results", [])}
    for cfg, c in report["configs"].items():
        for r in c["results"]:
            n = base.get(r["batch"])
            for peer, key in (("kernel", cfg), ("kernel_fused", f"{cfg}_fused")):
                k = r["peers"].get(peer, {}).get("ball_steps_per_s")
                if k and n:
                    rows.setdefault(r["batch"], {"batch": r["batch"]})[key] = k / n
    return [rows[b] for b in sorted(rows)]


def write_report(report: dict, path: Path, complete: bool) -> None:
    """Writes ``report`` with its ``targets`` to ``path`` (JSON); ``complete``: False while batches remain
    (what a run cut short leaves)."""
    report["complete"] = complete
    report["targets"] = targets(report)
    report["targets_lean"] = targets(report, "numba_lean")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2))


def _versions() -> dict:
    out = dict(python=platform.python_version(), jax=jax.__version__, numpy=np.__version__)
    for name in ("numba", "mujoco"):
        mod, _ = _optional(name)
        out[name] = mod.VERSION if mod else None
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batches", default="1024,4096,16384,65536",
                   help="comma-separated batch sizes (default: %(default)s)")
    p.add_argument("--configs", default="table,rackets,network",
                   help="comma-separated configurations: table (flight + table), rackets (plus two tracking "
                        "rackets), network (rackets plus the racket residual network; the kernel only) "
                        "(default: %(default)s)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per peer and batch; the median is kept "
                   "(default: %(default)s)")
    p.add_argument("--budget", type=float, default=4e6,
                   help="ball-steps per timed run, sets the steps per batch within [100, 1000] (default: %(default)g)")
    p.add_argument("--max-batch-mujoco", type=int, default=4096,
                   help="largest batch MuJoCo runs (it is far slower) (default: %(default)s)")
    p.add_argument("--max-batch-plain", type=int, default=1 << 30,
                   help="largest batch the plain scan runs (default: no limit)")
    p.add_argument("--max-batch-numba", type=int, default=1 << 30,
                   help="largest batch the numba CPU loops (numba, numba_lean) run (default: no limit)")
    p.add_argument("--max-batch-fused", type=int, default=1 << 30,
                   help="largest batch the fused kernel runs (default: no limit)")
    p.add_argument("--mujoco-chunk", type=int, default=64, help="balls per MuJoCo model (default: %(default)s)")
    p.add_argument("--mjx", action="store_true",
                   help="also run MJX (slow to compile and run on CPU; batches up to --max-batch-mjx)")
    p.add_argument("--max-batch-mjx", type=int, default=256, help="largest batch MJX runs (default: %(default)s)")
    p.add_argument("--agree-balls", type=int, default=512,
                   help="shots in the agreement check of first bounces (default: %(default)s)")
    p.add_argument("--quick", action="store_true",
                   help="a short run: batches 256,1024,4096, budget 1e6, MuJoCo up to 1024 balls, 256 agreement shots")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON output (default: benchmarks/results/peers_cpu.json)")
    p.add_argument("--plot", type=Path, default=None,
                   help="PNG of throughput against batch (default: the --out path with .png)")
    args = p.parse_args(argv)
    if args.quick:
        args.batches, args.budget, args.max_batch_mujoco, args.agree_balls = "256,1024,4096", 1e6, 1024, 256
    batches = [int(b) for b in args.batches.split(",")]
    configs = [c for c in args.configs.split(",")]
    bad = set(configs) - set(CONFIGS)
    if bad:
        p.error(f"--configs: unknown {sorted(bad)}; known: {list(CONFIGS)}")
    model = load_model(MODEL, dtype=jnp.float32)
    gpu = jax.default_backend() == "gpu"
    device = str(jax.devices()[0])
    report = dict(benchmark="rally_kernel_peers", unit="ball-steps/s (batch x steps / seconds)", model=MODEL,
                  dt_s=DT, integrator="rk4", dtype="float32", device=device,
                  device_kind=jax.devices()[0].device_kind, platform=platform.platform(),
                  cpu_count=__import__("os").cpu_count(), versions=_versions(), repeats=args.repeats,
                  budget=args.budget, quick=args.quick,
                  fused_kernel="pallas, triton (compiled)" if gpu else "the kernel's body as plain XLA over the batch",
                  notes=["mujoco/mjx: similar physics, not the same (MuJoCo's ellipsoid fluid model and soft "
                         "contact, float64; flight + table only)",
                         "plain_scan: end-of-step contact check, no time of impact; its first bounce is the "
                         "linear interpolation of the step's end points (diagnostic only)",
                         "numba: dead balls (floor, out, rest) stop their loop; the kernel and the plain scan "
                         "step every ball for every step (branch-free)",
                         "numba_lean, numba_cuda_lean: flight + table only, the table as the plane z = r with a "
                         "linear time of impact, the coefficient tables read by bracketing; no Hermite time of "
                         "impact, table edges, net or event log"],
                  configs={})
    for cfg in configs:
        print(f"[{cfg}] setting up peers", flush=True)
        peers = Peers(model, cfg, args.mujoco_chunk, args.mjx and cfg == "table",
                      log=lambda s: print(s, flush=True))
        for n, why in peers.skipped.items():
            print(f"  {n}: skipped ({why})", flush=True)
        numba_compile = compile_numba(peers)
        print(f"  agreement of first bounces on {args.agree_balls} shots", flush=True)
        agree = agreement(peers, args.agree_balls, 1000)
        for n, a in agree.items():
            if a["median_m"] is not None:
                print(f"    {n:15s} median {a['median_m'] * 1e3:9.4f} mm  max {a['max_m'] * 1e3:9.4f} mm "
                      f"({a['compared']} compared{', against ' + a['against'] if 'against' in a else ''})", flush=True)
        max_batch = {"mujoco": args.max_batch_mujoco, "plain_scan": args.max_batch_plain, "mjx": args.max_batch_mjx,
                     "kernel_fused": args.max_batch_fused, "numba": args.max_batch_numba,
                     "numba_lean": args.max_batch_numba}
        rows = []
        report["configs"][cfg] = dict(
            rackets="tracking_rackets() (2, ttsim_jax.policies), updated racket model" if cfg != "table" else None,
            residual_network=f"configs/residual/{MODEL}.toml, untrained (PRNGKey(0))" if cfg == "network" else None,
            skipped=peers.skipped, numba_compile_s=numba_compile, agreement_first_bounce=agree, results=rows)
        for batch in batches:
            n_steps = steps_for(batch, args.budget)
            print(f"  batch {batch} x {n_steps} steps", flush=True)
            res = time_batch(peers, batch, n_steps, args.repeats, max_batch, log=lambda s: print(s, flush=True))
            kernel = res["kernel"]["ball_steps_per_s"]
            for n, r in res.items():
                if "ball_steps_per_s" in r:
                    r["ratio_to_kernel"] = r["ball_steps_per_s"] / kernel
                    print(f"    {n:15s} {r['ball_steps_per_s']:14,.0f} ball-steps/s  x{r['ratio_to_kernel']:.3f} "
                          f"of kernel (compile/warm-up {r['compile_s']:.1f} s)", flush=True)
            rows.append(dict(batch=batch, n_steps=n_steps, peers=res))
            write_report(report, args.out, complete=False)  # a run cut short keeps what it measured
    write_report(report, args.out, complete=True)
    for key, base in (("targets", "numba"), ("targets_lean", "numba_lean")):
        for row in report[key]:
            print(f"  batch {row['batch']}: kernel / {base} flight + table: "
                  + ", ".join(f"{k} {v:.3f}" for k, v in row.items() if k != "batch"), flush=True)
    print(f"written {args.out}")
    png = args.plot or args.out.with_suffix(".png")
    plot(report, png)
    print(f"written {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
