"""Speed of the aerodynamic identification: the batched fit against scipy's least_squares.

Fits 200 SpinDOE flight segments (those with a measured spin; initial position, initial velocity,
C_D and C_M per segment) twice in one process:

* batched: :func:`ttsim_jax.fit.flightfit.fit_segments`, the vmapped Levenberg-Marquardt solver, one
  compiled call per group of up to 16 segments of similar length; timed from cold (tracing and
  compilation included: the first call of the process) and warm;
* scipy: ``scipy.optimize.least_squares(method="lm")`` per segment over the same residual function
  (:func:`ttsim_jax.fit.flightfit.residual`, jitted, the segment padded to the same capacity) from the
  same start, with the Jacobian either by scipy's finite differences (``jac="2-point"``, the plain
  use; the residual runs in float64 so that the differences mean something) or by the jitted
  forward-mode Jacobian :func:`ttsim_jax.fit.flightfit.jacobian` (``jac="jax"``, float32 like the
  batched fit); timed with and without the compilation of those functions, which are compiled with
  the batched fit's XLA options (``aero.COMPILER_OPTIONS``) so that the cold times compare alike;
* jaxopt (for the choice of solver): ``jaxopt.LevenbergMarquardt`` over the same residual,
  vmapped over the same groups (forward-mode Jacobian, Cholesky), cold and warm.

Prints JSON (times, the ratios scipy / batched from this one run, the agreement of the fitted
coefficients, the machine and its load average: the machine may be shared, so compare ratios from
one run, not times across runs).

    python benchmarks/fit_speed.py --data ../shared/data/real/spindoe --out benchmarks/results/fit_speed_cpu.json
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from report_json import emit  # noqa: E402


def _real_spindoe() -> Path:
    return Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real" / "spindoe"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=_real_spindoe(), help="SpinDOE folder (default: %(default)s)")
    p.add_argument("--segments", type=int, default=200, help="segments to fit (default: %(default)s)")
    p.add_argument("--repeats", type=int, default=3,
                   help="warm runs of the batched fit and of each scipy configuration; medians are reported (default: %(default)s)")
    p.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = p.parse_args(argv)

    t_start = time.perf_counter()
    c_start = time.process_time()
    import jax

    jax.config.update("jax_enable_x64", True)  # for scipy's float64 residual; the batched fit stays float32
    import jax.numpy as jnp
    from scipy.optimize import least_squares

    from ttsim_jax.data.importers import import_source
    from ttsim_jax.fit import flightfit as A
    from ttsim_jax.fit import segment_batches as B

    ds = import_source(args.data, "spindoe")
    ids, times, positions, spins, conf = B.dataset_segments(ds)
    keep = np.flatnonzero(conf >= 0.5)[: args.segments]
    if len(keep) < args.segments:
        print(f"only {len(keep)} segments with a measured spin", file=sys.stderr)
    times = [times[i] for i in keep]
    positions = [positions[i] for i in keep]
    spins = spins[keep]
    t_loaded, c_loaded = time.perf_counter(), time.process_time()

    # ---- batched, cold (the process's first fit: tracing and compilation included)
    t0, c0 = time.perf_counter(), time.process_time()
    cold = A.fit_segments(times, positions, spins)
    t_cold, c_cold = time.perf_counter() - t0, time.process_time() - c0
    warm_runs = []
    for _ in range(args.repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        warm = A.fit_segments(times, positions, spins)
        warm_runs.append((time.perf_counter() - t0, time.process_time() - c0))
    t_warm, c_warm = np.median(warm_runs, axis=0)

    # ---- scipy over the same residual
    from ttsim_jax.params import load_model

    size = max(B.capacity(len(t)) for t in times)
    opts = dict(compiler_options=A.COMPILER_OPTIONS)
    res_jit = jax.jit(A.residual, **opts)
    jac_jit = jax.jit(lambda *a: A.jacobian(*a)[0], **opts)
    guess_jit = jax.jit(A.initial_guess, **opts)

    def run_scipy(jac_kind: str):
        dtype = np.float64 if jac_kind == "2-point" else np.float32
        air = A.Air.from_model(load_model("conti2026"), dtype)
        t0, c0 = time.perf_counter(), time.process_time()
        theta, nfev = [], 0
        for i in range(len(times)):
            tau, pos, mask, spin = (jnp.asarray(a[0]) for a in B.pack(times, positions, spins, [i], size, 1, dtype))
            args_ = (tau, pos, mask, spin, jnp.asarray(len(times[i])), air)
            x0 = np.asarray(guess_jit(tau, pos, mask), np.float64)
            fun = lambda th: np.asarray(res_jit(jnp.asarray(th, dtype), *args_), np.float64)  # noqa: E731
            jac = "2-point"
            if jac_kind == "jax":
                jac = lambda th: np.asarray(jac_jit(jnp.asarray(th, dtype), *args_), np.float64)  # noqa: E731
            sol = least_squares(fun, x0, jac=jac, method="lm")
            theta.append(sol.x)
            nfev += sol.nfev
        return time.perf_counter() - t0, time.process_time() - c0, np.asarray(theta), nfev

    scipy = {}
    for kind in ("2-point", "jax"):
        first, first_cpu, theta, nfev = run_scipy(kind)  # includes compiling the residual (and Jacobian) once
        runs = [run_scipy(kind) for _ in range(args.repeats)]
        again, again_cpu = np.median([r[:2] for r in runs], axis=0)
        theta = runs[-1][2]
        d = np.abs(theta[:, 6:] - warm.theta[:, 6:])
        scipy[kind] = {
            "total_s": first, "warm_s": again, "total_cpu_s": first_cpu, "warm_cpu_s": again_cpu,
            "function_evaluations": int(nfev),
            "ratio_to_batched_cold": first / t_cold, "ratio_to_batched_warm": again / t_warm,
            "median_abs_diff_cd_cm": np.median(d, axis=0).tolist(),
            "p95_abs_diff_cd_cm": np.percentile(d, 95, axis=0).tolist(),
        }

    # ---- jaxopt's LevenbergMarquardt over the same residual, vmapped over the same groups
    from jaxopt import LevenbergMarquardt

    # Forward-mode Jacobian (its default J^T r is reverse mode, which the integration's
    # while_loop, stopping at the group's length, does not support).
    solver = LevenbergMarquardt(residual_fun=A.residual, maxiter=A.ITERATIONS + 1, tol=A.TOL, materialize_jac=True,
                                solver="cholesky")

    def group_jaxopt(tau, pos, mask, spin, n, air):
        x0 = jax.vmap(A.initial_guess)(tau, pos, mask)
        sol = jax.vmap(lambda x, t, p, m, s: solver.run(x, t, p, m, s, n, air))(x0, tau, pos, mask, spin)
        return sol.params, sol.state.iter_num

    jaxopt_jit = jax.jit(group_jaxopt, compiler_options=A.COMPILER_OPTIONS)
    air32 = A.default_air()

    def run_jaxopt():
        t0, c0 = time.perf_counter(), time.process_time()
        pending = [(idx, jaxopt_jit(*(jnp.asarray(a) for a in arrays), jnp.asarray(n_max), air32))
                   for idx, arrays, n_max in B.batches(times, positions, spins, B.GROUP)]
        theta, iters = np.full((len(times), 8), np.nan), np.zeros(len(times), int)
        for idx, (th, it) in pending:
            theta[idx], iters[idx] = np.asarray(th)[: len(idx)], np.asarray(it)[: len(idx)]
        return time.perf_counter() - t0, time.process_time() - c0, theta, iters

    j_cold, j_cold_cpu, _, _ = run_jaxopt()
    j_warm, j_warm_cpu, j_theta, j_iters = run_jaxopt()
    d = np.abs(j_theta[:, 6:] - warm.theta[:, 6:])
    jaxopt_result = {
        "solver": "jaxopt.LevenbergMarquardt(materialize_jac=True, solver='cholesky'), vmapped over the same groups",
        "cold_s": j_cold, "warm_s": j_warm, "cold_cpu_s": j_cold_cpu, "warm_cpu_s": j_warm_cpu,
        "ratio_to_batched_cold": j_cold / t_cold, "ratio_to_batched_warm": j_warm / t_warm,
        "segments_at_maxiter": int(np.sum(j_iters >= A.ITERATIONS + 1)),
        "median_abs_diff_cd_cm": np.nanmedian(d, axis=0).tolist(),
        "p95_abs_diff_cd_cm": np.nanpercentile(d, 95, axis=0).tolist(),
    }

    result = {
        "benchmark": "aerodynamic identification speed",
        "command": "python benchmarks/fit_speed.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "segments": len(times),
        "samples": int(sum(len(t) for t in times)),
        "longest_segment": int(max(len(t) for t in times)),
        "batched": {"cold_s": t_cold, "warm_s": t_warm, "cold_cpu_s": c_cold, "warm_cpu_s": c_warm,
                    "iterations": A.ITERATIONS, "warm_repeats_median_of": args.repeats, "batch": B.BATCH, "group": B.GROUP, "tol": A.TOL,
                    "compiler_options": A.COMPILER_OPTIONS,
                    "median_rmse_mm": float(np.nanmedian(warm.rmse) * 1e3),
                    "cold_equals_warm": bool(np.allclose(cold.theta, warm.theta, equal_nan=True))},
        "scipy_least_squares_lm": scipy,
        "jaxopt": jaxopt_result,
        "import_s": t_loaded - t_start,
        "import_cpu_s": c_loaded - c_start,
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count(),
                    "load_average": os.getloadavg(), "jax": jax.__version__, "backend": jax.default_backend()},
    }
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
