"""Speed of sensitivity Jacobians: the full Jacobian of the landing point of N shots against every
input (all model parameters, ball and racket state) by reverse mode through the rally kernel, and
its ratio to central finite differences over the same inputs (two forward runs of the N shots per
input).

    python benchmarks/sensitivity.py --shots 4096 --out benchmarks/results/sensitivity_cpu.json

The Jacobian is timed twice in one process: the first call compiles (the forward run and one
reverse pass per horizon bucket used: one by default), the second reuses them. Both include the
forward run of every shot at the full horizon that picks the shots that land and groups them by
their landing step (``jacobians.horizon_plan``); each shot stops at its landing and a chunk's
steps after its last landing are skipped. Finite differences are timed on ``--fd-columns`` inputs (each a
batched forward run of all shots at +h and -h, until the last shot stops) and scaled to all
inputs: the cost of a forward run does not depend on which input moved; ``fd_planned_*`` scales
that by the share of shot-steps the Jacobian's plan runs (finite differences over only the landed
shots, in the plan's chunks, each until its last landing: an estimate, not timed). Each phase records wall time and the process's CPU time (all
threads), and the load average at its end: the machine may be shared.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from report_json import emit  # noqa: E402  (the scripts' folder is on sys.path when run as a script)
from ttsim_jax import load_model  # noqa: E402
from ttsim_jax.sensitivity.cases import sampled_shots  # noqa: E402
from ttsim_jax.sensitivity.jacobians import flatten_inputs, horizon_plan, jacobian, layout_of, outcomes  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--shots", type=int, default=4096)
    p.add_argument("--horizon", type=float, default=1.2, help="flight after the contact [s]")
    p.add_argument("--dt", type=float, default=1e-3)
    p.add_argument("--fd-columns", type=int, default=4)
    p.add_argument("--chunk", type=int, default=512,
                   help="shots per compiled Jacobian call, as `ttsim sensitivity --chunk` (0: all at once)")
    p.add_argument("--buckets", type=int, default=1, help="horizon buckets, as `jacobian(buckets=...)`")
    p.add_argument("--repeats", type=int, default=3, help="compiled Jacobian runs; their median is reported")
    p.add_argument("--no-fd", action="store_true", help="time the Jacobian only")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)

    model = load_model("conti2026")
    n_steps = int(round(args.horizon / args.dt))
    t0 = time.perf_counter()
    # the closed-form aim (no aiming through the model): the shots' construction is not what is timed;
    # it ignores drag and the Magnus force, so about 40 % of the shots (most lobs and topspin drives)
    # miss the table (long, wide or into the net) and have no gradient
    shots = sampled_shots(model, args.shots, seed=0, dt=args.dt, aim=False)
    t_shots = time.perf_counter() - t0
    layout = layout_of(model)
    print(f"{args.shots} shots sampled and rackets solved in {t_shots:.1f} s; {layout.n_columns} inputs", flush=True)

    timings = {}

    def timed(name, fn):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        timings[f"{name}_s"] = time.perf_counter() - w0
        timings[f"{name}_cpu_s"] = time.process_time() - c0
        timings[f"{name}_load_average"] = os.getloadavg()[0]
        print(f"{name}: {timings[f'{name}_s']:.1f} s wall, {timings[f'{name}_cpu_s']:.1f} s CPU, "
              f"load average {timings[f'{name}_load_average']:.2f}", flush=True)
        return out

    def run_jacobian():
        return jacobian(model, shots, target="landing", dt=args.dt, n_steps=n_steps, mode="rev",
                        chunk=args.chunk or None, buckets=args.buckets)

    jac = timed("jacobian_first", run_jacobian)
    warm = []
    for i in range(args.repeats):
        jac = timed(f"jacobian_warm{i}", run_jacobian)
        warm.append((timings.pop(f"jacobian_warm{i}_s"), timings.pop(f"jacobian_warm{i}_cpu_s"),
                     timings.pop(f"jacobian_warm{i}_load_average")))
    # the compiled Jacobian: the median of the repeats (each run listed beside it)
    timings["jacobian_second_s"] = float(np.median([w for w, _, _ in warm]))
    timings["jacobian_second_cpu_s"] = float(np.median([c for _, c, _ in warm]))
    timings["jacobian_second_load_average"] = float(np.median([a for _, _, a in warm]))
    timings["jacobian_warm_runs"] = [dict(wall_s=w, cpu_s=c, load_average=a) for w, c, a in warm]
    if args.no_fd:
        print(json.dumps(timings, indent=1))
        return timings

    nominal = flatten_inputs(model, shots, layout)
    h = 1e-3 * np.maximum(np.abs(nominal).mean(0), 1e-3)
    first = timed("forward_first",
                  lambda: outcomes(model, shots, nominal, target="landing", dt=args.dt, n_steps=n_steps))

    def differences():
        fd = []
        for c in range(args.fd_columns):
            step = np.zeros_like(nominal)
            step[:, c] = h[c]
            plus = outcomes(model, shots, nominal + step, target="landing", dt=args.dt, n_steps=n_steps).values
            minus = outcomes(model, shots, nominal - step, target="landing", dt=args.dt, n_steps=n_steps).values
            fd.append((plus - minus) / (2 * h[c]))
        return fd

    fd = timed("fd", differences)
    t_fd = timings["fd_s"]
    per_column = t_fd / args.fd_columns
    fd_all = per_column * layout.n_columns
    ok = jac.valid
    chunk = args.chunk or args.shots
    # shot-steps the Jacobian's plan runs (landed shots in chunks sorted by their last step, each
    # chunk until its last shot stops) against the timed differences' (all shots in one batch,
    # until the last stops)
    steps = np.asarray(first.steps)
    plan = horizon_plan(steps, first.valid, n_steps, chunk, args.buckets)
    planned = sum(chunk * int(steps[rows].max()) for rows, _ in plan)
    share = planned / (args.shots * int(steps.max()))
    fd = np.stack(fd, -1)[ok]
    ad = jac.jac[ok][:, :, :args.fd_columns]
    rel = np.abs(ad - fd) / (np.abs(fd).max((0, 1), keepdims=True) + 1e-9)
    result = dict(
        shots=args.shots, chunk=chunk, landed=int(ok.sum()), inputs=layout.n_columns,
        n_steps=n_steps, dt=args.dt, buckets=args.buckets,
        horizons={str(int(h)): int((jac.horizon == h).sum()) for h in np.unique(jac.horizon[jac.horizon > 0])},
        planned_shot_step_share=share,
        jacobian_first_includes="compilation (forward run + one reverse pass per bucket used) and the forward run",
        jacobian_second_includes="median of --repeats compiled runs, each with the forward run at the full horizon",
        dtype=str(model.ball.radius.dtype), backend=jax.default_backend(), cpus=os.cpu_count(),
        load_average=os.getloadavg()[0], machine=platform.machine(), jax=jax.__version__,
        sampling_s=t_shots, **timings, fd_seconds_per_input=per_column, fd_all_inputs_s=fd_all,
        fd_over_jacobian=fd_all / timings["jacobian_second_s"],
        fd_over_jacobian_cpu=(timings["fd_cpu_s"] / args.fd_columns * layout.n_columns
                              / timings["jacobian_second_cpu_s"]),
        fd_planned_all_inputs_cpu_s=timings["fd_cpu_s"] / args.fd_columns * layout.n_columns * share,
        fd_planned_over_jacobian_cpu=(timings["fd_cpu_s"] / args.fd_columns * layout.n_columns * share
                                      / timings["jacobian_second_cpu_s"]),
        fd_columns_checked=args.fd_columns, fd_vs_jacobian_median_rel_gap=float(np.median(rel)),
    )
    emit(result, args.out)
    return result


if __name__ == "__main__":
    main()
