"""The resumable rollout: halves equal the whole, per-ball parameters equal single balls, the lean
step equals the reference step, time does not drift, new values never recompile."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, Execution, Racket, Record, init_state, load_model, per_ball_axes, rollout, simulate
from ttsim_jax.effects import make
from ttsim_jax.kernel.rollout import _rollout
from ttsim_jax.physics.events import NONE, RACKET, TABLE

import padding as shared
from padding import pad_balls

B = 64
N = 400


def shots(n=B, seed=0):
    """Serves and drives from the near end, some with enough speed to reach the far racket."""
    rng = np.random.default_rng(seed)
    pos = np.stack([rng.uniform(-1.6, -1.2, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0.05, 0.45, n)], -1)
    vel = np.stack([rng.uniform(3, 14, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-3, 2.5, n)], -1)
    spin = rng.uniform(-500, 500, (n, 3))
    return Ball.create(pos, vel, spin)


def two_rackets(n_steps, dt=1e-3):
    """A racket at each end, moving at constant velocity, as a (T, 2, ...) schedule."""
    rot_far = jnp.diag(jnp.array([-1.0, -1.0, 1.0]))
    far = Racket.create(jnp.array([1.55, 0.0, 0.15]), rot=rot_far, vel=jnp.array([-1.0, 0.0, 0.5]),
                        ang_vel=jnp.array([0.0, 8.0, 0.0]), face=(0.3, 0.3))
    near = Racket.create(jnp.array([-1.6, 0.0, 0.2]), vel=jnp.array([1.0, 0.0, 0.3]), face=(0.3, 0.3))
    both = jax.tree.map(lambda a, b: jnp.stack([a, b]), far, near)
    t = jnp.arange(n_steps)[:, None, None] * dt
    sched = jax.tree.map(lambda a: jnp.broadcast_to(a, (n_steps,) + a.shape), both)
    return sched.replace(pos=both.pos[None] + t * both.vel[None])


# Two compiled float64 shapes serve most tests: B balls for N steps with the two rackets, with
# shared parameters, and with per-ball parameters and rackets (recorded, in one block).
PER_BALL = ("table.e0", "aero.rho_air", "effects.0.wind")


@pytest.fixture(scope="module")
def model():
    """conti2026 in moving air (an effect acting in the flight)."""
    return load_model("conti2026").replace(effects=(make("air_flow"),))


@pytest.fixture(scope="module")
def whole(model):
    state = init_state(shots())
    return rollout(model, state, N, 1e-3, two_rackets(N))


def with_values(model, e0, rho, wind):
    return model.replace(table=model.table.replace(e0=e0), aero=model.aero.replace(rho_air=rho),
                         effects=(model.effects[0].replace(wind=wind),))


def per_ball_rollout(model, batched, balls, block_size=0):
    """``batched`` (``model`` with (B,) values of PER_BALL) and a racket schedule per ball."""
    sched = jax.tree.map(lambda a: jnp.broadcast_to(a[None], (B,) + a.shape), two_rackets(N))
    return rollout(batched, init_state(balls), N, 1e-3, sched, model_axes=per_ball_axes(model, *PER_BALL),
                   execution=Execution(block_size=block_size), record=Record(every=100))


# three parameter sets, ball i gets set i % 3; balls 0-2 are one shot (so it ends in three places)
SETS = dict(e0=jnp.array([0.85, 0.93, 0.99]), rho=jnp.array([1.1, 1.2, 1.3]),
            wind=jnp.array([[0.5, 0.0, 0.0], [0.0, 0.0, 0.0], [-0.5, 0.3, 0.0]]))
PICK = np.arange(B) % 3


def per_ball_shots():
    return jax.tree.map(lambda a: a.at[1:3].set(a[0]), shots())


@pytest.fixture(scope="module")
def per_ball(model):
    """(batched model, rollout) of the per-ball shape, in one block."""
    batched = with_values(model, *(v[PICK] for v in SETS.values()))
    return batched, per_ball_rollout(model, batched, per_ball_shots())


def test_two_halves_equal_one_rollout(model, whole):
    sched = two_rackets(N)
    half = jax.tree.map(lambda a: a[N // 2:], sched)
    s1, o1 = rollout(model, init_state(shots()), N // 2, 1e-3, sched)
    s2, o2 = rollout(model, s1, N // 2, 1e-3, half)
    s, o = whole
    np.testing.assert_allclose(np.asarray(s2.ball.as_array()), np.asarray(s.ball.as_array()), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(s2.status), np.asarray(s.status))
    assert int(s2.step) == N and float(s2.time) == pytest.approx(float(s.time), abs=1e-15)
    # the two logs, concatenated per ball, are the one log
    n_events = 0
    for i in range(B):
        k1, k2 = int(o1.events.count[i]), int(o2.events.count[i])
        kinds = np.concatenate([np.asarray(o1.events.kind[i, :k1]), np.asarray(o2.events.kind[i, :k2])])
        times = np.concatenate([np.asarray(o1.events.time[i, :k1]), np.asarray(o2.events.time[i, :k2])])
        k = int(o.events.count[i])
        assert k == k1 + k2
        np.testing.assert_array_equal(kinds, np.asarray(o.events.kind[i, :k]))
        np.testing.assert_allclose(times, np.asarray(o.events.time[i, :k]), atol=1e-12)
        n_events += k
    kinds = np.asarray(o.events.kind)
    assert n_events > B and (kinds == RACKET).any() and (kinds == TABLE).any()


def test_lean_step_equals_reference_step(model, whole):
    state = init_state(shots())
    ref_state, ref = rollout(model, state, N, 1e-3, two_rackets(N), execution=Execution(reference=True))
    s, o = whole
    np.testing.assert_array_equal(np.asarray(o.events.kind), np.asarray(ref.events.kind))
    np.testing.assert_array_equal(np.asarray(o.events.count), np.asarray(ref.events.count))
    np.testing.assert_allclose(np.asarray(o.events.pre.pos), np.asarray(ref.events.pre.pos), atol=1e-12)
    np.testing.assert_allclose(np.asarray(s.ball.as_array()), np.asarray(ref_state.ball.as_array()), atol=1e-10)


def test_execution_and_record_options_are_values_and_the_loose_keywords_are_gone(model, whole):
    """``Execution`` and ``Record`` are compared and hashed by value (equal options share the
    compiled program: an equal ``Record`` built anew compiles nothing); the keywords they replaced
    (``reference=``, ``record_every=``, ``sample_residual=``) are a TypeError naming them; an
    unknown value is a ValueError naming it."""
    assert Execution(reference=True) == Execution(reference=True)
    assert hash(Execution(fused=False, block_size=0)) == hash(Execution(fused=False, block_size=0))
    assert Execution() != Execution(remat=False)
    assert Record(every=5, max_events=3) == Record(every=5, max_events=3) != Record(every=5)
    assert hash(Record(until_events=1)) == hash(Record(until_events=1))
    rollout(model, init_state(shots()), N, 1e-3, two_rackets(N))
    size = _rollout._cache_size()
    rollout(model, init_state(shots()), N, 1e-3, two_rackets(N), record=Record(every=0, max_events=8))
    assert _rollout._cache_size() == size
    for old in (dict(reference=True), dict(record_every=10), dict(sample_residual=True), dict(refrence=True)):
        with pytest.raises(TypeError, match=next(iter(old))):
            rollout(model, init_state(shots()), N, 1e-3, **old)
    with pytest.raises(ValueError, match="contact_capacity"):
        Execution(contact_capacity=0)
    with pytest.raises(ValueError, match=r"Record\(every=...\) must be an int >= 0, got -1"):
        Record(every=-1)
    with pytest.raises(TypeError, match="record must be a ttsim_jax.Record"):
        rollout(model, init_state(shots()), N, 1e-3, record=dict(every=10))


def test_single_buffer_equals_loop_of_buffers(model, whole):
    """The branch-free buffering of accelerators: one buffer of a single row per step, the whole
    batch whenever two or more balls are flagged in a step (often, with 64 balls and two rackets),
    gives the events and states of the CPU's loop of buffers."""
    s1, o1 = rollout(model, init_state(shots()), N, 1e-3, two_rackets(N),
                     execution=Execution(buffering="single", contact_capacity=1))
    s, o = whole
    np.testing.assert_array_equal(np.asarray(o1.events.kind), np.asarray(o.events.kind))
    np.testing.assert_allclose(np.asarray(o1.events.time), np.asarray(o.events.time), atol=1e-12)
    np.testing.assert_array_equal(np.asarray(s1.status), np.asarray(s.status))
    np.testing.assert_allclose(np.asarray(s1.ball.as_array()), np.asarray(s.ball.as_array()), atol=1e-10)
    with pytest.raises(ValueError, match="buffering"):
        rollout(model, init_state(shots()), N, 1e-3, execution=Execution(buffering="sometimes"))


def test_until_events_freezes_each_ball_at_its_event(model, whole):
    """A ball stops advancing after the step of its first event (``until_events=1``): its log holds
    the events of that step (a second one within the same step, such as a net crossing just before
    a bounce) as the full rollout logs them and nothing after; balls without an event run as before."""
    s1, o1 = rollout(model, init_state(shots()), N, 1e-3, two_rackets(N), record=Record(until_events=1))
    s, o = whole
    count, full = np.asarray(o1.events.count), np.asarray(o.events.count)
    assert (full >= 2).sum() > B // 4  # most balls would have gone on to a second event
    assert np.all((count >= np.minimum(full, 1)) & (count <= full))
    times, more = np.asarray(o.events.time), count > 1
    assert np.all(times[more, np.maximum(count - 1, 0)[more]] - times[more, 0] < 1e-3)
    assert count.sum() < full.sum()
    np.testing.assert_array_equal(np.asarray(o1.events.kind[:, 0]), np.asarray(o.events.kind[:, 0]))
    np.testing.assert_allclose(np.asarray(o1.events.time[:, 0]), np.asarray(o.events.time[:, 0]), atol=1e-12)
    np.testing.assert_allclose(np.asarray(o1.events.post.vel[:, 0]), np.asarray(o.events.post.vel[:, 0]),
                               atol=1e-12)
    none = full == 0
    # within rounding: the two are different programs, which XLA may fuse (and contract into
    # multiply-adds) differently
    np.testing.assert_allclose(np.asarray(s1.ball.pos)[none], np.asarray(s.ball.pos)[none], rtol=0, atol=1e-12)
    # a frozen ball is where its event step left it: within one step's flight of its logged event
    hit = full > 0
    gap = np.linalg.norm(np.asarray(s1.ball.pos)[hit] - np.asarray(o.events.post.pos[:, 0])[hit], axis=-1)
    assert gap.max() < 0.03 and not np.allclose(np.asarray(s1.ball.pos)[hit], np.asarray(s.ball.pos)[hit])
    with pytest.raises(ValueError, match="until_events"):
        rollout(model, init_state(shots()), N, 1e-3, record=Record(max_events=2, until_events=3))


@pytest.mark.slow  # 33 s of compilation; test_lean_step_equals_reference_step checks the same on 64 shots
def test_lean_step_equals_reference_on_thousands_of_shots():
    """Event sequences of 2,048 random shots with two rackets, float32: the lean step (exact
    detection only where a gap changes sign, in a small buffer that overflows on busy steps) and the
    reference step (exact detection for every ball) agree event for event."""
    m = load_model("conti2026", dtype=jnp.float32)
    balls = jax.tree.map(lambda a: a.astype(jnp.float32), shots(2048, seed=3))
    sched = jax.tree.map(lambda a: a.astype(jnp.float32), two_rackets(600))
    # fused=False: at 2,048 balls "auto" would take the fused path on a CPU, and the lean step is what is tested
    lean, lo = rollout(m, init_state(balls), 600, 1e-3, sched, execution=Execution(contact_capacity=32, fused=False))
    ref, ro = rollout(m, init_state(balls), 600, 1e-3, sched, execution=Execution(reference=True))
    np.testing.assert_array_equal(np.asarray(lo.events.kind), np.asarray(ro.events.kind))
    np.testing.assert_array_equal(np.asarray(lean.status), np.asarray(ref.status))
    # the two compile differently, so float32 rounding differs; a contact on the table's edge
    # turns a position difference into a normal difference 1/r (50 /m) times larger, and a
    # 0.6 s flight after it into about 2e-5 m
    np.testing.assert_allclose(np.asarray(lean.ball.pos), np.asarray(ref.ball.pos), atol=1e-4)
    assert int(np.sum(np.asarray(lo.events.kind) == RACKET)) > 500  # 682


def test_per_ball_parameters_equal_single_balls(model, per_ball):
    batched, (s, o) = per_ball
    for i in range(3):
        one = with_values(model, *(v[i] for v in SETS.values()))
        si, oi = rollout(one, init_state(per_ball_shots()), N, 1e-3, two_rackets(N))  # the shape of `whole`
        sel = PICK == i
        np.testing.assert_allclose(np.asarray(si.ball.pos)[sel], np.asarray(s.ball.pos)[sel], atol=1e-12)
        np.testing.assert_array_equal(np.asarray(oi.events.kind)[sel], np.asarray(o.events.kind)[sel])
    assert len({round(float(x), 6) for x in s.ball.pos[:3, 0]}) == 3
    # new per-ball values do not recompile
    size = _rollout._cache_size()
    per_ball_rollout(model, batched.replace(table=batched.table.replace(e0=batched.table.e0 * 0.99)),
                     per_ball_shots())
    assert _rollout._cache_size() == size


def test_per_ball_leaf_with_wrong_shape_is_refused(model):
    m = load_model("conti2026")
    with pytest.raises(ValueError, match=r"table.e0.*leading axis must be the batch \(4\)"):
        rollout(m, init_state(shots(4)), 10, model_axes=per_ball_axes(m, "table.e0"))
    # a leaf after a field the model leaves empty (no residual network): the check names it
    assert model.residual is None
    with pytest.raises(ValueError, match=r"\.effects\[0\]\.wind is per ball but has shape \(3,\)"):
        rollout(model, init_state(shots(4)), 10, model_axes=per_ball_axes(model, "effects.0.wind"))
    with pytest.raises(ValueError, match="no field 'table.nope'"):
        per_ball_axes(m, "table.nope")


def test_time_is_a_step_count_and_does_not_drift():
    m = load_model("conti2026", dtype=jnp.float32)
    s = init_state(pad_balls(Ball.create([[0.5, 0.0, 3.0]], [[0.0, 0.0, 0.0]], dtype=jnp.float32), shared.B))
    for _ in range(3):  # the suite's shared shape (padding.py), resumed
        s, _ = rollout(m, s, shared.N, 1e-3, shared.resting_racket(), record=Record(every=shared.RECORD))
    assert int(s.step) == 3 * shared.N
    assert float(s.time) == pytest.approx(3 * shared.N * 1e-3, abs=1e-6)
    # a float32 clock adding dt each step would be off by ~1.2e-4 s here
    clock = np.float32(0.0)
    for _ in range(3 * shared.N):
        clock = np.float32(clock + np.float32(1e-3))
    assert abs(float(clock) - 3 * shared.N * 1e-3) > 1e-4


def test_changing_dt_continues_from_the_current_time(model, whole):
    s, _ = whole  # N steps of 1 ms
    s, _ = rollout(model, s, N, 2e-3, two_rackets(N))  # the same compiled shape
    assert float(s.time) == pytest.approx(N * 1e-3 + N * 2e-3, abs=1e-12)


def test_simulate_is_init_state_then_rollout(model, whole):
    r = simulate(model, shots(), N, 1e-3, two_rackets(N))
    s, o = whole
    np.testing.assert_array_equal(np.asarray(r.final.pos), np.asarray(s.ball.pos))
    np.testing.assert_array_equal(np.asarray(r.events.kind), np.asarray(o.events.kind))
    assert int(np.sum(np.asarray(r.events.kind) != NONE)) == int(np.sum(np.minimum(np.asarray(o.events.count), 8)))


def test_blocks_of_balls_equal_the_whole_batch(model, per_ball):
    """Blocks (here 5 blocks of 13 balls, the last one padded with dead balls) with per-ball
    parameters and a per-ball racket schedule give the unblocked results."""
    batched, (s0, o0) = per_ball
    s1, o1 = per_ball_rollout(model, batched, per_ball_shots(), block_size=13)
    np.testing.assert_allclose(np.asarray(s1.ball.as_array()), np.asarray(s0.ball.as_array()), atol=1e-12)
    np.testing.assert_array_equal(np.asarray(o1.events.kind), np.asarray(o0.events.kind))
    np.testing.assert_array_equal(np.asarray(s1.status), np.asarray(s0.status))
    np.testing.assert_allclose(np.asarray(o1.trajectory.pos), np.asarray(o0.trajectory.pos), atol=1e-12)
    np.testing.assert_allclose(np.asarray(o1.times), np.asarray(o0.times))
    assert o1.trajectory.pos.shape == (B, N // 100, 3) and int(s1.step) == N
