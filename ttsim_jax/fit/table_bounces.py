"""The table bounces of a dataset with their estimated pre- and post-bounce states: what the table
fit (:mod:`ttsim_jax.fit.table`) is fitted to.

The states come from the observations alone (:meth:`ttsim_jax.data.Dataset.contacts`);
bounces are then checked against the model's table (on the playing surface, moving down before and
up after, fast enough horizontally for the residual to act) and those failing a check are counted by
reason (:data:`SKIP_REASONS`).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from ttsim_jax.data import contact_states as estimation
from ttsim_jax.fit.racket_arrays import model_and_name
from ttsim_jax.physics import table as table_stage

SKIP_REASONS = {k: v for k, v in estimation.SKIP_REASONS.items()
                if k in ("no_incoming_segment", "no_outgoing_segment", "few_incoming_samples",
                         "few_outgoing_samples", "low_spin_conf_in", "low_spin_conf_out", "bad_fit", "non_finite")}
SKIP_REASONS.update(
    off_surface="bounce position outside the playing surface (an edge or side contact)",
    not_approaching="ball not moving down before the bounce (v_z- >= 0)",
    not_leaving="ball leaves with less normal speed than the rest threshold (sustained contact)",
    slow_horizontal="horizontal speed below min_horizontal_speed: the residual is faded there",
    residual_bounded="the fitted residual would be scaled down by the energy bound",
)


@dataclasses.dataclass
class Bounces:
    """Table bounces with estimated states (surface frame = world frame, flat table).

    Attributes:
        vel_in, spin_in, vel_out, spin_out: (N, 3) velocity [m/s] and spin [rad/s] before / after.
        event_id: (N,) ids of the bounces.
        skipped: reason -> event ids of the bounces not used (:data:`SKIP_REASONS`).
        n_bounces: table events examined.
    """

    vel_in: np.ndarray
    spin_in: np.ndarray
    vel_out: np.ndarray
    spin_out: np.ndarray
    event_id: np.ndarray
    skipped: dict
    n_bounces: int

    def __len__(self) -> int:
        return len(self.vel_in)

    def counts(self) -> dict:
        """reason -> number of bounces skipped for it (only reasons that occurred)."""
        return {k: len(v) for k, v in self.skipped.items() if v}


def table_bounces(ds, model="conti2026", fit: estimation.ContactFit = estimation.ContactFit(),
                  min_horizontal_speed: float = table_stage.RESIDUAL_FADE_SPEED, validate: bool = True,
                  progress: Callable | None = None) -> Bounces:
    """The table bounces of a dataset with their pre- and post-bounce states.

    Arguments:
        ds: a :class:`~ttsim_jax.data.Dataset` with ``table`` events and segments.
        model: bundled name, TOML path or Model (table geometry).
        fit: how the states are estimated (:class:`~ttsim_jax.data.contact_states.ContactFit`; its
            ``contact_point`` and ``max_face_gap`` do not apply).
        min_horizontal_speed: slower bounces are skipped [m/s] (the residual fades below 1 m/s).
        validate: validate ``ds`` first.
        progress: optional ``progress(done, total)`` over the bounces.

    Returns:
        :class:`Bounces` (only those that passed every check).
    """
    from ttsim_jax.data import validate as check

    m, _ = model_and_name(model)
    if validate:
        check(ds)
    ev = ds.events
    rows = np.flatnonzero(np.asarray(ev["kind"]).astype(str) == "table")
    event_ids = np.asarray(ev["event_id"], np.int64)[rows]
    pos = np.stack([np.asarray(ev[k], np.float64)[rows] for k in "xy"], -1)
    skipped = {k: [] for k in SKIP_REASONS}
    vin, win, vout, wout, _, good = ds.contacts(fit, progress).states(event_ids, skipped)
    half = np.array([0.5 * float(m.table.length), 0.5 * float(m.table.width)])
    finite = np.isfinite(np.concatenate([vin, win, vout, wout], 1)).all(1)
    checks = (("non_finite", ~finite),
              ("off_surface", np.any(np.abs(pos) > half, axis=1)),
              ("not_approaching", vin[:, 2] >= 0.0),
              ("not_leaving", vout[:, 2] < table_stage.REST_SPEED),
              ("slow_horizontal", np.linalg.norm(vin[:, :2], axis=1) < min_horizontal_speed))
    keep = np.zeros(len(event_ids), bool)
    keep[good] = True
    for reason, bad in checks:
        bad = bad & keep
        skipped[reason].extend(int(e) for e in event_ids[bad])
        keep &= ~bad
    return Bounces(vel_in=vin[keep], spin_in=win[keep], vel_out=vout[keep], spin_out=wout[keep],
                   event_id=event_ids[keep], skipped=skipped, n_bounces=len(event_ids))
