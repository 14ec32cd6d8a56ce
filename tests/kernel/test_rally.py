import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import (Ball, Execution, Racket, RacketPolicy, Record, init_state, load_model, rollout, simulate,
                       stack_models)
from ttsim_jax.physics.events import FLOOR, NET, RACKET, TABLE
from ttsim_jax.kernel.rollout import _rollout, memory_bytes

from padding import B, N, RECORD, pad_balls, simulate_shared


def serve_batch(n=B, seed=0):
    rng = np.random.default_rng(seed)
    pos = np.stack([rng.uniform(-1.6, -1.3, n), rng.uniform(-0.4, 0.4, n), rng.uniform(0.15, 0.35, n)], -1)
    vel = np.stack([rng.uniform(4, 9, n), rng.uniform(-1, 1, n), rng.uniform(-2, 1, n)], -1)
    spin = rng.uniform(-300, 300, (n, 3))
    return Ball.create(pos, vel, spin)


# Most tests run the suite's shared compiled shape (padding.py): B balls, N steps, the racket
# schedule below (f64 unless a test is about dtypes); a ball of a smaller scenario is padded with
# balls that never meet it.


def racket_schedule(n, x=1.6):
    racket = Racket.create(jnp.array([x, 0.0, 0.2]), rot=jnp.diag(jnp.array([-1.0, -1.0, 1.0])),
                           vel=jnp.array([-0.5, 0.0, 0.1]))
    t = jnp.arange(n)[:, None] * 1e-3
    return jax.tree.map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), racket).replace(
        pos=racket.pos + t * racket.vel)


def pad(balls):
    return pad_balls(balls, B)


@pytest.mark.parametrize("name", ["nakashima2011", "durr2026", "conti2026"])
def test_vmapped_batch_equals_each_ball_alone(name):
    """Each ball, run in a batch of copies of itself, ends exactly as it does among the others
    (no ball sees another's contacts, buffers or events); one compiled shape."""
    m = load_model(name)
    balls = serve_batch()
    sched = racket_schedule(N)
    batch = simulate_shared(m, balls, racket=sched)
    assert TABLE in set(np.asarray(batch.events.kind).ravel().tolist())
    for i in range(B):
        alone = simulate_shared(m, jax.tree.map(lambda a: jnp.repeat(a[i:i + 1], B, 0), balls), racket=sched)
        np.testing.assert_allclose(np.asarray(alone.final.as_array()[0]), np.asarray(batch.final.as_array()[i]),
                                   rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(np.asarray(alone.events.kind[0]), np.asarray(batch.events.kind[i]))


def test_no_retrace_when_parameters_or_dt_change():
    a = load_model("conti2026")
    sched = racket_schedule(N)
    simulate_shared(a, serve_batch(), 1e-3, racket=sched)
    size = _rollout._cache_size()
    b = a.replace(table=a.table.replace(e0=a.table.e0 * 0.9), aero=a.aero.replace(rho_air=a.aero.rho_air * 1.1))
    simulate_shared(b, serve_batch(seed=1), 2e-3, racket=sched)
    assert _rollout._cache_size() == size


def test_batched_parameters_domain_randomisation():
    base = load_model("conti2026")
    scales = (0.9, 1.0, 1.05, 0.95, 1.02, 0.98, 0.92, 1.03)
    models = [base.replace(table=base.table.replace(e0=base.table.e0 * s)) for s in scales]
    balls = jax.tree.map(lambda a: jnp.repeat(a[:1], B, 0), serve_batch(1))
    sched = racket_schedule(N)
    r = simulate_shared(stack_models(models), balls, racket=sched, model_axes=0)
    for i, mi in enumerate(models):
        one = simulate_shared(mi, balls, racket=sched)  # the shared shape: every row is ball 0
        np.testing.assert_allclose(np.asarray(one.final.pos[0]), np.asarray(r.final.pos[i]), atol=1e-12)
    assert len({round(float(x), 6) for x in r.final.pos[:, 0]}) == len(scales)


@pytest.mark.parametrize("name", ["nakashima2011", "durr2026", "conti2026"])
def test_no_nan_for_extreme_inputs(name, dtype):
    m = load_model(name, dtype=dtype)
    balls = Ball.create(
        [[-1.3, 0.0, 0.3], [0.2, 0.1, 0.02], [0.0, 0.0, 0.5], [-1.3, 0.3, 0.1], [0.5, 0.0, 0.02], [0.0, 0.0, 0.3]],
        [[35.0, 0.0, -2.0], [0.0, 0.0, 0.0], [0.0, 0.0, -8.0], [35.0, -5.0, 3.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
        [[0.0, 1000.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-700.0, -700.0, 0.0], [0.0, 0.0, 1000.0],
         [1000.0, 0.0, 0.0]], dtype=dtype)
    r = simulate_shared(m, balls, racket=racket_schedule(N))
    for leaf in jax.tree.leaves((r.final, r.events.pre, r.events.post)):
        assert np.all(np.isfinite(np.asarray(leaf)))
    # a ball at rest on the table stays there; a vertical drop bounces straight up
    assert float(r.final.pos[1, 2]) == pytest.approx(0.02, abs=1e-3)
    assert int(r.events.kind[2, 0]) == TABLE
    assert abs(float(r.events.post.vel[2, 0, 0])) < 1e-3


def test_invalid_state_is_flagged_and_frozen_not_nan():
    m = load_model("conti2026")
    b = pad(Ball.create([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5]], [[1.0, 0.0, 0.0], [np.nan, 0.0, 0.0]]))
    r = simulate_shared(m, b, racket=racket_schedule(N))
    assert bool(r.alive[0]) and not bool(r.alive[1])
    assert int(r.status[1]) == 6  # invalid
    assert np.all(np.isfinite(np.asarray(r.final.pos[0])))


def first_bounce(m, dt, integrator="rk4"):
    """(bounce point, velocity and spin after it) of a topspin drive, run N steps at a time (the
    rollout resumes; dt is traced, so every step size shares one compiled shape)."""
    b = pad(Ball.create([[-1.5, -0.2, 0.3]], [[9.0, 0.8, 1.2]], [[50.0, 250.0, -60.0]], dtype=m.ball.mass.dtype))
    state = init_state(b)
    for _ in range(int(np.ceil(0.3 / (N * dt)))):  # the bounce comes at about 0.2 s
        state, out = rollout(m, state, N, dt, racket_schedule(N), integrator=integrator, record=Record(every=RECORD))
        kinds = np.asarray(out.events.kind[0]).tolist()
        if TABLE in kinds:
            k = kinds.index(TABLE)
            return tuple(np.asarray(x[0, k]) for x in (out.events.pre.pos, out.events.post.vel, out.events.post.spin))
    raise AssertionError(f"no bounce within 0.3 s at dt = {dt}")


@pytest.mark.parametrize("name", ["nakashima2011", "conti2026"])
def test_dt_convergence_landing_point(name):
    m = load_model(name)
    p1, v1, w1 = first_bounce(m, 1e-3)
    p4, v4, w4 = first_bounce(m, 0.25e-3)
    assert np.linalg.norm(p1 - p4) < 1e-3  # bounce point
    assert np.linalg.norm(v1 - v4) < 1e-2  # velocity after the bounce
    assert np.linalg.norm(w1 - w4) < 1.0  # spin after the bounce


def test_racket_policy_inside_scan_matches_schedule():
    m = load_model("conti2026")
    balls = pad(Ball.create([[-1.2, 0.0, 0.3], [-1.2, 0.05, 0.3]], [[6.0, 0.0, 1.0], [6.5, 0.0, 1.0]],
                            [[0.0, 150.0, 0.0], [0.0, 100.0, 0.0]]))
    sched = racket_schedule(N)

    def policy(params, ball, t):
        r0 = jax.tree.map(lambda a: a[0], sched)
        return jax.tree.map(lambda a: a[None], r0.replace(pos=r0.pos + t * params["vel"]))

    r1 = simulate_shared(m, balls, racket=sched)
    r2 = simulate_shared(m, balls, racket=RacketPolicy(params={"vel": sched.vel[0]}, fn=policy))
    np.testing.assert_allclose(np.asarray(r1.final.pos), np.asarray(r2.final.pos), atol=1e-9)
    for i in range(2):
        assert np.asarray(r1.events.kind[i, :2]).tolist() == [TABLE, RACKET]


def test_event_log_records_sequence_and_counts_overflow():
    m = load_model("conti2026")
    b = Ball.create([[0.5, 0.0, 0.05]], [[0.0, 0.0, 0.0]])  # bounces in place many times
    r = simulate_shared(m, b, racket=racket_schedule(N))
    assert r.events.kind.shape[1] == 8
    assert np.all(np.asarray(r.events.kind[0]) == TABLE)
    assert int(r.events.count[0]) > 8
    times = np.asarray(r.events.time[0])
    assert np.all(np.diff(times) > 0)


def test_net_is_reported_not_modelled():
    m = load_model("conti2026")
    r = simulate_shared(m, Ball.create([[-0.6, 0.0, 0.08]], [[5.0, 0.0, 0.5]]), racket=racket_schedule(N))
    kinds = np.asarray(r.events.kind[0]).tolist()
    assert NET in kinds
    k = kinds.index(NET)
    # passes through unchanged (to the last bit or two: XLA may compute the logged path point in two
    # fused loops, which round differently; a modelled net would change it by far more)
    np.testing.assert_allclose(np.asarray(r.events.post.vel[0, k]), np.asarray(r.events.pre.vel[0, k]),
                               rtol=1e-14, atol=0)
    assert float(r.events.post.vel[0, k, 0]) > 4.0


def test_recording_above_memory_budget_is_refused_with_size():
    m = load_model("conti2026")
    b = serve_batch(2)
    with pytest.raises(ValueError, match=r"needs .* GiB.*budget"):
        simulate(m, b, 1000, record=Record(every=1), execution=Execution(memory_budget_bytes=1000))
    # the shapes of what the rollout returns (traced, not compiled)
    r = jax.eval_shape(lambda b: simulate(m, b, 1000, record=Record(every=100)), b)
    assert r.trajectory.pos.shape == (2, 10, 3)
    # the estimate is the size of what the rollout returns
    need = memory_bytes(2, 1000, 100, 8, r.final.pos.dtype)
    size = lambda tree: sum(math.prod(x.shape) * x.dtype.itemsize for x in jax.tree.leaves(tree))  # noqa: E731
    assert need["state"] == size(r.state)
    assert need["event_log"] == size(r.events)
    assert need["recording"] == size(r.trajectory)
    # an event log too large for the budget is refused too, before anything compiles
    with pytest.raises(ValueError, match=r"event log 0\.\d\d GiB.*budget"):
        simulate(m, b, 1000, record=Record(max_events=10**6), execution=Execution(memory_budget_bytes=2**20))


def test_the_kernels_default_budget_is_the_packages(monkeypatch):
    """Without a budget of its own, a rollout is held to the one ``ttsim --memory-budget`` and
    ``TTSIM_MEMORY_BUDGET`` set (``ttsim_jax.sizes``), and says so."""
    m = load_model("conti2026")
    b = serve_batch(2)
    monkeypatch.setenv("TTSIM_MEMORY_BUDGET", "1M")
    with pytest.raises(ValueError, match=r"budget of 0\.00 GiB \(set by --memory-budget or TTSIM_MEMORY_BUDGET\)"):
        simulate(m, b, 1000, record=Record(max_events=10**6))
    monkeypatch.setenv("TTSIM_MEMORY_BUDGET", "64G")
    shapes = jax.eval_shape(lambda b: simulate(m, b, 1000, record=Record(max_events=10**6)), b)
    assert shapes.events.pre.pos.shape[1] == 10**6


def test_floor_stops_the_ball():
    m = load_model("conti2026")
    # off the near end of the table, away from the racket
    r = simulate_shared(m, Ball.create([[-1.0, 0.0, 0.3]], [[-3.0, 0.0, 0.0]]), racket=racket_schedule(N))
    assert not bool(r.alive[0]) and int(r.status[0]) == FLOOR
    assert float(r.final.pos[0, 2]) == pytest.approx(-0.74, abs=1e-6)


def test_time_of_impact_is_refined_beyond_linear():
    # The Newton step on the Hermite path puts the bounce point within microns even at 4 ms
    # steps; a linear time of impact alone would be off by about 0.05 mm here.
    m = load_model("conti2026", dtype=jnp.float64)
    assert np.linalg.norm(first_bounce(m, 4e-3)[0] - first_bounce(m, 5e-5)[0]) < 5e-6
