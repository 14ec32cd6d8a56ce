"""The fused flight path (Pallas on a GPU, its body as plain XLA on a CPU) equals the reference path.

The comparison uses ``test_rollout``'s shots, racket schedule and compiled shape (64 balls, 400
steps), two seeds of them, so that its reference rollouts are the ones that module compiles.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, Execution, RacketPolicy, Record, init_state, load_model, per_ball_axes, rollout
from ttsim_jax import effects as fx
from ttsim_jax.kernel import fused
from ttsim_jax.kernel.plans import within_reach
from ttsim_jax.kernel.ball_step import flight, may_have_event
from ttsim_jax.physics.events import INVALID, NET, RACKET, TABLE
from ttsim_jax.policies import tracking_rackets, tracking_rackets_fn, tracking_rackets_reach
from test_rollout import B, N, shots, two_rackets

SEEDS = (0, 1)


@pytest.fixture(scope="module")
def model():
    return load_model("conti2026")


@pytest.fixture(scope="module")
def runs(model):
    """(reference, fused) rollouts of each seed's shots."""
    sched = two_rackets(N)
    out = []
    for seed in SEEDS:
        state = init_state(shots(B, seed))
        out.append((rollout(model, state, N, 1e-3, sched), rollout(model, state, N, 1e-3, sched, execution=Execution(fused=True))))
    return out


def _assert_same_rollout(ref, fus, atol):
    (rs, ro), (fs, fo) = ref, fus
    np.testing.assert_array_equal(np.asarray(fs.status), np.asarray(rs.status))
    np.testing.assert_array_equal(np.asarray(fs.alive), np.asarray(rs.alive))
    assert int(fs.step) == int(rs.step) and float(fs.time) == float(rs.time)
    np.testing.assert_allclose(np.asarray(fs.ball.as_array()), np.asarray(rs.ball.as_array()), rtol=atol, atol=atol)
    re, fe = ro.events, fo.events
    for name in ("kind", "count", "racket"):
        np.testing.assert_array_equal(np.asarray(getattr(fe, name)), np.asarray(getattr(re, name)), err_msg=name)
    np.testing.assert_allclose(np.asarray(fe.time), np.asarray(re.time), atol=atol)
    for name in ("pre", "post"):
        np.testing.assert_allclose(np.asarray(getattr(fe, name).as_array()), np.asarray(getattr(re, name).as_array()),
                                   rtol=atol, atol=atol, err_msg=name)


def test_fused_equals_reference_on_random_shots(runs):
    kinds = []
    for ref, fus in runs:
        _assert_same_rollout(ref, fus, atol=1e-9)  # float64: rounding of the two flight codes only
        kinds.append(np.asarray(ref[1].events.kind))
    kinds = np.concatenate(kinds)
    # the 256 shots bounce, meet rackets and cross the net
    assert (kinds == TABLE).sum() > 100 and (kinds == RACKET).sum() > 20 and (kinds == NET).any()


def per_ball_rackets(n_steps, rng):
    """(B, T, 2, ...) schedules: :func:`two_rackets` moved and sped up per ball (a few cm, a few
    tenths of m/s), as the environment gives each of its rackets its own."""
    sched = two_rackets(n_steps)
    shift = jnp.asarray(rng.uniform(-0.05, 0.05, (B, 1, 2, 3)))
    speed = jnp.asarray(rng.uniform(-0.3, 0.3, (B, 1, 2, 3)))
    t = jnp.arange(n_steps)[None, :, None, None] * 1e-3
    each = jax.tree.map(lambda a: jnp.broadcast_to(a[None], (B,) + a.shape), sched)
    return each.replace(pos=each.pos + shift + t * speed, vel=each.vel + speed)


# slow: per-ball racket schedules run by default in the effects and residual comparisons below, and
# per-ball parameters in the Pallas kernel's reading of them (test_pallas_kernel_reads_per_ball_...)
@pytest.mark.slow
def test_fused_equals_reference_with_per_ball_parameters_and_rackets(model):
    """Per-ball ball, air, drag-table and table parameters (what domain randomisation, the
    sensitivity studies and the diagnosis fly) and a racket schedule per ball (what the
    environment gives its rackets) on the fused path: the reference path's events and states."""
    rng = np.random.default_rng(11)
    drag = model.aero.drag
    scale = jnp.asarray(rng.uniform(0.85, 1.15, B))
    batched = model.replace(
        ball=model.ball.replace(radius=jnp.asarray(rng.uniform(0.0198, 0.0202, B)),
                                mass=jnp.asarray(rng.uniform(0.0026, 0.0028, B))),
        aero=model.aero.replace(rho_air=jnp.asarray(rng.uniform(1.0, 1.3, B)),
                                drag=drag.replace(cd=scale[:, None, None] * drag.cd[None],
                                                  re_ref=jnp.broadcast_to(drag.re_ref, (B,) + drag.re_ref.shape),
                                                  sp=jnp.broadcast_to(drag.sp, (B,) + drag.sp.shape),
                                                  re_cap=jnp.full(B, drag.re_cap), cd_min=jnp.full(B, drag.cd_min))),
        table=model.table.replace(e0=jnp.asarray(rng.uniform(0.85, 0.95, B))))
    axes = per_ball_axes(model, "ball.radius", "ball.mass", "aero.rho_air", "aero.drag", "table.e0")
    _fused_matches_reference(model, batched, axes, 5, rng, apart=1e-3)


def _fused_matches_reference(model, batched, axes, seed, rng, apart, plain=None):
    """With a racket schedule per ball, the fused path's rollout of ``batched`` is the reference
    path's (and bounces and meets rackets); ``model``'s (the shared parameters, no effects) ends
    more than ``apart`` [m] elsewhere: what ``batched`` changes matters. ``plain``: ``model``
    written in ``batched``'s structure (``model_axes`` included), whose rollout reuses the
    compiled program of ``batched``'s."""
    assert fused.unsupported(batched, axes, integrator="rk4", policy=None, rackets_batched=True) is None
    state, sched = init_state(shots(B, seed=seed)), per_ball_rackets(N, rng)
    ref = rollout(batched, state, N, 1e-3, sched, model_axes=axes)
    fus = rollout(batched, state, N, 1e-3, sched, model_axes=axes, execution=Execution(fused=True))
    _assert_same_rollout(ref, fus, atol=1e-9)
    kinds = np.asarray(ref[1].events.kind)
    assert (kinds == TABLE).sum() > 40 and (kinds == RACKET).sum() > 5
    if plain is None:
        shared = rollout(model, state, N, 1e-3, sched, execution=Execution(fused=True))
    else:
        shared = rollout(plain, state, N, 1e-3, sched, model_axes=axes, execution=Execution(fused=True))
    assert float(jnp.max(jnp.abs(shared[0].ball.pos - fus[0].ball.pos))) > apart


def neutral_effects(batched, axes, n=B):
    """``batched`` with every effect at its neutral values (which reproduce the model without
    them: tests/effects), the per-ball ones broadcast to ``n`` balls: the same structure, shapes
    and axes, so its rollouts reuse ``batched``'s compiled programs."""
    dtype = batched.ball.radius.dtype
    neutral = batched.replace(effects=tuple(type(e).neutral(dtype=dtype) for e in batched.effects))
    return jax.tree.map(lambda ax, leaf: jnp.broadcast_to(leaf, (n,) + leaf.shape) if ax == 0 else leaf,
                        axes, neutral, is_leaf=lambda x: x is None)


def flight_effects(model, rng, n=B):
    """conti2026 with every flight hook of the catalogue (spin decay, air flow with gusts, ball
    variation, air density) and a contact-only one (table friction); the decay rate, the wind and
    the radius are drawn per ball."""
    effects = (fx.make("spin_decay", quadratic=2e-4).replace(rate=jnp.asarray(rng.uniform(0.5, 3.0, n))),
               fx.make("air_flow", gust_amp=np.full((3, 3), 0.3), gust_freq=[2.0, 3.0, 5.0]).replace(
                   wind=jnp.asarray(rng.uniform(-2.0, 2.0, (n, 3)))),
               fx.make("ball_variation", d_mass=1e-5).replace(d_radius=jnp.asarray(rng.uniform(-5e-5, 3e-4, n))),
               fx.make("air_density", d_rho=-0.1), fx.make("table_friction", d_mu=0.2))
    batched = model.replace(effects=effects)
    return batched, per_ball_axes(batched, "effects.0.rate", "effects.1.wind", "effects.2.d_radius")


def test_fused_equals_reference_with_effects_in_flight(model):
    """Effects acting in flight (every flight hook, time-dependent gusts, per-ball effect
    parameters) with a racket schedule per ball, on a CPU's fused path: the kernel evaluates the
    hooks at each RK4 stage's state and time, so the events and states are the reference path's."""
    if jax.default_backend() == "gpu":
        pytest.skip("effects in flight take the reference path on a GPU")
    rng = np.random.default_rng(23)
    batched, axes = flight_effects(model, rng)
    assert fused.in_flight(batched) and not fused.in_flight(model)
    # the effects matter: against the same program with every effect neutral (the model without them)
    _fused_matches_reference(model, batched, axes, 9, rng, apart=1e-2, plain=neutral_effects(batched, axes))
    # a table_surface effect moves the table the kernel stops balls at: refused
    tilted = model.replace(effects=(fx.make("table_tilt"),))
    why = fused.unsupported(tilted, per_ball_axes(tilted), integrator="rk4", policy=None, rackets_batched=False)
    assert "table's surface" in why and type(tilted.effects[0]).__name__ in why
    with pytest.raises(ValueError, match="table's surface"):
        rollout(tilted, init_state(shots(4)), 10, execution=Execution(fused=True))


def test_fused_equals_reference_with_the_sampled_residual(model):
    """The sampled residual on the fused path: a ball's draw is a function of the key, its step
    and its id, so the balls' own clocks give the reference path's draws (events, post-contact
    states, sigma), and another key gives other draws."""
    from ttsim_jax.physics.network import ResidualConfig, init_model

    net = init_model(ResidualConfig(trunk=(16, 16), head_width=8, n_clusters=4), jax.random.key(0))
    # not attenuated (beta 1 everywhere), corrections and sigmas of a few tenths of m/s and rad/s
    withnet = model.replace(residual=net.replace(beta_coef=jnp.array([1.0, 0.0, 0.0], jnp.float32),
                                                 y_scale=jnp.full(6, 0.3, jnp.float32)))
    state, sched = init_state(shots(B, seed=4)), two_rackets(N)
    key = jax.random.key(7)
    ref = rollout(withnet, state, N, 1e-3, sched, sample_key=key)
    fus = rollout(withnet, state, N, 1e-3, sched, sample_key=key, execution=Execution(fused=True))
    _assert_same_rollout(ref, fus, atol=1e-9)
    np.testing.assert_allclose(np.asarray(fus[1].events.sigma), np.asarray(ref[1].events.sigma), atol=1e-9)
    hits = np.asarray(ref[1].events.kind) == RACKET
    assert hits.sum() > 10
    other = rollout(withnet, state, N, 1e-3, sched, sample_key=jax.random.key(8),
                    execution=Execution(fused=True))
    # each ball's first racket contact (the same state before it with either key) drew anew
    first = hits & (np.cumsum(hits, axis=1) == 1)
    pre, pre2 = (np.asarray(r[1].events.pre.vel)[first] for r in (fus, other))
    post, post2 = (np.asarray(r[1].events.post.vel)[first] for r in (fus, other))
    np.testing.assert_allclose(pre2, pre, atol=1e-12)
    assert np.all(np.abs(post - post2).max(axis=-1) > 1e-6)


@pytest.fixture(scope="module")
def policy_run(model):
    """(model, model_axes, state, reference rollout) with two tracking rackets (a policy evaluated at
    each ball's own time, as the environment's rackets are) and per-ball table and air parameters."""
    rng = np.random.default_rng(31)
    batched = model.replace(table=model.table.replace(e0=jnp.asarray(rng.uniform(0.85, 0.95, B))),
                            aero=model.aero.replace(rho_air=jnp.asarray(rng.uniform(1.0, 1.3, B))))
    axes = per_ball_axes(model, "table.e0", "aero.rho_air")
    state = init_state(shots(B, seed=2))
    return batched, axes, state, rollout(batched, state, N, 1e-3, tracking_rackets(x=1.7), model_axes=axes)


def test_fused_equals_reference_with_a_racket_policy(policy_run):
    """The fused path stops each ball before its path meets the policy's reach and evaluates the
    policy there, so its events and states are the reference path's; none of its balls breaks the
    reach's promise (INVALID)."""
    batched, axes, state, ref = policy_run
    fus = rollout(batched, state, N, 1e-3, tracking_rackets(x=1.7), model_axes=axes, execution=Execution(fused=True))
    _assert_same_rollout(ref, fus, atol=1e-9)
    kinds = np.asarray(ref[1].events.kind)
    assert (kinds == TABLE).sum() > 40 and (kinds == RACKET).sum() > 10, np.bincount(kinds.ravel())
    assert not np.any(np.asarray(fus[0].status) == INVALID)


def test_fused_path_flags_a_policy_that_leaves_its_reach(policy_run):
    """A reach that does not hold the rackets (boxes 0.3 m to either side of the centre line, where
    the rackets follow the ball to 1 m): the fused path, which flew the balls by the promise, ends
    INVALID each ball that takes an ordinary step (the first, a bounce, a racket) away from the
    centre line, where the reference path (which checks nothing) flies on; the balls that stay
    near it are the reference path's."""
    batched, axes, state, ref = policy_run
    honest = tracking_rackets(x=1.7)

    def narrow(params, dt):
        return tracking_rackets_reach(params, dt).at[:, :, 1].multiply(0.3 / 1.077)

    liar = RacketPolicy(params=honest.params, fn=tracking_rackets_fn, reach=narrow)
    fus = rollout(batched, state, N, 1e-3, liar, model_axes=axes, execution=Execution(fused=True))
    status, ref_status = np.asarray(fus[0].status), np.asarray(ref[0].status)
    broken = status == INVALID
    assert 5 < broken.sum() < B - 5 and not np.any(ref_status == INVALID), broken.sum()
    np.testing.assert_array_equal(status[~broken], ref_status[~broken])
    np.testing.assert_allclose(np.asarray(fus[0].ball.pos)[~broken], np.asarray(ref[0].ball.pos)[~broken], atol=1e-9)
    # a broken ball stopped where it broke the promise: off the centre line, never further on
    y = np.abs(np.asarray(fus[0].ball.pos)[broken, 1])
    assert np.all(y > 0.3 - 0.077 - 0.05), y


def test_tracking_rackets_stay_within_their_reach():
    """:func:`tracking_rackets_reach` holds each racket's face over a step wherever the ball is and
    whichever way it flies (the promise the fused path flies by), for random policy parameters and
    steps; a box 1 cm smaller on any side does not."""
    rng = np.random.default_rng(3)
    n = 4096
    ball = Ball(pos=jnp.asarray(rng.uniform([-4.0, -3.0, -0.5], [4.0, 3.0, 3.0], (n, 3))),
                vel=jnp.asarray(rng.uniform(-20.0, 20.0, (n, 3))), spin=jnp.zeros((n, 3)))
    t = jnp.asarray(rng.uniform(0.0, 2.0, n))
    for x, swing, lift, dt in ((1.9, 4.0, 1.0, 1e-3), (1.5, 0.0, -2.0, 5e-3), (2.4, -3.0, 0.0, 2e-3)):
        params = {k: jnp.asarray(v) for k, v in dict(x=x, swing=swing, lift=lift, tilt=-0.3).items()}
        rackets = jax.vmap(tracking_rackets_fn, in_axes=(None, 0, 0))(params, ball, t)
        reach = tracking_rackets_reach(params, dt)
        assert bool(jnp.all(within_reach(rackets, reach, dt)))
        for side in (0, 1):
            for axis in range(3):
                smaller = reach.at[:, side, axis].add(0.01 if side == 0 else -0.01)
                assert not bool(jnp.all(within_reach(rackets, smaller, dt))), (x, side, axis)


def test_kernel_flies_until_the_step_before_a_possible_event(model):
    """Balls in open air take every sub-step; a ball about to land stops before the step the
    ordinary step flags, at most a few steps early (the margins); a budget is respected."""
    dt = 1e-3
    pos = np.array([[0.5, 0.0, 1.5], [-1.0, 0.0, 0.03], [0.5, 0.0, 1.5], [0.7, 0.2, 1.2]])
    vel = np.array([[5.0, 1.0, 2.0], [3.0, 0.0, -1.0], [5.0, 1.0, 2.0], [4.0, 0.0, 1.0]])
    spin = np.array([[0.0, 300.0, 0.0], [0.0, -200.0, 0.0], [0.0, 300.0, 0.0], [100.0, 0.0, 50.0]])
    ball = Ball.create(pos, vel, spin)
    budget = jnp.array([64, 64, 3, 0], jnp.int32)
    params, layout = fused.pack(model, jnp.asarray(dt), None, ball.pos.dtype)
    out, n = fused.fly(params, layout, ball, budget, substeps=16)
    n = np.asarray(n)
    assert n[0] == 16 and n[2] == 3 and n[3] == 0 and 0 < n[1] < 16

    one = lambda b: jax.tree.map(lambda a: a[None], b)  # noqa: E731
    fly_one = jax.jit(lambda b: flight(model, b, 0.0, dt))
    flag_one = jax.jit(lambda b, nxt: may_have_event(model, b, nxt, None, dt))
    for i in range(4):
        b = jax.tree.map(lambda a: a[i], ball)
        for _ in range(n[i]):
            nxt = fly_one(b)
            assert not flag_one(b, nxt)  # never flies through a flagged step
            b = nxt
        np.testing.assert_allclose(np.asarray(one(jax.tree.map(lambda a: a[i], out)).as_array()),
                                   np.asarray(one(b).as_array()), rtol=1e-12, atol=1e-12)
    # the landing ball: the ordinary step flags one of the next few steps
    b = jax.tree.map(lambda a: a[1], out)
    flags = []
    for _ in range(4):
        nxt = fly_one(b)
        flags.append(bool(flag_one(b, nxt)))
        b = nxt
    assert any(flags)


def test_per_ball_parameters_leave_the_shared_ones_scalars(model):
    """A per-ball air density gives the kernel one per-ball row (the density ratio it reads); the
    coefficient tables and the rest stay scalars, the values the shared model's vector holds (read
    as rows of B values, they cost the kernel 6.6x its time at 65,536 balls)."""
    rho = jnp.linspace(1.0, 1.3, 8)
    batched = model.replace(aero=model.aero.replace(rho_air=rho))
    (vector, matrix), layout = fused.pack(batched, jnp.asarray(1e-3), None, jnp.float64,
                                          per_ball_axes(model, "aero.rho_air"))
    shared, shared_layout = fused.pack(model, jnp.asarray(1e-3), None, jnp.float64)
    assert matrix.shape == (1, 8) and layout.rows.count(-1) == len(layout.rows) - 1
    ratio = layout.rows.index(0)
    np.testing.assert_allclose(np.asarray(matrix[0]), np.asarray(rho / model.aero.rho_air * shared[ratio]), rtol=1e-12)
    keep = np.arange(layout.size) != ratio
    np.testing.assert_array_equal(np.asarray(vector)[keep], np.asarray(shared)[keep])
    assert layout.size == shared_layout.size and shared_layout.rows == ()


@pytest.mark.parametrize("moving", [9, 100, 700])
def test_kernel_gathers_the_moving_balls_with_the_same_result(model, moving):
    """On a CPU the kernel flies only the balls with a budget, gathered into B/64, B/8 or B rows
    (here 1,024 balls: 16, 128 or all; the rollouts above, 64 balls, gather into 8): the same flight as over the whole batch, the others untouched."""
    b = 1024
    ball = shots(b, seed=3)
    budget = jnp.zeros(b, jnp.int32).at[np.random.default_rng(moving).choice(b, moving, replace=False)].set(24)
    params, layout = fused.pack(model, jnp.asarray(1e-3), None, ball.pos.dtype)
    out, n = jax.jit(lambda bl, bu: fused.fly(params, layout, bl, bu, substeps=24))(ball, budget)
    whole, n_whole = fused._fly_xla(params, layout, ball, budget, substeps=24)
    np.testing.assert_array_equal(np.asarray(n), np.asarray(n_whole))
    assert int((np.asarray(n) > 0).sum()) > 0.8 * moving  # most fly (a few stop at once)
    np.testing.assert_allclose(np.asarray(out.as_array()), np.asarray(whole.as_array()), rtol=1e-12, atol=1e-12)
    still = np.asarray(budget) == 0
    np.testing.assert_array_equal(np.asarray(out.as_array())[still], np.asarray(ball.as_array())[still])


def test_pallas_kernel_reads_per_ball_parameters_as_the_xla_body_does(model):
    """The Pallas kernel (run here in interpret mode, as Triton runs it on a GPU) with per-ball
    radius, air density, drag table and racket box: each program reads its balls' rows of the
    per-ball parameters, so the flight and the stops equal the XLA body's over the whole batch (and
    the flight differs from the shared model's)."""
    b, rng = 80, np.random.default_rng(5)  # 80 balls: blocks of 32, the last one padded
    cd = jnp.asarray(rng.uniform(0.8, 1.2, b))[:, None, None] * model.aero.drag.cd[None]
    batched = model.replace(ball=model.ball.replace(radius=jnp.asarray(rng.uniform(0.0195, 0.0205, b))),
                            aero=model.aero.replace(rho_air=jnp.asarray(rng.uniform(1.0, 1.3, b)),
                                                    drag=model.aero.drag.replace(cd=cd)))
    axes = per_ball_axes(model, "ball.radius", "aero.rho_air", "aero.drag.cd")
    ball = shots(b, seed=6)
    budget = jnp.full(b, 24, jnp.int32)
    # a racket box per ball, 5-30 cm ahead of it: some balls stop before theirs
    ahead = ball.pos + jnp.asarray(rng.uniform(0.05, 0.3, (b, 1))) * ball.vel / jnp.linalg.norm(ball.vel, axis=1,
                                                                                                 keepdims=True)
    boxes = jnp.stack([ahead - 0.05, ahead + 0.05], axis=1)[:, None]  # (B, 1, 2, 3)
    params, layout = fused.pack(batched, jnp.asarray(1e-3), boxes, ball.pos.dtype, axes)
    assert isinstance(params, tuple) and params[1].shape[1] == b
    out, n = fused.fly(params, layout, ball, budget, substeps=24, block=32, interpret=True)
    ref, n_ref = fused._fly_xla(params, layout, ball, budget, substeps=24)
    np.testing.assert_array_equal(np.asarray(n), np.asarray(n_ref))
    assert 10 < int(np.sum(np.asarray(n) < 24)) < b - 10  # some balls stopped at their own box, others flew on
    np.testing.assert_allclose(np.asarray(out.as_array()), np.asarray(ref.as_array()), rtol=1e-12, atol=1e-12)
    shared, shared_layout = fused.pack(model, jnp.asarray(1e-3), None, ball.pos.dtype)
    other, _ = fused._fly_xla(shared, shared_layout, ball, budget, substeps=24)
    flew = np.asarray(n) == 24
    assert float(jnp.max(jnp.abs(other.vel - out.vel)[flew])) > 1e-3


def test_kernel_lowers_to_triton(model):
    """The kernel uses only what Pallas's Triton backend lowers (no GPU needed to lower; the
    compilation of the Triton IR itself happens on the GPU)."""
    from jax import export

    ball = Ball.create(np.zeros((200, 3)), np.ones((200, 3)), np.ones((200, 3)), dtype=jnp.float32)
    boxes = jnp.zeros((2, 2, 3), jnp.float32)
    m32 = load_model("conti2026", dtype=jnp.float32)

    def fly(m, ball, budget):
        params, layout = fused.pack(m, jnp.float32(1e-3), boxes, jnp.float32)
        return fused.fly(params, layout, ball, budget, interpret=False)

    triton = export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton")
    exp = export.export(jax.jit(fly), platforms=("cuda",), disabled_checks=[triton])(
        m32, ball, jnp.zeros(200, jnp.int32))
    assert "__gpu$xla.gpu.triton" in exp.mlir_module()

    # per-ball parameters: each program reads a block of their rows
    def fly_each(m, ball, budget):
        params, layout = fused.pack(m, jnp.float32(1e-3), boxes, jnp.float32, per_ball_axes(m32, "aero.rho_air"))
        return fused.fly(params, layout, ball, budget, interpret=False)

    each = m32.replace(aero=m32.aero.replace(rho_air=jnp.full(200, 1.2, jnp.float32)))
    exp = export.export(jax.jit(fly_each), platforms=("cuda",), disabled_checks=[triton])(
        each, ball, jnp.zeros(200, jnp.int32))
    assert "__gpu$xla.gpu.triton" in exp.mlir_module()


def test_fused_refuses_what_it_does_not_cover(model):
    state = init_state(shots(4))
    policy = RacketPolicy(params=None, fn=lambda p, ball, t: None)  # no reach: where its rackets go is unknown
    with pytest.raises(ValueError, match="racket policy without a reach"):
        rollout(model, state, 10, racket=policy, execution=Execution(fused=True))
    # a reach of the wrong shape: refused before anything compiles, naming what it must be
    flat = RacketPolicy(params=tracking_rackets().params, fn=tracking_rackets_fn, reach=lambda p, dt: jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"reach\(params, dt\) gives shape \(2, 3\); it must be \(2, 2, 3\)"):
        rollout(model, state, 10, racket=flat)
    with pytest.raises(ValueError, match="integrator 'rk2'"):
        rollout(model, state, 10, integrator="rk2", execution=Execution(fused=True))
    with pytest.raises(ValueError, match="fused must be"):
        rollout(model, state, 10, execution=Execution(fused="yes"))


@pytest.mark.slow
def test_fused_equals_reference_in_float32_with_recording():
    """Float32, as on a GPU: the same events, states within float32 rounding, the same recording."""
    model = load_model("conti2026", dtype=jnp.float32)
    sched = jax.tree.map(lambda a: a.astype(jnp.float32), two_rackets(N))
    balls = jax.tree.map(lambda a: a.astype(jnp.float32), shots(4 * B, seed=7))
    state = init_state(balls)
    ref = rollout(model, state, N, 1e-3, sched, record=Record(every=100))
    fus = rollout(model, state, N, 1e-3, sched, record=Record(every=100), execution=Execution(fused=True))
    # 1e-4: float32 rounding grown over 400 steps and a few contacts (measured: 6e-5 on spins of
    # hundreds of rad/s, about 1e-7 relative; event times within 5e-8 s)
    _assert_same_rollout(ref, fus, atol=1e-4)
    np.testing.assert_allclose(np.asarray(fus[1].trajectory.as_array()), np.asarray(ref[1].trajectory.as_array()),
                               rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(np.asarray(fus[1].times), np.asarray(ref[1].times))


@pytest.mark.slow
def test_gradient_through_the_fused_path_is_the_reference_gradient(model):
    """``jax.grad`` of a fused rollout differentiates the reference path (the kernel has no reverse mode)."""
    balls = shots(8, seed=3)

    def landing(v0, fused_path):
        state = init_state(balls.replace(vel=balls.vel.at[:, 0].set(v0)))
        s, _ = rollout(model, state, 120, 1e-3, execution=Execution(fused=fused_path), record=Record(max_events=0))
        return jnp.sum(s.ball.pos[:, 0])

    v0 = balls.vel[:, 0]
    g_ref = jax.grad(landing)(v0, False)
    g_fused = jax.grad(landing)(v0, True)
    np.testing.assert_allclose(np.asarray(g_fused), np.asarray(g_ref), rtol=1e-10)
    assert np.all(np.asarray(g_ref) != 0.0)


def test_auto_takes_the_fused_path_where_it_was_measured_to_pay(model, monkeypatch):
    """``fused="auto"`` (the default): on a CPU from FUSED_AUTO_MIN_BATCH_CPU balls and
    FUSED_AUTO_MIN_STEPS_CPU steps, without a racket schedule per ball, a racket policy or an
    effect moving the air; on a GPU always but with a policy, per-ball rackets or per-ball
    parameters; and ``rollout`` follows it (the
    compiled program is replaced by a recorder: nothing compiles)."""
    import importlib

    R = importlib.import_module("ttsim_jax.kernel.rollout")
    n, t = R.FUSED_AUTO_MIN_BATCH_CPU, R.FUSED_AUTO_MIN_STEPS_CPU
    if jax.default_backend() == "cpu":
        assert not R.fused_pays(n - 1) and R.fused_pays(n) and R.fused_pays(1 << 20)
        assert R.fused_pays(n, n_steps=t) and not R.fused_pays(1 << 20, n_steps=t - 1)
        assert not R.fused_pays(1 << 20, rackets_batched=True)  # measured slower (see fused_pays)
        assert not R.fused_pays(1 << 20, air_hooks=True)
        assert R.fused_pays(1 << 20, per_ball=True)
    else:
        assert R.fused_pays(1) == (jax.default_backend() == "gpu")
        assert not R.fused_pays(1 << 20, per_ball=True) and not R.fused_pays(1 << 20, rackets_batched=True)
    taken = []
    monkeypatch.setattr(R, "_rollout", lambda *a, plan: taken.append(plan.fused))
    runs = ((n - 1, t, "auto", False), (n, t, "auto", False), (n, t - 1, "auto", False), (n, 10, True, False),
            (n, t, False, False))
    runs += ((n, t, "auto", True), (n, t, True, True))  # per-ball rackets: covered, slower
    for batch, steps, choice, own in runs:
        sched = two_rackets(steps)
        if own:  # a schedule per ball
            sched = jax.tree.map(lambda a: jnp.broadcast_to(a[None], (batch,) + a.shape), sched)
        rollout(model, init_state(shots(batch)), steps, 1e-3, sched, execution=Execution(fused=choice))
    pays = lambda b, s, c, own: c is True or (c == "auto" and R.fused_pays(b, own, n_steps=s))  # noqa: E731
    assert taken == [fused.SUBSTEPS if pays(*r) else 0 for r in runs], taken
    # a racket policy: measured slower on a CPU, not measured on a GPU; taken when asked for
    assert not R.fused_pays(1 << 20, policy=True)
    taken.clear()
    for choice in ("auto", True):
        rollout(model, init_state(shots(n)), t, 1e-3, tracking_rackets(), execution=Execution(fused=choice))
    assert taken == [0, fused.SUBSTEPS], taken
    if jax.default_backend() == "cpu":  # effects in flight: auto leaves out those that move the air
        taken.clear()
        for name in ("spin_decay", "air_flow"):
            rollout(model.replace(effects=(fx.make(name),)), init_state(shots(n)), t, 1e-3)
        assert taken == [fused.SUBSTEPS, 0], taken
