"""Aerodynamic identification of a dataset, end to end: select segments, fit each, regress, export.

:func:`identify_aero` runs the stages on a :class:`~ttsim_jax.data.Dataset` and returns an
:class:`AeroIdentification` holding every intermediate result; :func:`write_model` exports the
fitted model config. ``ttsim fit`` (:mod:`ttsim_jax.cli.fit`) is the command line over them.

Stages:

1. *select*: segments with at least ``min_samples`` observations and a spin confidence of at least
   ``min_spin_conf`` (C_D depends on the spin ratio, so segments without a measured spin cannot be
   placed in the table); sessions of the held-out split (``test_fraction``) are set aside.
2. *fit*: per segment, (p0, v0, C_D, C_M) by :func:`ttsim_jax.fit.flightfit.fit_segments`; segments
   whose fit RMSE exceeds ``max_rmse`` are dropped (the paper's 20 mm filter).
3. *regress*: C_D into the base model's breakpoint table, C_M into its piecewise form
   (:mod:`ttsim_jax.fit.aero_forms`), weighted by the fits' standard errors.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Callable

import numpy as np

from ttsim_jax.fit.flightfit import Air, SegmentFits, fit_segments
from ttsim_jax.fit.segment_batches import dataset_segments
from ttsim_jax.fit import aero_forms


@dataclasses.dataclass
class AeroIdentification:
    """What :func:`identify_aero` found.

    Attributes:
        base: path of the base model config.
        association: how segment coefficients are placed in the forms (``averaged`` or ``v_eff``).
        segment_ids: (S,) ids of the fitted segments; fits: their :class:`~ttsim_jax.fit.flightfit.SegmentFits`.
        used: (S,) bool, segments that entered the regression.
        counts: stage -> number of segments (``segments``, ``too_short``, ``low_spin_conf``,
            ``held_out``, ``fitted``, ``rmse``, ``used``).
        test_sessions: session ids of the held-out split.
        drag, magnus: the regressed :class:`~ttsim_jax.fit.aero_forms.FormFit` (None with no
            usable segment).
        seconds: stage -> wall time [s].
        settings: the thresholds used.
    """

    base: Path
    association: str
    segment_ids: np.ndarray
    fits: SegmentFits
    used: np.ndarray
    counts: dict
    test_sessions: list
    drag: aero_forms.FormFit | None
    magnus: aero_forms.FormFit | None
    seconds: dict
    settings: dict

    def summary(self) -> str:
        """A few lines per stage, for the terminal."""
        c, s = self.counts, self.seconds
        lines = [f"select: {c['segments']} segments; {c['too_short']} too short, {c['low_spin_conf']} without a "
                 f"measured spin (confidence < {self.settings['min_spin_conf']}), {c['held_out']} held out "
                 f"({len(self.test_sessions)} test sessions)",
                 f"fit:    {c['fitted']} segments in {s['fit']:.1f} s; median RMSE "
                 f"{_mm(np.nanmedian(self.fits.rmse))}; {c['rmse']} above {1e3 * self.settings['max_rmse']:.0f} mm "
                 f"dropped; {c['used']} used"]
        if self.drag is None:
            lines.append("regress: no usable segment; nothing fitted")
            return "\n".join(lines)
        used = self.used
        lines.append(f"        C_D median {np.median(self.fits.cd[used]):.3f}, C_M median {np.median(self.fits.cm[used]):.3f}, "
                     f"drag v_eff {np.min(self.fits.v_eff_drag[used]):.1f}-{np.max(self.fits.v_eff_drag[used]):.1f} m/s")
        rms = lambda form: (f"{form.rms_residual:.4f}" if np.isfinite(form.rms_residual)  # noqa: E731
                            else "not fitted (the base model's)")
        lines.append(f"regress ({self.association}; {', '.join(self.settings['forms'])}): weighted RMS residual of the "
                     f"C_D table {rms(self.drag)}, of the C_M form {rms(self.magnus)}")
        lines.append("  C_D table (rows: reference speeds; * = entry supported by data, support >= 1):")
        for k, row in enumerate(self.drag.values["cd"]):
            cells = " ".join(f"{v:.3f}{'*' if self.drag.support[k, j] >= 1 else ' '}" for j, v in enumerate(row))
            lines.append(f"    {cells}")
        sup = ", ".join(f"{x:.0f}" for x in self.magnus.support)
        lines.append(f"  C_M form support per reference speed: {sup}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-ready summary (no per-sample arrays)."""
        f = self.fits
        out = dict(base=str(self.base), association=self.association, counts=self.counts, seconds=self.seconds,
                   settings=self.settings, test_sessions=[int(x) for x in self.test_sessions],
                   segments=dict(segment_id=self.segment_ids.tolist(), used=self.used.tolist(),
                                 rmse=_clean(f.rmse), cd=_clean(f.cd), cm=_clean(f.cm),
                                 stderr_cd=_clean(f.stderr[:, 6]), stderr_cm=_clean(f.stderr[:, 7]),
                                 v_eff_drag=_clean(f.v_eff_drag), v_eff_magnus=_clean(f.v_eff_magnus),
                                 spin_rate=_clean(np.linalg.norm(f.spin, axis=1))))
        for name, form in (("drag", self.drag), ("magnus", self.magnus)):
            if form is not None:
                out[name] = dict(values={k: np.asarray(v).tolist() for k, v in form.values.items()},
                                 prior={k: np.asarray(v).tolist() for k, v in form.prior.items()},
                                 support=np.asarray(form.support).tolist(), n_used=form.n_used,
                                 rms_residual=form.rms_residual)
        return out


def _mm(x) -> str:
    return "-" if not np.isfinite(x) else f"{1e3 * x:.1f} mm"


def _clean(a) -> list:
    return [None if not np.isfinite(v) else float(v) for v in np.asarray(a, np.float64)]


FORMS = ("drag", "magnus")


def _unfitted(form) -> aero_forms.FormFit:
    """The base model's values of a form that is not regressed."""
    keys = ("cd",) if hasattr(form, "cd") else aero_forms.MAGNUS_FITTED
    values = {k: np.asarray(getattr(form, k), np.float64) for k in keys}
    support = np.zeros(np.shape(values[keys[0]]))
    return aero_forms.FormFit(values=values, prior=values, support=support, n_used=0, rms_residual=float("nan"))


def split_sessions(session_ids, test_fraction: float, seed: int) -> np.ndarray:
    """The held-out sessions: a ``test_fraction`` of the distinct ids, drawn with ``seed``."""
    ids = np.unique(np.asarray(session_ids))
    n = int(round(test_fraction * len(ids)))
    if test_fraction > 0 and len(ids) > 1:
        n = min(max(n, 1), len(ids) - 1)
    return np.sort(np.random.default_rng(seed).permutation(ids)[:n]) if n else np.array([], ids.dtype)


def identify_aero(ds, base: str | Path = "conti2026", *, association: str = "averaged", min_spin_conf: float = 0.5,
                  max_rmse: float = 0.02, min_samples: int = 5, test_fraction: float = 0.0, seed: int = 0,
                  alpha: float = 1.0, forms: tuple = FORMS, progress: Callable | None = None,
                  test_sessions=None) -> AeroIdentification:
    """Identifies C_D(Re, Sp) and C_M(v, w) from a dataset's flight segments.

    Arguments:
        ds: a :class:`~ttsim_jax.data.Dataset` with segments (and their spins).
        base: base model (bundled name or TOML path): ball, air, the forms' breakpoints and the
            prior of entries without data; its drag and Magnus models must be tables.
        association: ``"averaged"`` (default) or ``"v_eff"`` (the paper); see
            :mod:`ttsim_jax.fit.aero_forms`.
        min_spin_conf, max_rmse, min_samples: segment selection (see the module docstring).
        test_fraction, seed: fraction of sessions held out (for evaluation), and the seed of the draw.
        alpha: prior strength of the regression (pseudo-observations per entry).
        forms: which forms to regress (``"drag"``, ``"magnus"``); one left out keeps the base
            model's values.
        progress: optional ``progress(n_done, n_total)`` called after each fitted batch.
        test_sessions: the held-out session ids, given instead of drawn with ``test_fraction`` and
            ``seed`` (:func:`ttsim_jax.fit.pipeline.held_out_sessions` draws them per dataset).

    Returns:
        :class:`AeroIdentification`.
    """
    from ttsim_jax.params import ConfigError, load_model, resolve_model_path
    from ttsim_jax.physics.aero import DragTable, MagnusTable

    base_path = resolve_model_path(base)
    model = load_model(base_path)
    if not isinstance(model.aero.drag, DragTable) or not isinstance(model.aero.magnus, MagnusTable):
        raise ConfigError(f"{base_path}: the base model's [aero.drag] and [aero.magnus] must be of kind 'table' "
                          f"(they give the breakpoints of the fitted forms); found {type(model.aero.drag).__name__} "
                          f"and {type(model.aero.magnus).__name__}")
    seconds = {}
    t0 = time.perf_counter()
    seg = ds.segments
    n_obs = dict(zip(*np.unique(ds.observations["segment_id"], return_counts=True)))
    if test_sessions is None:
        test_sessions = split_sessions(seg["session_id"], test_fraction, seed)
    test_sessions = np.asarray(test_sessions, np.int64)
    counts = dict(segments=len(seg["segment_id"]), too_short=0, low_spin_conf=0, held_out=0)
    for k, sid in enumerate(seg["segment_id"]):
        if n_obs.get(sid, 0) < min_samples:
            counts["too_short"] += 1
        elif seg["spin_conf"][k] < min_spin_conf:
            counts["low_spin_conf"] += 1
        elif seg["session_id"][k] in test_sessions:
            counts["held_out"] += 1
    ids, times, positions, spins, conf = dataset_segments(ds, min_samples)
    session_of = dict(zip(seg["segment_id"], seg["session_id"]))
    keep = (conf >= min_spin_conf) & ~np.isin([session_of[i] for i in ids], test_sessions)
    ids, spins = ids[keep], spins[keep]
    times = [t for t, k in zip(times, keep) if k]
    positions = [p for p, k in zip(positions, keep) if k]
    seconds["select"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    air = Air.from_model(model)
    report = None if progress is None else (lambda done: progress(done, len(ids)))  # noqa: E731
    fits = fit_segments(times, positions, spins, air=air, progress=report)
    seconds["fit"] = time.perf_counter() - t0
    good = np.isfinite(fits.rmse) & np.all(np.isfinite(fits.stderr[:, 6:]), axis=1)
    used = good & (fits.rmse <= max_rmse)
    counts.update(fitted=len(ids), rmse=int((good & ~used).sum() + (~good).sum()), used=int(used.sum()))

    t0 = time.perf_counter()
    drag = magnus = None
    if used.any():
        w = np.linalg.norm(spins[used], axis=1)
        vel = [v for v, u in zip(fits.velocities, used) if u]
        drag, magnus = _unfitted(model.aero.drag), _unfitted(model.aero.magnus)
        if "drag" in forms:
            drag = aero_forms.fit_drag_table(
                model.aero.drag, fits.cd[used], fits.stderr[used, 6],
                aero_forms.force_weights(vel, spins[used], "drag"), w, float(model.ball.radius), float(model.aero.nu),
                association=association, alpha=alpha)
        if "magnus" in forms:
            magnus = aero_forms.fit_magnus_table(
                model.aero.magnus, fits.cm[used], fits.stderr[used, 7],
                aero_forms.force_weights(vel, spins[used], "magnus"), w, association=association, alpha=alpha)
    seconds["regress"] = time.perf_counter() - t0
    settings = dict(min_spin_conf=min_spin_conf, max_rmse=max_rmse, min_samples=min_samples,
                    test_fraction=test_fraction, seed=seed, alpha=alpha, forms=list(forms))
    return AeroIdentification(base=base_path, association=association, segment_ids=ids, fits=fits, used=used,
                              counts=counts, test_sessions=list(test_sessions), drag=drag, magnus=magnus,
                              seconds=seconds, settings=settings)


def write_model(result: AeroIdentification, out, *, name: str | None = None, source: str = "") -> Path:
    """Writes the identified model config (the base model with the fitted aerodynamics).

    Arguments:
        result: what :func:`identify_aero` returned (with fitted forms).
        out: the ``.toml`` file to write.
        name: the model's name (default: the file's stem).
        source: the config's ``source`` line.

    Returns:
        The written path.
    """
    if result.drag is None:
        raise ValueError("no fitted forms to write: no segment passed the selection")
    out = Path(out)
    return aero_forms.export_config(
        result.base, out, result.drag.values["cd"], result.magnus.values, name=name or out.stem,
        source=source or f"aerodynamics fitted by ttsim fit on {result.counts['used']} segments "
        f"({result.association} association) over {result.base.name}")
