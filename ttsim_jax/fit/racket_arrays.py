"""Measured racket contacts -> training arrays of the racket residual network.

For every racket contact of a :class:`~ttsim_jax.data.Dataset` that has a racket state, this
estimates the ball's state just before and just after the contact and converts both into the
racket frame exactly as the rally kernel does (:func:`ttsim_jax.physics.racket.racket_frame_state`),
so a network trained on the arrays corrects the simulator's own racket-frame prediction:

* ``x`` = (v~, w~, d) (8 inputs, conti2026) or (v~, w~) (6 inputs, durr2026): the ball's
  velocity relative to the face at the contact point (racket linear velocity plus, for racket
  kinds that use it, w_R x r), its spin relative to the racket's (the "nakashima" kind, used by
  durr2026, ignores the racket's angular velocity), and the contact position on the face.
* ``y_base`` = the base model's post-contact (v+, w+) for the model's racket parameters
  (:func:`ttsim_jax.physics.racket.base_response`).
* ``y_obs`` = the observed post-contact state in the same frame: R^T (v_out - v_surf),
  R^T (w_out - w_surf), with R, v_surf, w_surf those of the pre-contact state (the inverse of
  the paper's v+ = R v~+ + v_R + w_R x r, w+ = R w~+ + w_R).

The states come from the observations alone, or from the dataset's directly measured contact
states (:mod:`ttsim_jax.data.contact_states`, settings
:class:`~ttsim_jax.data.contact_states.ContactFit`); contacts lacking what is needed are skipped
and counted by reason (:data:`~ttsim_jax.data.contact_states.SKIP_REASONS`).

:func:`ttsim_jax.reality.synthetic_contact_dataset` makes a dataset of flights into known racket
states with a known post-contact law, for tests and for checking the pipeline end to end.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.data.contact_states import SKIP_REASONS, ContactFit
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics.rotations import quat_to_matrix

# Default residual inputs per bundled model: the paper's 8-input network, Dürr's 6-input one.
MODEL_INPUTS = {"conti2026": 8, "durr2026": 6}


@dataclasses.dataclass
class ContactArrays:
    """Training arrays of the racket residual network, one row per usable racket contact.

    Attributes:
        x: (N, n_inputs) racket-frame inputs (v~, w~[, d]).
        y_base: (N, 6) base-model post-contact (v+, w+), racket frame.
        y_obs: (N, 6) observed post-contact (v+, w+), racket frame.
        distance: (N,) contact distance |d| from the face centre [m].
        event_id, session_id: (N,) ids of the contacts.
        in_segment_id, out_segment_id: (N,) the segments the states were fitted on.
        world_in, world_out: (N, 6) fitted world-frame (velocity, spin) before / after.
        fit_rmse: (N, 2) RMS position residual of the incoming / outgoing fit [m].
        skipped: reason -> event ids of the skipped contacts (:data:`SKIP_REASONS`).
        n_contacts: racket events examined.
        model: name of the model whose racket parameters gave ``y_base``.
    """

    x: np.ndarray
    y_base: np.ndarray
    y_obs: np.ndarray
    distance: np.ndarray
    event_id: np.ndarray
    session_id: np.ndarray
    in_segment_id: np.ndarray
    out_segment_id: np.ndarray
    world_in: np.ndarray
    world_out: np.ndarray
    fit_rmse: np.ndarray
    skipped: dict
    n_contacts: int
    model: str = ""

    def __len__(self) -> int:
        return len(self.x)

    def counts(self) -> dict:
        """reason -> number of contacts skipped for it (only reasons that occurred)."""
        return {k: len(v) for k, v in self.skipped.items() if v}

    def summary(self) -> str:
        """One paragraph: how many racket contacts were used and why the others were not."""
        lines = [f"{len(self)} of {self.n_contacts} racket contacts usable"]
        for k, n in self.counts().items():
            lines.append(f"  skipped {n:5d}: {k} ({SKIP_REASONS[k]})")
        return "\n".join(lines)


def model_and_name(model):
    """(Model, name) from a bundled model name, a TOML path or a Model."""
    from ttsim_jax.params import Model, load_model

    if isinstance(model, Model):
        return model, model.name
    return load_model(model), str(model)


def default_inputs(model) -> int:
    """Residual inputs for a model: 8 (conti2026), 6 (durr2026); otherwise 6 for the
    "nakashima" racket kind, 8 for the others, unless the model carries a residual network."""
    return _default_inputs(*model_and_name(model))


def _default_inputs(m, name) -> int:
    if m.residual is not None:
        return m.residual.config.n_inputs
    if name in MODEL_INPUTS:
        return MODEL_INPUTS[name]
    return 6 if m.racket.kind == "nakashima" else 8


@jax.jit
def _frames(racket_params, radius, mass, rpos, rrot, rvel, rang, pos, vel_in, spin_in, vel_out, spin_out, d_table,
            use_table_d):
    from ttsim_jax.state import Racket

    def one(rp, rr, rv, rw, p, vi, wi, vo, wo, dt):
        racket = Racket(pos=rp, rot=rr, vel=rv, ang_vel=rw, face=jnp.zeros(2, rp.dtype))
        st = racket_stage.racket_frame_state(racket_params, racket, radius, p, vi, wi)
        d = jnp.where(use_table_d, dt, st["d"])
        vb, wb = racket_stage.base_response(racket_params, st["v"], st["w"], d, radius, mass)
        rot = st["rot"]
        v_obs = rot.T @ (vo - st["v_surf"])
        w_obs = rot.T @ (wo - st["w_surf"])
        gap = jnp.dot(rot[:, 0], p - rp) - radius
        return (jnp.concatenate([st["v"], st["w"], d]), jnp.concatenate([vb, wb]),
                jnp.concatenate([v_obs, w_obs]), gap)

    return jax.vmap(one)(rpos, rrot, rvel, rang, pos, vel_in, spin_in, vel_out, spin_out, d_table)


def contact_arrays(ds, model="conti2026", n_inputs: int | None = None, fit: ContactFit = ContactFit(),
                   validate: bool = True) -> ContactArrays:
    """Training arrays of the racket residual network from a dataset's racket contacts.

    Arguments:
        ds: a :class:`~ttsim_jax.data.Dataset` with racket events, racket states and segments.
        model: bundled model name, TOML path or :class:`~ttsim_jax.params.Model`; its racket
            parameters give the racket frame convention (racket spin used or not) and ``y_base``,
            its ball the radius and mass.
        n_inputs: 8 (v~, w~, d) or 6 (v~, w~); default :func:`default_inputs`.
        fit: how the contact states are estimated (:class:`ContactFit`).
        validate: validate ``ds`` first.

    Returns:
        :class:`ContactArrays` (float32 ``x``, ``y_base``, ``y_obs``; float64 diagnostics).
    """
    from ttsim_jax.data.batch import racket_contact_batch
    from ttsim_jax.kernel.ball_step import ball_properties

    m, name = model_and_name(model)
    n_inputs = _default_inputs(m, name) if n_inputs is None else int(n_inputs)
    if n_inputs not in (6, 8):
        raise ValueError(f"contact_arrays: n_inputs = {n_inputs!r}, must be 8 or 6")
    radius, mass = (float(v) for v in ball_properties(m))

    batch = racket_contact_batch(ds, validate=validate)  # the join: event <-> racket state <-> segments
    n = int(np.sum(np.asarray(batch.mask)))
    in_row = np.asarray(batch.in_segment)[:n]
    out_row = np.asarray(batch.out_segment)[:n]
    event_ids = np.asarray(ds.rackets["event_id"], np.int64)[:n]
    # Float values come from the tables in float64 (batch arrays follow JAX's default float,
    # float32, which cannot hold absolute times to the sub-millisecond).
    ev = ds.events
    rows = ds.event_rows(event_ids)
    p_c = np.stack([np.asarray(ev[k], np.float64)[rows] for k in "xyz"], -1) if n else np.zeros((0, 3))
    sess = np.asarray(ev["session_id"], np.int64)[rows] if n else np.zeros(0, np.int64)
    rk = ds.rackets
    col = lambda *ks: np.stack([np.asarray(rk[k], np.float64)[:n] for k in ks], -1)  # noqa: E731
    r_pos, r_vel, r_ang = col("x", "y", "z"), col("vx", "vy", "vz"), col("wx", "wy", "wz")
    r_rot = quat_to_matrix(col("qw", "qx", "qy", "qz")) if n else np.zeros((0, 3, 3))
    d_table = col("d_y", "d_z")

    skipped = {k: [] for k in SKIP_REASONS}
    kinds = np.asarray(ev["kind"]).astype(str)
    stateless = np.setdiff1d(np.asarray(ev["event_id"], np.int64)[kinds == "racket"], event_ids)
    skipped["no_racket_state"] = [int(e) for e in stateless]

    vin, win, vout, wout, rmse, good = ds.contacts(fit).states(event_ids, skipped)
    seg_ids = np.asarray(ds.segments["segment_id"], np.int64)
    if len(good):
        j = lambda a: jnp.asarray(a[good])  # noqa: E731
        x8, y_base, y_obs, gap = (np.asarray(a, np.float64) for a in _frames(
            m.racket, jnp.asarray(radius), jnp.asarray(mass), j(r_pos), j(r_rot), j(r_vel), j(r_ang), j(p_c), j(vin),
            j(win), j(vout), j(wout), j(d_table), jnp.asarray(fit.contact_point == "table")))
    else:
        x8, y_base, y_obs, gap = np.zeros((0, 8)), np.zeros((0, 6)), np.zeros((0, 6)), np.zeros(0)
    keep = np.ones(len(good), bool)
    checks = (("non_finite", ~(np.isfinite(x8).all(1) & np.isfinite(y_base).all(1) & np.isfinite(y_obs).all(1))),
              ("off_face", np.abs(gap) > fit.max_face_gap),
              ("not_approaching", x8[:, 0] >= 0.0),
              ("not_leaving", y_obs[:, 0] <= 0.0))
    for reason, bad in checks:
        bad = bad & keep
        skipped[reason].extend(int(event_ids[good[k]]) for k in np.flatnonzero(bad))
        keep &= ~bad
    g = good[keep]
    x8, y_base, y_obs = x8[keep], y_base[keep], y_obs[keep]
    f32 = lambda a: np.ascontiguousarray(a, np.float32)  # noqa: E731
    return ContactArrays(
        x=f32(x8[:, :n_inputs]), y_base=f32(y_base), y_obs=f32(y_obs),
        distance=np.linalg.norm(x8[:, 6:8], axis=1), event_id=event_ids[g], session_id=sess[g],
        in_segment_id=_segment_ids(seg_ids, in_row[g]), out_segment_id=_segment_ids(seg_ids, out_row[g]),
        world_in=np.concatenate([vin[g], win[g]], 1), world_out=np.concatenate([vout[g], wout[g]], 1),
        fit_rmse=rmse[g], skipped=skipped, n_contacts=n + len(stateless), model=name,
    )


def _segment_ids(seg_ids, rows) -> np.ndarray:
    """Segment ids of segments-table ``rows``, -1 for none (a contact whose states were measured
    directly has no segments)."""
    rows = np.asarray(rows, np.int64)
    out = np.full(len(rows), -1, np.int64)
    out[rows >= 0] = seg_ids[rows[rows >= 0]]
    return out
