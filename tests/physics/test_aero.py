import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, load_model, simulate
from ttsim_jax.physics import aero
from ttsim_jax.physics.aero import ConstantCoefficient

from padding import simulate_shared


def vacuum(dtype):
    m = load_model("nakashima2011", dtype=dtype)
    zero = jnp.zeros((), dtype)
    return m.replace(aero=m.aero.replace(drag=ConstantCoefficient(zero), magnus=ConstantCoefficient(zero),
                                         buoyancy=zero))


# Each (dtype, integrator) compiles its own rollout. By default every integrator runs in float64
# and rk4 in float32 too; float32 with rk2 and euler (no code of its own) runs with -m slow.
@pytest.mark.parametrize("dtype,integrator", [
    pytest.param(jnp.float32, "rk4", id="f32-rk4"),
    pytest.param(jnp.float32, "rk2", id="f32-rk2", marks=pytest.mark.slow),
    pytest.param(jnp.float32, "euler", id="f32-euler", marks=pytest.mark.slow),
    pytest.param(jnp.float64, "rk4", id="f64-rk4"),
    pytest.param(jnp.float64, "rk2", id="f64-rk2"),
    pytest.param(jnp.float64, "euler", id="f64-euler"),
])
def test_vacuum_parabola_matches_closed_form(dtype, integrator):
    m = vacuum(dtype)
    p0, v0 = np.array([-1.0, 0.2, 0.5]), np.array([4.0, -0.5, 2.0])
    ball = Ball.create(p0[None], v0[None], [[30.0, -200.0, 10.0]], dtype=dtype)
    r = simulate_shared(m, ball, 1e-3, integrator=integrator)  # the suite's shared shape
    t = np.asarray(r.times)
    flight = t <= 0.4 + 1e-9  # the free flight, before the ball comes down on the table
    t = t[flight]
    expect = p0 + v0 * t[:, None] + 0.5 * np.array([0, 0, -9.81]) * t[:, None] ** 2
    tol = {"rk4": 1e-9, "rk2": 1e-9, "euler": 5e-3}[integrator] + (5e-5 if dtype == jnp.float32 else 0)
    pos = np.asarray(r.trajectory.pos[0])[flight]
    assert len(pos) == 40
    np.testing.assert_allclose(pos, expect, atol=tol)
    # semi-implicit Euler errs by g t dt / 2 in z: first order, not exact
    if integrator == "euler":
        assert abs(float(pos[-1, 2]) - expect[-1, 2]) > 1e-4


def test_acceleration_matches_paper_force_equation():
    m = load_model("nakashima2011")
    r, mass = 0.02, float(m.ball.mass)
    v, w = jnp.array([8.0, 1.0, -2.0]), jnp.array([10.0, 150.0, -40.0])
    a = aero.acceleration(m.aero, m.ball.radius, m.ball.mass, jnp.zeros(3), v, w, 0.0)
    rho = 1.184
    area, vol = np.pi * r**2, 4 / 3 * np.pi * r**3
    f_d = -0.5 * 0.54 * rho * area * np.linalg.norm(v) * np.asarray(v)
    f_m = -0.069 * rho * vol * np.cross(v, w)  # paper: -C_M rho V v x w
    f_g = mass * np.array([0, 0, -9.81]) * (1 - rho * vol / mass)
    np.testing.assert_allclose(np.asarray(a), (f_d + f_m + f_g) / mass, rtol=1e-10)


def test_drag_table_hits_paper_breakpoints_and_interpolates():
    d = load_model("conti2026").aero.drag
    nu, r = 1.506e-5, 0.02
    cd = lambda v, sp: float(aero.drag_table(d, v, sp * v / r, r, nu))  # noqa: E731
    v_ref = np.array([6640, 19920, 33201, 46481]) * nu / (2 * r)
    # at a reference speed and a breakpoint: the table value
    assert cd(v_ref[1], 0.75) == pytest.approx(0.55, abs=1e-6)
    assert cd(v_ref[2], 0.95) == pytest.approx(0.41, abs=1e-6)
    assert cd(v_ref[3], 0.84) == pytest.approx(0.37, abs=1e-6)
    # between breakpoints: linear in Sp (7.5 m/s row: 0.55 at 0.75, 0.48 at 1.1)
    assert cd(v_ref[1], 0.925) == pytest.approx(0.515, abs=1e-6)
    # between reference speeds at the same Sp: linear in Re (the documented reading)
    mid = 0.5 * (v_ref[1] + v_ref[2])
    assert cd(mid, 0.2) == pytest.approx(0.5 * (0.49 + 0.47), abs=1e-6)
    # below 2.5 m/s held, flat beyond the last breakpoint
    assert cd(1.0, 0.5) == pytest.approx(0.55, abs=1e-6)
    assert cd(v_ref[3], 3.0) == pytest.approx(0.45, abs=1e-6)
    # above 17.5 m/s: linear extrapolation with the 12.5 / 17.5 rows, held past the cap
    assert cd(22.5, 0.2) == pytest.approx(0.47 + 2 * (0.47 - 0.47), abs=1e-6)
    row12 = 0.41 + (1.0 - 0.95) / (1.3 - 0.95) * (0.48 - 0.41)  # 12.5 m/s curve at Sp = 1
    row17 = 0.37 + (1.0 - 0.84) / (1.2 - 0.84) * (0.45 - 0.37)  # 17.5 m/s curve at Sp = 1
    w = (2 * 22.5 * r / nu - 33201) / (46481 - 33201)  # = 2.0
    assert cd(22.5, 1.0) == pytest.approx((1 - w) * row12 + w * row17, abs=1e-6)
    assert cd(30.0, 2.0) == pytest.approx(cd(40.0, 2.0), abs=1e-9)


def test_magnus_table_linear_quadratic_and_clamped():
    p = load_model("conti2026").aero.magnus
    cm = lambda v, w: float(aero.magnus_table(p, v, w, 0.02, 1.506e-5))  # noqa: E731
    assert cm(7.5, 100.0) == pytest.approx(0.37 - 8.0e-4 * 100, abs=1e-9)  # linear part
    assert cm(7.5, 500.0) == pytest.approx(-2e-7 * 500**2 + 1.7e-4 * 500 + 0.0587, abs=1e-9)  # quadratic
    assert cm(9.0, 100.0) == pytest.approx(0.5 * (0.37 - 0.08) + 0.5 * (0.375 - 0.0658), abs=1e-9)
    assert cm(1.0, 100.0) == pytest.approx(0.08, abs=1e-9)  # held below 2 m/s
    assert cm(30.0, 100.0) == pytest.approx(0.371 - 0.0448, abs=1e-9)  # held above 17 m/s
    assert cm(13.5, 3000.0) == 0.0  # the quadratic goes negative: clamped


def test_durr_magnus_hardly_depends_on_spin_and_is_finite_at_zero_spin():
    p = load_model("durr2026").aero.magnus
    f = lambda w: float(aero.magnus_durr(p, 10.0, w, 0.02, 1.506e-5) * w)  # noqa: E731  (force ~ C_M |w|)
    assert f(100.0) == pytest.approx(f(200.0), rel=0.01)
    g = jax.grad(lambda w: aero.acceleration(load_model("durr2026").aero, 0.02, 2.72e-3, jnp.zeros(3),
                                             jnp.array([5.0, 0, 0]), w, 0.0).sum())(jnp.zeros(3))
    assert np.all(np.isfinite(g))


@pytest.mark.parametrize("name", ["nakashima2011", "durr2026", "conti2026"])
def test_flight_mirror_symmetry_in_y(name):
    m = load_model(name)
    mirror = np.array([1.0, -1.0, 1.0])
    b = Ball.create([[-1.3, 0.3, 0.25]], [[9.0, -1.5, 1.5]], [[40.0, 180.0, -250.0]])
    # spin is an axial vector: under y -> -y it maps to (-wx, wy, -wz)
    bm = Ball.create(b.pos * mirror, b.vel * mirror, -b.spin * mirror)
    both = jax.tree.map(lambda a, c: jnp.concatenate([a, c]), b, bm)
    r = simulate_shared(m.replace(table=m.table.replace(residual=0 * m.table.residual)), both)  # the shared shape
    assert int(r.events.count[0]) >= 1  # through a bounce
    np.testing.assert_allclose(np.asarray(r.trajectory.pos[1]) * mirror, np.asarray(r.trajectory.pos[0]), atol=1e-12)
    np.testing.assert_allclose(-np.asarray(r.final.spin[1]) * mirror, np.asarray(r.final.spin[0]), atol=1e-9)


def test_spin_decay_hook_reaches_flight():
    from flax import struct

    @struct.dataclass
    class Decay:
        rate: jnp.ndarray

        def spin_derivative(self, value, vel, spin, t):
            return value - self.rate * spin

    m = load_model("conti2026").replace(effects=(Decay(jnp.asarray(2.0)),))
    b = Ball.create([[-1.0, 0.0, 0.5]], [[3.0, 0.0, 3.0]], [[0.0, 100.0, 0.0]])
    r = simulate(m, b, 250)
    assert float(r.final.spin[0, 1]) == pytest.approx(100.0 * np.exp(-2.0 * 0.25), rel=1e-6)


def test_the_tables_jvp_through_their_partials_is_jaxs_own():
    """coefficients() carries a table's tangents through its two partials (aero._through_partials):
    the tangents of six directions at once, the gradient by a table entry and the second derivative
    are those of JAX's own differentiation of the table, for every table kind."""
    m = load_model("conti2026", dtype=jnp.float64)
    d, mg = m.aero.drag, m.aero.magnus
    fields = lambda p: {f: getattr(p, f) for f in p.__dataclass_fields__}  # noqa: E731
    kinds = [(d, mg), (aero.BlendedDragTable(**fields(d)), aero.MagnusValueTable(**fields(mg)))]
    radius = m.ball.radius
    rng = np.random.default_rng(1)
    v = jnp.asarray(rng.normal(size=(4, 3)) * 8)
    w = jnp.asarray(rng.normal(size=(4, 3)) * 300)
    dirs = jnp.asarray(rng.normal(size=(6, 6)))  # six directions over (v, w)

    def own(a_, v, w):
        speed, rate = jnp.linalg.norm(v), jnp.linalg.norm(w)
        return (aero.DRAG_MODELS[type(a_.drag)](a_.drag, speed, rate, radius, a_.nu),
                aero.MAGNUS_MODELS[type(a_.magnus)](a_.magnus, speed, rate, radius, a_.nu))

    def new(a_, v, w):
        return aero.coefficients(a_, v, w, radius)

    @jax.jit
    def derivatives(a, v, w):
        def at(f, v, w):
            tangents = jax.vmap(lambda t: jax.jvp(lambda x: f(a, x[:3], x[3:]), (jnp.concatenate([v, w]),), (t,))[1])(dirs)
            return tangents, jax.grad(lambda a_: sum(f(a_, v, w)))(a), jax.hessian(lambda x: f(a, x, w)[0])(v)
        return [jax.vmap(lambda v_, w_: at(f, v_, w_))(v, w) for f in (new, own)]

    for drag, magnus in kinds:
        a = m.aero.replace(drag=drag, magnus=magnus)
        assert {aero.DRAG_MODELS[type(drag)], aero.MAGNUS_MODELS[type(magnus)]} <= aero.TABLE_FUNCTIONS
        got, want = derivatives(a, v, w)
        assert np.abs(np.array(want[0])).max() > 1e-6  # the tables do move
        for x, y in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-9, atol=1e-12)
