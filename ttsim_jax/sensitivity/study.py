"""A whole sensitivity study, as ``ttsim sensitivity`` runs it: shots, Jacobians, local-gradient
flags, error budget, optional Monte Carlo check, report files."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ttsim_jax.files.atomic import atomic_write
from ttsim_jax.sensitivity import budgets, report
from ttsim_jax.sensitivity.cases import dataset_shots, sampled_shots
from ttsim_jax.sensitivity.jacobians import STATE_GROUPS, jacobian, layout_of, local_flags
from ttsim_jax.sensitivity.targets import check_target
from ttsim_jax.sizes import require as require_memory


@dataclass
class StudyConfig:
    """Options of a study (see ``ttsim sensitivity --help``)."""

    model: str = "conti2026"
    residual: str | None = None
    data: str | None = None
    shots: int = 256
    types: tuple | None = None
    seed: int = 0
    target: str = "landing"
    dt: float = 1e-3
    horizon: float = 1.5
    chunk: int = 512
    mode: str = "rev"
    check: bool = True
    monte_carlo: int = 0
    racket_pos: float = budgets.RACKET_POS_STD
    racket_vel: float = budgets.RACKET_VEL_STD
    racket_rot_deg: float = budgets.RACKET_ROT_STD_DEG
    spin_rel: float = budgets.SPIN_REL_STD
    spin_abs: float = budgets.SPIN_ABS_STD
    param_cov: str | None = None
    float64: bool = False


def check_locality(cfg: StudyConfig, jac, shots, scale, n_steps) -> dict:
    """:func:`~ttsim_jax.sensitivity.jacobians.local_flags` in float64 (in float32, differences of
    landing points at the small probe are as large as its rounding noise), with probes of the typical
    change for state inputs and a tenth of it (0.1 %) for parameters, which keeps a table's
    breakpoints in order."""
    import jax
    import jax.numpy as jnp

    from ttsim_jax import load_model

    jax.config.update("jax_enable_x64", True)
    model = load_model(cfg.model, dtype=jnp.float64, residual=cfg.residual)
    probe = {g: scale if g in STATE_GROUPS else 0.1 * scale for g in dict.fromkeys(jac.groups)}
    return local_flags(model, shots, jac, probe, dt=cfg.dt, n_steps=n_steps, batch=cfg.chunk)


def study_bytes(cfg: StudyConfig, inputs: int, n_steps: int) -> int:
    """What :func:`run_study` holds at once [bytes]: per shot its Jacobian (3 components x every
    input, in float64 for the report, with the local check's and the budget's copies: 4 of them),
    its state and the Monte Carlo samples' landing points; per shot of a chunk, the reverse pass's
    stored steps (remat keeps about one ball state, 9 numbers, per step)."""
    item = 8 if cfg.float64 else 4
    per_shot = 4 * 3 * (inputs + 9) * 8 + 1024 + (cfg.monte_carlo or 0) * 3 * 8
    per_chunk_shot = n_steps * 9 * item * 4
    return cfg.shots * per_shot + min(cfg.chunk, cfg.shots) * per_chunk_shot


def run_study(cfg: StudyConfig, out: Path, log=print) -> dict:
    """Runs a study and writes ``sensitivity.json``, ``report.md``, ``heatmaps.png`` and (for the
    landing target) ``budget.png`` into ``out``.

    Returns:
        The summary (:func:`ttsim_jax.sensitivity.report.summarise`) plus the paths written.
    """
    import jax
    import jax.numpy as jnp

    from ttsim_jax import load_model

    check_target(cfg.target)
    if cfg.float64:
        jax.config.update("jax_enable_x64", True)
    model = load_model(cfg.model, dtype=jnp.float64 if cfg.float64 else jnp.float32, residual=cfg.residual)
    n_steps = int(math.ceil(cfg.horizon / cfg.dt))
    sources = []
    if cfg.target == "landing":  # a bad covariance file is refused before the work starts
        sources = budgets.default_sources(cfg.racket_pos, cfg.racket_vel, cfg.racket_rot_deg, cfg.spin_rel,
                                          cfg.spin_abs)
        if cfg.param_cov:
            sources.append(budgets.parameter_source(cfg.param_cov, layout_of(model).columns()))
    require_memory(f"a sensitivity study of {cfg.shots} shots",
                   study_bytes(cfg, len(layout_of(model).columns()), n_steps), remedy="ask for fewer shots (--shots) or a smaller --chunk")
    t0 = time.perf_counter()
    if cfg.data:
        shots = dataset_shots(model, cfg.data, dt=cfg.dt, limit=cfg.shots)
    else:
        shots = sampled_shots(model, cfg.shots, seed=cfg.seed, types=cfg.types, dt=cfg.dt)
    log(f"{len(shots)} shots ({shots.source}) in {time.perf_counter() - t0:.1f} s")
    log(f"differentiating through the kernel ({cfg.mode} mode; the first chunk compiles: a few minutes the first "
        "time, cached afterwards) ...")
    t0 = time.perf_counter()
    jac = jacobian(model, shots, target=cfg.target, dt=cfg.dt, n_steps=n_steps, mode=cfg.mode, chunk=cfg.chunk,
                   progress=True)
    t_jac = time.perf_counter() - t0
    log(f"Jacobian of {cfg.target}: {len(shots)} shots x {jac.jac.shape[1]} components x {jac.jac.shape[2]} inputs "
        f"in {t_jac:.1f} s ({cfg.mode} mode, compilation included); {int(jac.valid.sum())} shots landed")
    scale = report.column_scales(jac)
    if cfg.check:
        t0 = time.perf_counter()
        flags = check_locality(cfg, jac, shots, scale, n_steps)
        log(f"local-gradient check: {int((jac.valid & flags['flag']).sum())} of {int(jac.valid.sum())} landed shots "
            f"flagged in {time.perf_counter() - t0:.1f} s")
    else:
        b = len(shots)
        flags = dict(flag=~jac.valid, flip=np.zeros(b, bool), groups={}, disagreement={}, checked=False)
    budget = mc = None
    if sources:
        budget = budgets.linear_budget(jac, sources)
        if cfg.monte_carlo:
            t0 = time.perf_counter()
            mc = budgets.monte_carlo(model, shots, jac, sources, cfg.monte_carlo, dt=cfg.dt, n_steps=n_steps,
                                     seed=cfg.seed, batch=cfg.chunk)
            ok = report.usable(jac, flags, budget.groups) & (mc["kept"] > 0.99)
            ratio = np.sqrt(np.einsum("bkk->b", mc["cov"][ok]) / np.einsum("bkk->b", budget.cov[ok]))
            log(f"Monte Carlo ({cfg.monte_carlo} samples per shot) in {time.perf_counter() - t0:.1f} s: "
                f"landing std MC / linear on {int(ok.sum())} smooth shots: median {np.median(ratio):.3f}, "
                f"5-95 % {np.quantile(ratio, 0.05):.3f}-{np.quantile(ratio, 0.95):.3f}"
                if ok.any() else "Monte Carlo: no smooth shot to compare")
    summary = report.summarise(jac, shots, flags, budget, scale)
    out.mkdir(parents=True, exist_ok=True)
    meta = dict(model=cfg.model, residual=cfg.residual, source=shots.source, dt=cfg.dt, n_steps=n_steps,
                mode=cfg.mode, seconds_jacobian=t_jac, sources=[dict(name=s.name, columns=list(s.columns))
                                                                for s in sources])
    paths = dict(json=report.write_json(out / "sensitivity.json", meta=meta, jac=jac, shots=shots, flags=flags,
                                        summary=summary, scale=scale, budget=budget, mc=mc))
    atomic_write(out / "report.md", summary["markdown"].encode(), "the report")
    paths["report"] = out / "report.md"
    paths["heatmaps"] = report.heatmaps(jac, shots, summary["sensitivity"], summary["ok_group"],
                                        out / "heatmaps.png")
    if budget is not None:
        paths["budget"] = report.budget_bars(summary, budget.sources, out / "budget.png")
    summary["paths"] = paths
    return summary
