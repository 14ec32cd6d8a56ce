"""The residual network inside the jitted rally kernel: same result as applied by hand, no
recompilation when swapping parameters, sigma in the event log, sampling."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, Racket, init_state, load_model, rollout, simulate
from ttsim_jax.fit import residual as F
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics import residual as R
from ttsim_jax.physics.events import RACKET, TABLE
from ttsim_jax.kernel.rollout import _rollout
from ttsim_jax.kernel.step import ball_properties

import padding as shared
from padding import simulate_shared

TINY = R.ResidualConfig(trunk=(16, 16), head_width=8, n_clusters=20, dropout=0.1)
N_STEPS = 600
RACKET0 = dict(pos=[1.6, 0.0, 0.2], vel=[-0.5, 0.0, 0.1], ang_vel=[0.0, 5.0, 3.0])


def racket_at(t):
    """The racket moving at constant velocity: its state at time t (what the schedule samples)."""
    return Racket.create(jnp.asarray(RACKET0["pos"]) + t * jnp.asarray(RACKET0["vel"]),
                         rot=jnp.diag(jnp.array([-1.0, -1.0, 1.0])), vel=jnp.asarray(RACKET0["vel"]),
                         ang_vel=jnp.asarray(RACKET0["ang_vel"]))


def schedule(n=N_STEPS):
    return jax.vmap(racket_at)(jnp.arange(n) * 1e-3)


def balls():
    """Three serves that bounce on the table and then hit the racket, one that misses it."""
    return Ball.create([[-1.4, 0.0107, 0.2944], [-1.4, 0.0357, 0.2930], [-1.4, -0.02, 0.30], [-1.4, 0.5, 0.3]],
                       [[7.154, 0.0, 0.957], [8.210, 0.0, 0.155], [7.6, 0.0, 0.5], [8.0, 0.0, 0.5]],
                       [[128.4, 192.7, 137.5], [-9.5, -28.6, -30.5], [0.0, 80.0, 0.0], [0.0, 0.0, 0.0]])


@pytest.fixture(scope="module")
def setup():
    """conti2026 with a small residual network trained on synthetic contacts of its own base model."""
    base = load_model("conti2026")
    radius, mass = (float(v) for v in ball_properties(base))
    data = F.make_synthetic_contacts(1500, seed=0, base_fn=F.racket_base_fn(base.racket, radius, mass))
    tc = F.TrainConfig(batch_size=64, max_epochs=8, patience=50, learning_rate=3e-3, kmeans_iters=10)
    net, _ = F.train_residual(data["x"], data["y_base"], data["y_obs"], TINY, tc, progress=False)
    model = base.replace(residual=net)
    result = simulate(model, balls(), N_STEPS, racket=schedule())
    return base, net, model, result


def racket_events(result):
    kinds = np.asarray(result.events.kind)
    return [(b, int(k)) for b in range(kinds.shape[0]) for k in np.flatnonzero(kinds[b] == RACKET)]


def test_kernel_matches_network_applied_by_hand(setup):
    base, net, model, result = setup
    hits = racket_events(result)
    assert {b for b, _ in hits} == {0, 1, 2}, np.asarray(result.events.kind)
    radius, mass = ball_properties(base)
    ev = result.events
    for b, k in hits:
        pre = jax.tree.map(lambda a: a[b, k], ev.pre)
        racket = racket_at(ev.time[b, k])
        st = racket_stage.racket_frame_state(base.racket, racket, radius, pre.pos, pre.vel, pre.spin)
        v_b, w_b = racket_stage.base_response(base.racket, st["v"], st["w"], st["d"], radius, mass)
        x = jnp.concatenate([st["v"], st["w"], st["d"]])[None]
        out = R.residual_outputs(net, x)
        assert float(out["beta"][0]) > 0.5  # the network really acts on this contact
        assert float(jnp.linalg.norm(out["dv"][0])) > 1e-3
        v_post = st["rot"] @ (v_b + out["dv"][0]) + st["v_surf"]
        w_post = st["rot"] @ (w_b + out["dw"][0]) + st["w_surf"]
        np.testing.assert_allclose(np.asarray(ev.post.vel[b, k]), np.asarray(v_post), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(np.asarray(ev.post.spin[b, k]), np.asarray(w_post), rtol=1e-6, atol=1e-5)
        sigma = np.concatenate([np.asarray(out["sigma_v"][0]), np.asarray(out["sigma_w"][0])])
        np.testing.assert_allclose(np.asarray(ev.sigma[b, k]), sigma, rtol=1e-6)
        np.testing.assert_allclose(np.asarray(ev.contact[b, k]), np.asarray(st["d"]), atol=1e-9)


def test_sigma_logged_for_racket_contacts_only(setup):
    _, _, _, result = setup
    kinds = np.asarray(result.events.kind)
    sigma = np.asarray(result.events.sigma)
    assert (kinds == TABLE).sum() >= 3 and (kinds == RACKET).sum() == 3
    assert np.all(sigma[kinds == RACKET] > 0.0)
    assert np.all(sigma[kinds != RACKET] == 0.0)
    base, _, _, _ = setup
    plain = simulate_shared(base, balls(), racket=schedule(shared.N))  # the suite's shared shape
    assert np.all(np.asarray(plain.events.sigma) == 0.0)
    # the correction changed the racket contacts and only them
    first_table = [int(np.flatnonzero(kinds[b] == TABLE)[0]) for b in range(3)]
    for b, k in enumerate(first_table):
        np.testing.assert_allclose(np.asarray(result.events.post.vel[b, k]), np.asarray(plain.events.post.vel[b, k]))
    for b, k in racket_events(result):
        assert not np.allclose(np.asarray(result.events.post.vel[b, k]), np.asarray(plain.events.post.vel[b, k]))


def test_swapping_residual_parameters_does_not_recompile(setup):
    _, net, model, result = setup
    size = _rollout._cache_size()
    keys = iter(jax.random.split(jax.random.key(3), 64))
    other = net.replace(variables=jax.tree_util.tree_map(
        lambda a: a * (1.0 + 0.1 * jax.random.normal(next(keys), a.shape, a.dtype)), net.variables),
        sigma_scale=net.sigma_scale * 2.0)
    again = simulate(model.replace(residual=other), balls(), N_STEPS, racket=schedule())
    assert _rollout._cache_size() == size
    (b, k), *_ = racket_events(result)
    assert not np.allclose(np.asarray(again.events.post.vel[b, k]), np.asarray(result.events.post.vel[b, k]))


def test_sampling_changes_post_states_unless_sigma_is_zero(setup):
    _, net, model, result = setup
    key = jax.random.key(11)
    sampled = simulate(model, balls(), N_STEPS, racket=schedule(), sample_residual=True, key=key)
    other = simulate(model, balls(), N_STEPS, racket=schedule(), sample_residual=True, key=jax.random.key(12))
    hits = racket_events(result)
    assert [e for e in racket_events(sampled)] == hits
    for b, k in hits:
        for r in (sampled, other):
            assert not np.allclose(np.asarray(r.events.post.spin[b, k]), np.asarray(result.events.post.spin[b, k]))
        assert not np.allclose(np.asarray(sampled.events.post.vel[b, k]), np.asarray(other.events.post.vel[b, k]))
    # sigma -> 0: the sampled contact equals the deterministic one
    sharp = model.replace(residual=net.replace(sigma_scale=jnp.zeros(6, jnp.float32)))
    quiet = simulate(sharp, balls(), N_STEPS, racket=schedule(), sample_residual=True, key=key)
    for b, k in hits:
        np.testing.assert_allclose(np.asarray(quiet.events.post.vel[b, k]), np.asarray(result.events.post.vel[b, k]),
                                   atol=1e-12)
        np.testing.assert_allclose(np.asarray(quiet.events.post.spin[b, k]),
                                   np.asarray(result.events.post.spin[b, k]), atol=1e-9)
        assert np.all(np.asarray(quiet.events.sigma[b, k]) == 0.0)


def test_sampled_correction_depends_on_the_ball_not_on_its_buffer_slot(setup):
    """A ball's sampled correction is drawn from its id and the step: the same with a one-row buffer
    (every busy step overflows to the full batch), with the default buffer, and with the balls
    in another order."""
    _, _, model, _ = setup
    key = jax.random.key(5)
    one = simulate(model, balls(), N_STEPS, racket=schedule(), sample_residual=True, key=key, contact_capacity=1)
    default = simulate(model, balls(), N_STEPS, racket=schedule(), sample_residual=True, key=key)
    np.testing.assert_array_equal(np.asarray(one.events.kind), np.asarray(default.events.kind))
    np.testing.assert_allclose(np.asarray(one.events.post.spin), np.asarray(default.events.post.spin), atol=1e-9)
    np.testing.assert_allclose(np.asarray(one.final.pos), np.asarray(default.final.pos), atol=1e-12)
    # reversed order, same ids: the same draws per ball
    order = np.arange(4)[::-1]
    rev = jax.tree.map(lambda a: a[order], balls())
    state, out = rollout(model, init_state(rev, ball_id=order), N_STEPS, 1e-3, schedule(), sample_residual=True,
                         key=key)
    np.testing.assert_allclose(np.asarray(out.events.post.spin)[order], np.asarray(default.events.post.spin),
                               atol=1e-9)
