"""Dataset -> racket-frame training arrays (ttsim_jax.fit.racket_arrays)."""

import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Racket, load_model
from ttsim_jax.data import Dataset
from ttsim_jax.data.contact_states import ContactFit
from ttsim_jax.fit.racket_arrays import contact_arrays
from ttsim_jax.reality.synthetic_contacts import racket_base_fn, true_residual
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics.rotations import matrix_to_quat, quat_to_matrix
from ttsim_jax.reality import synthetic_contact_dataset
from ttsim_jax.kernel.ball_step import ball_properties


@pytest.fixture(scope="module")
def synthetic():
    return synthetic_contact_dataset(12, seed=4, residual_fn=true_residual)


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    m = quat_to_matrix(q)
    np.testing.assert_allclose(m @ np.swapaxes(m, 1, 2), np.broadcast_to(np.eye(3), m.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=1e-12)
    np.testing.assert_allclose(matrix_to_quat(m), q, atol=1e-12)
    # 90 degrees about z: racket x-axis -> world y
    quarter = quat_to_matrix([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
    np.testing.assert_allclose(quarter @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


def test_round_trip_of_known_contacts(synthetic):
    ds, truth = synthetic
    arrays = contact_arrays(ds, "conti2026")
    assert len(arrays) == 12 and arrays.counts() == {} and arrays.n_contacts == 12
    np.testing.assert_array_equal(arrays.event_id, truth["event_id"])
    x, y_obs = truth["x"], truth["y_obs"]
    # velocities from the quadratic fit: within a few cm/s of the truth (drag jerk over 50 ms);
    # spins and contact positions exact up to float32
    np.testing.assert_allclose(arrays.x[:, :3], x[:, :3], atol=0.06)
    np.testing.assert_allclose(arrays.x[:, 3:6], x[:, 3:6], atol=1e-3)
    np.testing.assert_allclose(arrays.x[:, 6:8], x[:, 6:8], atol=1e-6)
    np.testing.assert_allclose(arrays.y_obs[:, :3], y_obs[:, :3], atol=0.06)
    np.testing.assert_allclose(arrays.y_obs[:, 3:], y_obs[:, 3:], atol=1e-3)
    np.testing.assert_allclose(arrays.distance, truth["distance"], atol=1e-6)
    # y_base is the base model at the recovered inputs
    m = load_model("conti2026")
    np.testing.assert_allclose(arrays.y_base, np.asarray(racket_base_fn(m.racket, *ball_properties(m))(arrays.x)),
                               rtol=1e-4, atol=1e-3)
    # ... and the observed residual is the known one, up to the velocity-fit error
    res = arrays.y_obs - arrays.y_base
    np.testing.assert_allclose(res[:, :3], np.asarray(true_residual(x))[:, :3], atol=0.12)
    assert arrays.fit_rmse.max() < 1e-3


def test_hand_built_contact_with_racket_spin():
    """One contact built by hand with Dataset.from_arrays: a ballistic flight (no drag) into a
    spinning, moving, tilted racket; the quadratic fit is then exact."""
    g = np.array([0.0, 0.0, -9.81])
    t_c = 2.0
    p_c = np.array([1.35, 0.10, 0.30])
    v_in, w_in = np.array([7.0, -0.5, -1.0]), np.array([20.0, -150.0, 60.0])
    v_out, w_out = np.array([-9.0, 0.8, 2.0]), np.array([-40.0, 200.0, 10.0])
    t_in = t_c - (0.3 + np.arange(8)[::-1]) / 200.0
    t_out = t_c + (0.6 + np.arange(8)) / 200.0
    path = lambda v, t: p_c + np.outer(t - t_c, v) + 0.5 * np.outer((t - t_c) ** 2, g)  # noqa: E731
    t = np.r_[t_in, t_out]
    pos = np.r_[path(v_in, t_in), path(v_out, t_out)]
    spin = np.r_[np.tile(w_in, (8, 1)), np.tile(w_out, (8, 1))]
    angle = np.pi + 0.3  # the face normal points back along -x, turned 0.3 rad about z
    quat = [np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)]
    rot = quat_to_matrix(quat)
    r_pos = p_c - rot @ [0.02, 0.01, -0.02]  # ball centre one radius in front of d = (0.01, -0.02)
    r_vel, r_ang = np.array([-2.0, 0.3, 1.0]), np.array([3.0, -8.0, 15.0])
    ds = Dataset.from_arrays(np.zeros(16, int), t, pos, spin=spin,
                             events=dict(session_id=[0], t=[t_c], kind=["racket"], pos=[p_c]),
                             rackets=dict(pos=[r_pos], quat=[quat], vel=[r_vel], ang_vel=[r_ang],
                                          contact=[[0.01, -0.02]]))
    for name in ("conti2026", "durr2026"):
        m = load_model(name)
        arrays = contact_arrays(ds, name)
        assert len(arrays) == 1, arrays.summary()
        racket = Racket.create(r_pos, rot=rot, vel=r_vel, ang_vel=r_ang)
        radius = float(m.ball.radius)
        st = racket_stage.racket_frame_state(m.racket, racket, radius, jnp.asarray(p_c), jnp.asarray(v_in),
                                             jnp.asarray(w_in))
        expect_x = np.concatenate([st["v"], st["w"], st["d"]])[: arrays.x.shape[1]]
        np.testing.assert_allclose(arrays.x[0], expect_x, rtol=1e-5, atol=1e-4)
        expect_y = np.concatenate([np.asarray(st["rot"]).T @ (v_out - np.asarray(st["v_surf"])),
                                   np.asarray(st["rot"]).T @ (w_out - np.asarray(st["w_surf"]))])
        np.testing.assert_allclose(arrays.y_obs[0], expect_y, rtol=1e-5, atol=1e-4)
        np.testing.assert_allclose(arrays.world_in[0], np.r_[v_in, w_in], atol=1e-6)
        np.testing.assert_allclose(arrays.world_out[0], np.r_[v_out, w_out], atol=1e-6)
        np.testing.assert_allclose(arrays.distance[0], np.hypot(0.01, 0.02), atol=1e-9)
        if name == "durr2026":  # the "nakashima" kind ignores the racket's spin
            assert arrays.x.shape == (1, 6)
            np.testing.assert_allclose(arrays.x[0, 3:6], rot.T @ w_in, rtol=1e-5)
        else:
            assert arrays.x.shape == (1, 8)
            np.testing.assert_allclose(arrays.x[0, 3:6], rot.T @ (w_in - r_ang), rtol=1e-5)


def test_skipped_contacts_are_counted_with_reasons(synthetic):
    ds, _ = synthetic
    seg = dict(ds.segments)
    conf = seg["spin_conf"].copy()
    # session 0: incoming spin unknown; session 1: outgoing spin unknown
    conf[(seg["session_id"] == 0) & (seg["end_event_id"] >= 0)] = 0.0
    conf[(seg["session_id"] == 1) & (seg["start_event_id"] >= 0)] = 0.2
    obs = dict(ds.observations)
    # session 2: only 3 samples before the contact
    drop = np.flatnonzero((obs["session_id"] == 2) & (obs["t"] < 1.0))[:-3]
    keep = np.ones(len(obs["t"]), bool)
    keep[drop] = False
    obs = {k: v[keep] for k, v in obs.items()}
    bad = ds.replace(segments=dict(seg, spin_conf=conf), observations=obs)
    arrays = contact_arrays(bad, "conti2026")
    assert arrays.counts() == {"low_spin_conf_in": 1, "low_spin_conf_out": 1, "few_incoming_samples": 1}
    assert arrays.skipped["low_spin_conf_in"] == [0] and arrays.skipped["few_incoming_samples"] == [2]
    assert len(arrays) == 9 and 2 not in arrays.event_id
    assert "few_incoming_samples" in arrays.summary()
    loose = contact_arrays(bad, "conti2026", fit=ContactFit(min_spin_conf=0.0, min_samples=3, degree=1))
    assert loose.counts() == {} and len(loose) == 12
    with pytest.raises(ValueError, match="min_samples"):
        ContactFit(degree=2, min_samples=3)
