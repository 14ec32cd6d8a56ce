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
    from ttsim_jax.fit.choices import LATENT_MIN_SAMPLES
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
    fitted = np.zeros(len(rows), bool)
    for name, model in models:  # a segment too short for a latent spin comes back not ok: spin 0
        ls = fit_latent_spin(times, positions, model, min_samples=LATENT_MIN_SAMPLES)
        out[name][rows] = np.where(ls.ok[:, None], ls.spin, 0.0)
        fitted |= ls.ok
    source[rows[fitted]] = "latent"
    source[rows[~fitted]] = "zero"
    if through_bounce:
        bounce = _through_bounce(ds, models, seg_rows, rows, out, source)
    return out, source, bounce


def _through_bounce(ds, models, seg_rows, rows, out, source) -> np.ndarray:
    """Replaces, in ``out`` and ``source``, the latent spins of ``rows`` whose segment starts at a
    table bounce by the spin leaving that bounce (:func:`incoming_spins`); (N,) which were."""
    from ttsim_jax.fit.bounce_spin import bounce_pairs, fit_bounce_spin

    done = np.zeros(len(seg_rows), bool)
    starts = np.asarray(ds.segments["start_event_id"], np.int64)[seg_rows[rows]]
    pairs = bounce_pairs(ds, starts[starts >= 0])
    # each pair's outgoing segment is one of ``rows``' segments
    at_row = dict(zip(seg_rows[rows].tolist(), rows.tolist()))
    at = np.array([at_row[int(r)] for r in pairs["out_row"]], np.int64)
    if not len(at):
        return done
    for name, model in models:
        fit = fit_bounce_spin(pairs["times_in"], pairs["positions_in"], pairs["times_out"], pairs["positions_out"],
                              pairs["t_contact"], model)
        out[name][at[fit.ok]] = fit.spin_out[fit.ok]
        done[at[fit.ok]] = True
    source[done] = "latent"
    return done
