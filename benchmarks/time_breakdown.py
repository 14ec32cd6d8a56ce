"""Where a ball-step's time goes: the rally kernel taken apart, beside the lean hand-written loop.

Flight + table, no rackets, the same shots for every stage (``ttsim_jax.shots.sample_shots``),
conti2026 without effects, float32, dt = 1 ms. Each stage adds one piece to the one before:

- ``numba_lean``: the lean hand loop (``peers_numba``, ``lean=True``): RK4 with the C_D / C_M
  tables, the table as the plane z = r with a linear time of impact, nothing else.
- ``numba_full``: the hand loop with the kernel's full geometry and events (``lean=False``).
- ``xla_flight``: the package's own flight step (``kernel.ball_step.flight``: RK4, the coefficient
  models) as XLA compiles it, ``vmap`` over a block of 1,024 balls inside a ``lax.scan`` over
  steps, blocks one after the other (the kernel's layout); no contact at all, so the balls fall
  through the table: the arithmetic of flight alone.
- ``xla_flags``: the same plus the cheap event tests of every step (``kernel.ball_step.may_have_event``:
  table box swept, sustained contact, floor, net plane, leaving play, validity), counted so that
  they are not optimised away; still no contact handled.
- ``kernel_nolog``: the rally kernel's reference path (``fused=False``) without an event log
  (``Record(max_events=0)``): the flagged balls gathered into buffers, exact time of impact, contacts.
- ``kernel``: the same with the event log (``Record(max_events=8)``).
- ``kernel_fused``: the default path at this size (``fused="auto"``: the flight kernel's body as
  plain XLA over the batch on a CPU).

Besides the times, XLA's own cost analysis of one step of ``xla_flight`` and ``xla_flags`` gives the
floating-point operations and the bytes a compiled step reads and writes, per ball.

    python benchmarks/time_breakdown.py --out benchmarks/results/time_breakdown_cpu.json
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax import Execution, Record, init_state, load_model, rollout
from ttsim_jax.kernel import ball_step as kstep
from ttsim_jax.policies import tracking_rackets
from ttsim_jax.shots import sample_shots
from ttsim_jax.state import Ball

from report_json import emit  # the scripts' folder is on sys.path when run as a script

BLOCK = 1024


def xla_stage(model, with_flags: bool):
    """A jitted (balls (B, 9) blocked as (n_blocks, BLOCK, ...), n_steps) -> (balls, flagged count)."""
    dt = jnp.float32(1e-3)

    def block(ball):
        def body(carry, k):
            ball, count = carry
            t = k.astype(jnp.float32) * dt
            free = jax.vmap(kstep.flight, in_axes=(None, 0, None, None))(model, ball, t, dt)
            if with_flags:
                flag = jax.vmap(kstep.may_have_event, in_axes=(None, 0, 0, None, None))(model, ball, free, None, dt)
                count = count + jnp.sum(flag)
            return (free, count), None

        return body

    def run(balls, n_steps: int):
        def one(ball):
            (ball, count), _ = jax.lax.scan(block(ball), (ball, jnp.int32(0)), jnp.arange(n_steps))
            return ball, count

        return jax.lax.map(one, balls)

    return jax.jit(run, static_argnums=1)


def one_step_cost(model, with_flags: bool, batch: int = BLOCK) -> dict:
    """XLA's cost analysis of one step of ``batch`` balls, per ball."""
    dt = jnp.float32(1e-3)

    def step(ball):
        free = jax.vmap(kstep.flight, in_axes=(None, 0, None, None))(model, ball, jnp.float32(0.0), dt)
        if not with_flags:
            return free
        return free, jax.vmap(kstep.may_have_event, in_axes=(None, 0, 0, None, None))(model, ball, free, None, dt)

    z = jnp.zeros((batch, 3), jnp.float32)
    cost = jax.jit(step).lower(Ball(z, z, z)).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return {k: float(cost.get(k, float("nan"))) / batch for k in ("flops", "transcendentals", "bytes accessed")}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", type=int, default=65536, help="balls (default: %(default)s; a multiple of 1,024)")
    p.add_argument("--steps", type=int, default=300, help="steps per timed run (default: %(default)s)")
    p.add_argument("--repeats", type=int, default=5, help="timed runs per stage, interleaved (default: %(default)s)")
    p.add_argument("--out", type=Path, default=None, help="write the JSON here (default: print only)")
    args = p.parse_args(argv)
    if args.batch % BLOCK:
        p.error(f"--batch must be a multiple of {BLOCK}")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import peers_numba  # noqa: E402 (numba is optional for the package, needed here)

    model = load_model("conti2026", dtype=jnp.float32)
    shots, _ = sample_shots(args.batch, seed=0)
    balls = Ball(*(jnp.asarray(a, jnp.float32) for a in (shots.pos, shots.vel, shots.spin)))
    host = Ball(*(np.asarray(a, np.float32) for a in (shots.pos, shots.vel, shots.spin)))
    params = peers_numba.pack_params(model, tracking_rackets().params)
    blocked = jax.tree.map(lambda a: a.reshape(-1, BLOCK, 3), balls)
    n = args.steps
    flight, flags = xla_stage(model, False), xla_stage(model, True)

    def kernel(max_events, fused):
        def run():
            state, out = rollout(model, init_state(balls), n, 1e-3, record=Record(max_events=max_events),
                                 execution=Execution(fused=fused))
            return state.ball.pos
        return run

    stages = {
        "numba_lean": lambda: peers_numba.rollout_cpu(params, host, n, 1e-3, False, lean=True),
        "numba_full": lambda: peers_numba.rollout_cpu(params, host, n, 1e-3, False, lean=False),
        "xla_flight": lambda: flight(blocked, n)[0].pos,
        "xla_flags": lambda: flags(blocked, n)[1],
        "kernel_nolog": kernel(0, False),
        "kernel": kernel(8, False),
        "kernel_fused": kernel(8, "auto"),
    }
    first = {}
    for name, run in stages.items():
        t0 = time.perf_counter()
        jax.block_until_ready(run())
        first[name] = time.perf_counter() - t0
        print(f"{name:13s} first call (compiles) {first[name]:6.1f} s", flush=True)
    times = {name: [] for name in stages}
    for _ in range(args.repeats):
        for name, run in stages.items():
            t0 = time.perf_counter()
            jax.block_until_ready(run())
            times[name].append(time.perf_counter() - t0)
    lean = statistics.median(times["numba_lean"])
    rows = {}
    for name in stages:
        med = statistics.median(times[name])
        rows[name] = dict(median_s=med, run_s=times[name], ball_steps_per_s=args.batch * n / med,
                          ns_per_ball_step=1e9 * med / (args.batch * n), of_lean=lean / med)
        print(f"{name:13s} {rows[name]['ball_steps_per_s'] / 1e6:7.2f} M ball-steps/s  "
              f"{rows[name]['ns_per_ball_step']:6.1f} ns per ball-step  {rows[name]['of_lean']:.2f} of the lean loop",
              flush=True)
    cost = {"xla_flight": one_step_cost(model, False), "xla_flags": one_step_cost(model, True)}
    for name, c in cost.items():
        print(f"{name:13s} per ball-step: {c['flops']:.0f} flops, {c['transcendentals']:.0f} transcendentals, "
              f"{c['bytes accessed']:.0f} bytes accessed (XLA cost analysis)")
    report = dict(benchmark="time_breakdown", unit="ball-steps/s", batch=args.batch, n_steps=n, dt_s=1e-3,
                  dtype="float32", model="conti2026", rackets=None, repeats=args.repeats, stages=rows,
                  first_call_s=first, xla_cost_per_ball_step=cost, load_average=os.getloadavg(),
                  device=str(jax.devices()[0]), platform=platform.platform(), jax=jax.__version__)
    emit(report, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
