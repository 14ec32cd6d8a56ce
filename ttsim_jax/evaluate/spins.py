"""The spin a ball brings into a contact, for the evaluation's table and landing stages.

Measured where the record has a confident spin; elsewhere, by the ``spin`` setting, the incoming
segment's latent spin (:mod:`ttsim_jax.fit.latent_spin`, fitted under each model) or, for a
segment that starts at a bounce, the spin leaving that bounce with both segments fitted as one
flight (:mod:`ttsim_jax.fit.bounce_spin`); or 0.
"""

from __future__ import annotations

import numpy as np


def incoming_spins(ds, models: list, seg_rows: np.ndarray, known: np.ndarray, measured: np.ndarray,
                   spin: str, *, through_bounce: bool = False) -> tuple[dict, np.ndarray, np.ndarray]:
    """The spin each model gives a contact's incoming segment, by ``spin`` (as for the flight stage).

    Arguments:
        ds: the dataset; models: [(name, Model)].
        seg_rows: (N,) rows of the incoming segments in ``ds.segments``.
        known: (N,) bool, the segment's spin is measured with confidence; measured: (N, 3) that spin.
        spin: one of :data:`~ttsim_jax.fit.choices.SPIN_SOURCES`.
        through_bounce: where a latent spin is wanted for a segment that starts at a table bounce
            with a segment before it, take the spin leaving that bounce from the two segments
            fitted as one flight (:mod:`ttsim_jax.fit.bounce_spin`), which tells the spin's size
            where one flight cannot. Not for scoring the bounce itself against the table law: that
            fit assumes the law.

    Returns:
        ({name: (N, 3) spin [rad/s]}, source (N,) ``"measured"``, ``"latent"`` or ``"zero"``,
        bounce (N,) bool: the latent spin came through a bounce). A latent spin is the segment's
        fitted spin (:mod:`ttsim_jax.fit.latent_spin`, under each model); a segment too short for
        one, or whose fit failed, gives spin 0.
    """
    from ttsim_jax.fit.flight import LATENT_MIN_SAMPLES
    from ttsim_jax.fit.latent_spin import fit_latent_spin

    n = len(seg_rows)
    use_measured = known & (spin in ("auto", "measured"))
    base = np.where(use_measured[:, None], measured, 0.0)
    source = np.where(use_measured, "measured", "zero").astype("U8")
    want = (~use_measured) if spin == "auto" else np.full(n, spin == "latent")
    rows = np.flatnonzero(want)
    out = {name: base.copy() for name, _ in models}
    bounce = np.zeros(n, bool)
    if not len(rows):
        return out, source, bounce
    seg = ds.segments
    obs_rows = ds.segment_rows(np.asarray(seg["segment_id"])[seg_rows[rows]])
    times = [np.asarray(ds.observations["t"], np.float64)[r] for r in obs_rows]
    positions = [ds.positions[r] for r in obs_rows]
    long_enough = np.array([len(t) >= LATENT_MIN_SAMPLES for t in times], bool)
    fitted = np.zeros(len(rows), bool)
    for name, model in models:
        ls = fit_latent_spin([t for t, k in zip(times, long_enough) if k],
                             [p for p, k in zip(positions, long_enough) if k], model, min_samples=LATENT_MIN_SAMPLES)
        at = rows[long_enough]
        out[name][at] = np.where(ls.ok[:, None], ls.spin, 0.0)
        out[name][rows[~long_enough]] = 0.0
        fitted[np.flatnonzero(long_enough)[ls.ok]] = True
    source[rows[fitted]] = "latent"
    source[rows[~fitted]] = "zero"
    if through_bounce:
        bounce = _through_bounce(ds, models, seg_rows, rows, out, source)
    return out, source, bounce


def _through_bounce(ds, models, seg_rows, rows, out, source) -> np.ndarray:
    """Replaces, in ``out`` and ``source``, the latent spins of ``rows`` whose segment starts at a
    table bounce by the spin leaving that bounce (:func:`incoming_spins`); (N,) which were."""
    from ttsim_jax.fit.bounce_spin import MIN_SAMPLES, fit_bounce_spin

    seg, ev = ds.segments, ds.events
    starts = np.asarray(seg["start_event_id"], np.int64)[seg_rows[rows]]
    ev_rows = np.where(starts >= 0, ds.event_rows(np.where(starts >= 0, starts, 0)), -1)
    kinds = np.asarray(ev["kind"]).astype(str)
    is_bounce = (ev_rows >= 0) & (kinds[np.maximum(ev_rows, 0)] == "table")
    before, _ = ds.segments_around(np.where(is_bounce, starts, -1))
    pick = np.flatnonzero(is_bounce & (before >= 0))
    done = np.zeros(len(seg_rows), bool)
    if not len(pick):
        return done
    seg_ids = np.asarray(seg["segment_id"])
    obs_in = ds.segment_rows(seg_ids[before[pick]])
    obs_out = ds.segment_rows(seg_ids[seg_rows[rows[pick]]])
    keep = [k for k in range(len(pick)) if min(len(obs_in[k]), len(obs_out[k])) >= MIN_SAMPLES]
    if not keep:
        return done
    t_all = np.asarray(ds.observations["t"], np.float64)
    t_c = np.asarray(ev["t"], np.float64)[ev_rows[pick[keep]]]
    at = rows[pick[keep]]
    for name, model in models:
        fit = fit_bounce_spin([t_all[obs_in[k]] for k in keep], [ds.positions[obs_in[k]] for k in keep],
                              [t_all[obs_out[k]] for k in keep], [ds.positions[obs_out[k]] for k in keep], t_c, model)
        out[name][at[fit.ok]] = fit.spin_out[fit.ok]
        done[at[fit.ok]] = True
    source[done] = "latent"
    return done
