"""The residual network inside the jitted rally kernel: same result as applied by hand, no
recompilation when swapping parameters, sigma in the event log, sampling."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, Execution, Racket, init_state, load_model, rollout, simulate
from ttsim_jax.fit.network_config import TrainConfig
from ttsim_jax.fit.network_training import train_residual
from ttsim_jax.reality.synthetic_contacts import make_synthetic_contacts, racket_base_fn
from ttsim_jax.physics.network import ResidualConfig, residual_outputs
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics.events import RACKET, TABLE
from ttsim_jax.kernel.rollout import _rollout
from ttsim_jax.kernel.ball_step import ball_properties

import padding as shared
from padding import simulate_shared

TINY = ResidualConfig(trunk=(16, 16), head_width=8, n_clusters=20, dropout=0.1)
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
    data = make_synthetic_contacts(1500, seed=0, base_fn=racket_base_fn(base.racket, radius, mass))
    tc = TrainConfig(batch_size=64, max_epochs=8, patience=50, learning_rate=3e-3, kmeans_iters=10)
    net, _ = train_residual(data["x"], data["y_base"], data["y_obs"], TINY, tc, progress=False)
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
        # the racket at the contact: the schedule's sample at the step's start, moved and turned on
        start = np.floor(float(ev.time[b, k]) / 1e-3) * 1e-3
        racket = racket_stage.advance(racket_at(start), ev.time[b, k] - start)
        st = racket_stage.racket_frame_state(base.racket, racket, radius, pre.pos, pre.vel, pre.spin)
        v_b, w_b = racket_stage.base_response(base.racket, st["v"], st["w"], st["d"], radius, mass)
        x = jnp.concatenate([st["v"], st["w"], st["d"]])[None]
        out = residual_outputs(net, x)
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
    sampled = simulate(model, balls(), N_STEPS, racket=schedule(), sample_key=key)
    other = simulate(model, balls(), N_STEPS, racket=schedule(), sample_key=jax.random.key(12))
    hits = racket_events(result)
    assert [e for e in racket_events(sampled)] == hits
    for b, k in hits:
        for r in (sampled, other):
            assert not np.allclose(np.asarray(r.events.post.spin[b, k]), np.asarray(result.events.post.spin[b, k]))
        assert not np.allclose(np.asarray(sampled.events.post.vel[b, k]), np.asarray(other.events.post.vel[b, k]))
    # sigma -> 0: the sampled contact equals the deterministic one
    sharp = model.replace(residual=net.replace(sigma_scale=jnp.zeros(6, jnp.float32)))
    quiet = simulate(sharp, balls(), N_STEPS, racket=schedule(), sample_key=key)
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
    one = simulate(model, balls(), N_STEPS, racket=schedule(), sample_key=key, execution=Execution(contact_capacity=1))
    default = simulate(model, balls(), N_STEPS, racket=schedule(), sample_key=key)
    np.testing.assert_array_equal(np.asarray(one.events.kind), np.asarray(default.events.kind))
    np.testing.assert_allclose(np.asarray(one.events.post.spin), np.asarray(default.events.post.spin), atol=1e-9)
    np.testing.assert_allclose(np.asarray(one.final.pos), np.asarray(default.final.pos), atol=1e-12)
    # reversed order, same ids: the same draws per ball
    order = np.arange(4)[::-1]
    rev = jax.tree.map(lambda a: a[order], balls())
    state, out = rollout(model, init_state(rev, ball_id=order), N_STEPS, 1e-3, schedule(), sample_key=key)
    np.testing.assert_allclose(np.asarray(out.events.post.spin)[order], np.asarray(default.events.post.spin),
                               atol=1e-9)


@pytest.mark.slow  # 34 s; accelerators' buffering (a CPU never takes it), the network-free case stays in the default run
def test_single_buffering_runs_the_network_on_the_racket_rows_only(setup):
    """Accelerators' buffering evaluates the network on B/256 rows, those with a racket contact
    (``step.NET_FRACTION``): its events, sampled draws included, equal the CPU loop's (the network on
    every buffer row), both when a step's racket balls fit those rows (shots spread in time) and
    when they do not (copies of the same shots, meeting the racket in the same steps: the whole
    batch runs)."""
    from ttsim_jax.kernel import step as kstep

    _, _, model, _ = setup
    b, key = 128, jax.random.key(7)
    copy = jnp.arange(b) // 4
    four = jax.tree.map(lambda a: a[jnp.arange(b) % 4], balls())
    spread = four.replace(pos=four.pos.at[:, 0].add(-0.012 * copy))  # a copy per 1.5 ms or so
    same = four.replace(pos=four.pos.at[:, 1].add(1e-4 * copy))
    assert 64 // kstep.NET_FRACTION < 32  # the copies of a shot do not fit the network's rows at once
    for shots, spread_out in ((spread, True), (same, False)):
        kw = dict(sample_key=key)
        s0, o0 = rollout(model, init_state(shots), N_STEPS, 1e-3, schedule(),
                         execution=Execution(contact_capacity=64, buffering="loop"), **kw)
        s1, o1 = rollout(model, init_state(shots), N_STEPS, 1e-3, schedule(),
                         execution=Execution(contact_capacity=64, buffering="single"), **kw)
        kind = np.asarray(o0.events.kind)
        step = np.floor(np.asarray(o0.events.time)[kind == RACKET] / 1e-3 + 1e-9).astype(int)
        assert len(step) > 40  # many racket contacts, with their network corrections
        assert (np.bincount(step).max() <= 3) == spread_out, np.bincount(step).max()
        np.testing.assert_array_equal(np.asarray(o1.events.kind), kind)
        np.testing.assert_allclose(np.asarray(o1.events.time), np.asarray(o0.events.time), atol=1e-12)
        for field in ("vel", "spin"):
            np.testing.assert_allclose(np.asarray(getattr(o1.events.post, field)),
                                       np.asarray(getattr(o0.events.post, field)), atol=1e-9)
        np.testing.assert_allclose(np.asarray(o1.events.sigma), np.asarray(o0.events.sigma), atol=1e-12)
        np.testing.assert_allclose(np.asarray(s1.ball.as_array()), np.asarray(s0.ball.as_array()), atol=1e-9)


def test_network_rows_are_gathered_from_anywhere_in_the_buffer(setup):
    """The contact buffer's rows in one step, ten table bounces first and two racket contacts
    last: the network evaluated on two rows gathered from the racket contacts gives what it gives
    on every row (sampled draws included), and nothing on the table rows."""
    from ttsim_jax.kernel.axes import resolve_axes
    from ttsim_jax.kernel.ball_step import flight
    from ttsim_jax.kernel.step import _events, _StepInputs

    _, _, model, _ = setup
    rk = jax.tree.map(lambda a: a[None], racket_at(0.0))  # one racket, normal -x, face centre (1.6, 0, 0.2)
    n_table = 10
    pos = [[-1.0 + 0.1 * i, 0.1, 0.0215] for i in range(n_table)] + [[1.5755, 0.01, 0.2], [1.5755, -0.02, 0.21]]
    vel = [[1.0, 0.0, -2.0]] * n_table + [[6.0, 0.0, 0.2], [5.0, 0.1, 0.0]]
    ball = Ball.create(pos, vel, [[0.0, 50.0, 0.0]] * len(pos))
    b = len(pos)
    axes = resolve_axes(model, None)
    free = jax.vmap(flight, in_axes=(None, 0, None, None))(model.replace(residual=None), ball, 0.0, 1e-3)
    inputs = _StepInputs(ball, jnp.ones(b, bool), free, rk, jnp.arange(b) + 100, 0.0, 1e-3, jax.random.key(2))
    every = _events(model, axes, inputs, jnp.arange(b), sample=True)
    gathered = _events(model, axes, inputs, jnp.arange(b), sample=True, net_rows=2)
    kind = np.asarray(every.events.kind)  # (rows, events in the step)
    assert list(kind[:, 0]) == [TABLE] * n_table + [RACKET] * 2 and np.all(kind[:, 1:] == 0)
    for a, g in zip(jax.tree.leaves(every), jax.tree.leaves(gathered)):
        np.testing.assert_allclose(np.asarray(g), np.asarray(a), atol=1e-12)
    sigma = np.asarray(every.events.sigma)[:, 0]
    assert np.all(sigma[n_table:] != 0.0) and np.all(sigma[:n_table] == 0.0)
