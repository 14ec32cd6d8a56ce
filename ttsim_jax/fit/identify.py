"""Aerodynamic identification of a dataset, end to end: select segments, fit each, regress, export.

:func:`identify_aero` runs the stages on a :class:`~ttsim_jax.data.Dataset` and returns an
:class:`AeroIdentification` holding every intermediate result; :func:`write_model` exports the
fitted model config. ``ttsim fit`` (:mod:`ttsim_jax.cli.fit`) is the command line over them.

Stages:

1. *select*: segments with at least ``min_samples`` observations; sessions of the held-out split
   (``test_fraction``) are set aside. A segment's spin is its measured one where the confidence is
   at least ``min_spin_conf``. With ``spin="auto"`` the others take the latent spin of
   :mod:`ttsim_jax.fit.latent_spin`, fitted under the base model from the segment's own samples
   (segments whose latent spin is of undecided size, ``LatentSpin.ambiguous``, are left out: their
   spin ratio, where C_D is placed, is unknown); with ``spin="measured"`` they are left out.
2. *fit*: per segment, (p0, v0, C_D, C_M) by :func:`ttsim_jax.fit.flightfit.fit_segments` at that
   spin; segments whose fit RMSE exceeds ``max_rmse`` are dropped (the paper's 20 mm filter).
3. *regress*: C_D into the base model's breakpoint table from every fitted segment, C_M into its
   piecewise form (:mod:`ttsim_jax.fit.aero_forms`) from the segments with a measured spin only,
   weighted by the fits' standard errors. Why the two differ: a flight's deceleration shows its
   C_D whatever the spin, and the spin only places it along the spin ratio; a latent spin is the
   spin the base model's C_M needs to bend the flight as observed, so a C_M fitted from it returns
   the base's C_M, not the ball's.

Why latent spins enter the drag: a pooled fit whose C_D comes from one dataset's spinning balls
is flown on every dataset, and a dataset without measured spin whose balls decelerate otherwise
is then made worse by the fit (the MPI launcher recordings against SpinDOE's C_D: 5-45 % worse
on held-out sessions over 10 seeds); with their latent spins they inform the entries they fly in.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Callable

import numpy as np

from ttsim_jax.fit.choices import LATENT_MIN_SAMPLES
from ttsim_jax.fit.flightfit import Air, SegmentFits, fit_segments
from ttsim_jax.fit.latent_spin import fit_latent_spin
from ttsim_jax.fit.segment_batches import dataset_segments
from ttsim_jax.fit import aero_forms


@dataclasses.dataclass
class AeroIdentification:
    """What :func:`identify_aero` found.

    Attributes:
        base: path of the base model config.
        association: how segment coefficients are placed in the forms (``averaged`` or ``v_eff``).
        segment_ids: (S,) ids of the fitted segments; fits: their :class:`~ttsim_jax.fit.flightfit.SegmentFits`.
        used: (S,) bool, segments that entered the C_D regression (those with ``spin_source``
            ``"measured"`` the C_M regression too).
        spin_source: (S,) ``"measured"`` or ``"latent"``: where each fitted segment's spin came from.
        counts: stage -> number of segments: ``segments`` = ``too_short`` + ``held_out`` +
            ``low_spin_conf`` (training segments without a measured spin left out) + ``fitted``;
            ``latent`` (fitted at their latent spin), ``ambiguous`` (of those left out: a latent
            spin of undecided size); ``rmse`` (dropped by the fit's RMSE), ``used`` (in the C_D
            regression), ``used_measured`` (of them with a measured spin: in the C_M regression).
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
    spin_source: np.ndarray
    counts: dict
    test_sessions: list
    drag: aero_forms.FormFit | None
    magnus: aero_forms.FormFit | None
    seconds: dict
    settings: dict

    def summary(self) -> str:
        """A few lines per stage, for the terminal."""
        c, s = self.counts, self.seconds
        latent = (f", {c['latent']} at their latent spin (of these {c['ambiguous']} with a latent spin of undecided "
                  "size left out)" if self.settings["spin"] == "auto" else "")
        lines = [f"select: {c['segments']} segments; {c['too_short']} too short, {c['held_out']} held out "
                 f"({len(self.test_sessions)} test sessions), {c['low_spin_conf']} without a measured spin "
                 f"(confidence < {self.settings['min_spin_conf']}) left out{latent}",
                 f"fit:    {c['fitted']} segments in {s['fit']:.1f} s; median RMSE "
                 f"{_mm(np.nanmedian(self.fits.rmse))}; {c['rmse']} above {1e3 * self.settings['max_rmse']:.0f} mm "
                 f"dropped; {c['used']} used for C_D, {c['used_measured']} of them (a measured spin) for C_M"]
        if self.drag is None:
            lines.append("regress: no usable segment; nothing fitted")
            return "\n".join(lines)
        used = self.used
        measured = used & (self.spin_source == "measured")
        cm = f"{np.median(self.fits.cm[measured]):.3f}" if measured.any() else "-"
        lines.append(f"        C_D median {np.median(self.fits.cd[used]):.3f}, C_M median {cm}, "
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
                                 spin_source=[str(x) for x in self.spin_source],
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
#: Where :func:`identify_aero` takes the spin of a segment without a measured one from.
IDENTIFY_SPINS = ("auto", "measured")


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
                  alpha: float = 1.0, forms: tuple = FORMS, spin: str = "auto", progress: Callable | None = None,
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
        spin: ``"auto"`` (default): segments without a measured spin enter the C_D regression at
            their latent spin; ``"measured"``: they are left out (see the module docstring).
        progress: optional ``progress(n_done, n_total)`` called after each fitted batch.
        test_sessions: the held-out session ids, given instead of drawn with ``test_fraction`` and
            ``seed`` (:func:`ttsim_jax.fit.pipeline.held_out_sessions` draws them per dataset).

    Returns:
        :class:`AeroIdentification`.
    """
    from ttsim_jax.params import ConfigError, load_model, resolve_model_path
    from ttsim_jax.physics.aero import DragTable, MagnusTable

    if spin not in IDENTIFY_SPINS:
        raise ValueError(f"spin = {spin!r}: expected one of {IDENTIFY_SPINS}")
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
    ids, times, positions, spins, conf = dataset_segments(ds, min_samples)
    session_of = dict(zip(seg["segment_id"], seg["session_id"]))
    training = ~np.isin([session_of[i] for i in ids], test_sessions)
    measured = conf >= min_spin_conf
    spins = np.where(measured[:, None], spins, 0.0)
    keep = training & measured
    counts = dict(segments=len(seg["segment_id"]), latent=0, ambiguous=0)
    if spin == "auto":
        rows = np.flatnonzero(training & ~measured & (np.array([len(t) for t in times]) >= LATENT_MIN_SAMPLES))
        if len(rows):
            latent = fit_latent_spin([times[i] for i in rows], [positions[i] for i in rows], model,
                                     min_samples=LATENT_MIN_SAMPLES)
            good = latent.ok & ~latent.ambiguous
            spins[rows[good]] = latent.spin[good]
            keep[rows[good]] = True
            counts.update(latent=int(good.sum()), ambiguous=int((latent.ok & latent.ambiguous).sum()))
    counts.update(too_short=int(sum(n_obs.get(i, 0) < min_samples for i in seg["segment_id"])),
                  held_out=int((~training).sum()), low_spin_conf=int((training & ~keep).sum()))
    source = np.where(measured[keep], "measured", "latent")
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
    with_spin = used & (source == "measured")
    counts.update(fitted=len(ids), rmse=int((good & ~used).sum() + (~good).sum()), used=int(used.sum()),
                  used_measured=int(with_spin.sum()))

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
        if "magnus" in forms and with_spin.any():
            vel_m = [v for v, u in zip(fits.velocities, with_spin) if u]
            magnus = aero_forms.fit_magnus_table(
                model.aero.magnus, fits.cm[with_spin], fits.stderr[with_spin, 7],
                aero_forms.force_weights(vel_m, spins[with_spin], "magnus"), np.linalg.norm(spins[with_spin], axis=1),
                association=association, alpha=alpha)
    seconds["regress"] = time.perf_counter() - t0
    settings = dict(min_spin_conf=min_spin_conf, max_rmse=max_rmse, min_samples=min_samples,
                    test_fraction=test_fraction, seed=seed, alpha=alpha, forms=list(forms), spin=spin)
    return AeroIdentification(base=base_path, association=association, segment_ids=ids, fits=fits, used=used,
                              spin_source=source,
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
