"""The effect catalogue: construction, exact neutrality, one test per effect that it changes what it
should and nothing else, and finite gradients through every in-simulator effect's parameters."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, Execution, Racket, init_state, load_model, rollout, simulate
from ttsim_jax import effects as fx
from ttsim_jax.physics import aero as aero_stage
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics import table as table_stage
from ttsim_jax.kernel.ball_step import ball_properties

PLAIN = load_model("conti2026")
SIM = fx.names("simulator")
REC = fx.names("record")

# A racket at the +x end facing -x (rotation diag(-1, -1, 1): x -> -x, y -> -y, z -> z).
R_POS = jnp.array([1.6, 0.0, 0.25])
R_ROT = jnp.diag(jnp.array([-1.0, -1.0, 1.0]))
CONTACT_POINTS = {"centre": (0.0, 0.0), "mid": (0.03, 0.02), "logo": (0.0, -0.065), "edge": (0.0, 0.085)}


def _racket_probe(model, d, speed):
    """Post-contact (v, w) of a ball arriving at speed ``speed`` at contact point d."""
    radius, mass = ball_properties(model)
    racket = Racket(pos=R_POS, rot=R_ROT, vel=jnp.array([-1.0, 0.3, 0.5]), ang_vel=jnp.array([0.0, 2.0, -1.0]),
                    face=jnp.array([0.09, 0.09]))
    y_axis, z_axis = R_ROT[:, 1], R_ROT[:, 2]
    pos = R_POS + d[0] * y_axis + d[1] * z_axis + radius * R_ROT[:, 0]
    v, w, _ = racket_stage.racket_contact(model.racket, racket, radius, mass, pos, jnp.array([speed, 1.0, -2.0]),
                                          jnp.array([30.0, 250.0, -40.0]), model.effects)
    return jnp.concatenate([v, w])


def probe(model) -> dict:
    """Every stage's output at fixed states: what an effect may change."""
    radius, mass = ball_properties(model)
    out = {"ball": jnp.stack([radius, mass])}
    f = aero_stage.derivative(model.aero, radius, mass, model.effects)
    y = (jnp.array([-0.5, 0.2, 0.3]), jnp.array([9.0, -1.0, 2.0]), jnp.array([-50.0, 400.0, 80.0]))
    out["flight"] = jnp.concatenate([jnp.concatenate(f(y, jnp.asarray(t))[1:]) for t in (0.3, 1.7)])
    at = jnp.array([0.6, 0.25, 0.02])
    h, n = table_stage.surface(model.effects, at)
    out["surface"] = jnp.concatenate([h[None], n])
    for name, vz in (("table_slow", -2.0), ("table_fast", -9.0)):
        p, v, w = table_stage.table_contact(model.table, radius, at, jnp.array([5.0, 0.5, vz]),
                                            jnp.array([20.0, -150.0, 30.0]), model.effects)
        out[name] = jnp.concatenate([p, v, w])
    for name, d in CONTACT_POINTS.items():
        out[f"racket_{name}_slow"] = _racket_probe(model, jnp.asarray(d), 4.0)
    out["racket_centre_fast"] = _racket_probe(model, jnp.asarray(CONTACT_POINTS["centre"]), 30.0)
    return {k: np.asarray(v) for k, v in out.items()}


BASE = None


def base_probe():
    global BASE
    if BASE is None:
        BASE = probe(PLAIN)
    return BASE


def changed_keys(effect) -> set:
    got = probe(PLAIN.replace(effects=(effect,)))
    return {k for k, v in got.items() if not np.array_equal(v, base_probe()[k])}


RACKET_ALL = {f"racket_{n}_slow" for n in CONTACT_POINTS} | {"racket_centre_fast"}
TABLE = {"table_slow", "table_fast"}


# ------------------------------------------------------------------------ the catalogue
def test_catalogue_lists_every_effect_with_units_and_values():
    assert set(SIM) == {"spin_decay", "air_flow", "table_tilt", "table_unevenness", "ball_variation", "worn_ball",
                        "buckling", "racket_logo", "racket_edge", "rubber_anisotropy", "air_density", "table_friction"}
    assert set(REC) == {"racket_state_error", "position_noise", "spin_noise", "missing_frames", "clock_rate",
                        "camera_scale", "spin_calibration", "spin_unmeasured"}
    for name, cls in fx.CATALOGUE.items():
        assert cls.NAME == name and cls.DESCRIPTION and cls.SCOPE in fx.SCOPES
        assert cls.hooks(), name
        for key, p in cls.PARAMS.items():
            assert p.unit and p.doc, (name, key)
        for inst in (cls.neutral(), cls.default(), cls.sample(np.random.default_rng(3))):
            for key, p in cls.PARAMS.items():
                assert np.shape(getattr(inst, key)) == p.shape, (name, key)
                assert np.all(np.isfinite(np.asarray(getattr(inst, key))))
        a, b = cls.sample(np.random.default_rng(7)), cls.sample(np.random.default_rng(7))
        assert a.to_dict() == b.to_dict()
        assert cls.from_dict(a.to_dict()).to_dict() == a.to_dict()
    text = fx.describe()
    assert "racket_logo" in text and "[m/s]" in text


def test_bad_names_and_parameters_are_named():
    with pytest.raises(fx.EffectError, match="unknown effect 'wind'.*air_flow"):
        fx.parse_names("wind,spin_decay")
    with pytest.raises(fx.EffectError, match="air_flow.*unknown parameter 'speed'"):
        fx.make("air_flow", speed=3.0)
    with pytest.raises(fx.EffectError, match="parameter 'wind' = .*shape"):
        fx.make("air_flow", wind=[1.0, 2.0])
    # "all" is every effect but those that take away or falsify a record's spin, asked for by name
    assert fx.parse_names("all") == [n for n in fx.names() if n not in ("spin_calibration", "spin_unmeasured")]
    assert fx.parse_names("none") == []
    assert fx.parse_names("spin_unmeasured") == ["spin_unmeasured"]
    assert fx.parse_names("racket_edge,spin_decay") == ["spin_decay", "racket_edge"]  # catalogue order


# ------------------------------------------------------------------------ neutrality
def test_neutral_values_reproduce_the_plain_model_exactly():
    neutral = PLAIN.replace(effects=tuple(fx.effect_class(n).neutral() for n in SIM))
    got, base = probe(neutral), base_probe()
    for k in base:
        np.testing.assert_array_equal(got[k], base[k], err_msg=k)
    # through the whole rally kernel: see test_rally_kernel_neutral_and_gradients
    for name in REC:
        e = fx.effect_class(name).neutral()
        rng = np.random.default_rng(0)
        pos = rng.normal(size=(5, 3))
        if name in ("position_noise", "camera_scale"):
            np.testing.assert_array_equal(e.observe_positions(pos, rng), pos)
        elif name == "clock_rate":
            t = np.cumsum(rng.uniform(0.0, 3.0, 50))
            np.testing.assert_array_equal(e.record_times(t), t)
        elif name == "spin_noise":
            spin, conf = e.measure_spin(pos * 100, np.full(5, 0.1), rng)
            np.testing.assert_array_equal(spin, pos * 100)
            np.testing.assert_array_equal(conf, np.ones(5))
        elif name == "missing_frames":
            assert e.drop_frames(np.arange(100) * 0.005, rng).all()
        elif name == "spin_calibration":
            np.testing.assert_allclose(e.measure_spin(pos * 100, rng), pos * 100, rtol=0, atol=1e-12)
        elif name == "spin_unmeasured":
            spin, conf = e.measure_spin(pos * 100, np.full(5, 0.7), rng)
            np.testing.assert_array_equal(spin, pos * 100)
            np.testing.assert_array_equal(conf, np.full(5, 0.7))
        else:
            rot = np.broadcast_to(np.eye(3), (5, 3, 3))
            out = e.record_racket(pos, rot, pos * 3, pos * 2, rng)
            for a, b in zip(out, (pos, rot, pos * 3, pos * 2)):
                np.testing.assert_allclose(a, b, atol=1e-15)


# ------------------------------------------------------------------------ one test per effect
def test_spin_calibration_scales_turns_and_flips_by_hand():
    rng = np.random.default_rng(0)
    spin = rng.normal(size=(400, 3)) * 200
    # a quarter turn about z takes x to y; scale 1.2
    e = fx.make("spin_calibration", scale=0.2, rotation=[0.0, 0.0, np.pi / 2], flip=0.0)
    out = e.measure_spin(spin, rng)
    np.testing.assert_allclose(out, 1.2 * np.stack([-spin[:, 1], spin[:, 0], spin[:, 2]], 1), atol=1e-9)
    flipped = fx.make("spin_calibration", scale=0.0, rotation=[0.0, 0.0, 0.0], flip=0.25).measure_spin(spin, rng)
    sign = np.sum(flipped * spin, 1) < 0
    np.testing.assert_allclose(np.abs(flipped), np.abs(spin), atol=1e-12)
    assert 0.18 < sign.mean() < 0.32


def test_spin_unmeasured_zeroes_spin_and_confidence_of_its_share():
    rng = np.random.default_rng(1)
    spin, conf = rng.normal(size=(1000, 3)) * 100, rng.uniform(0.5, 1.0, 1000)
    got, c = fx.make("spin_unmeasured", fraction=1.0).measure_spin(spin, conf, rng)
    assert not got.any() and not c.any()
    got, c = fx.make("spin_unmeasured", fraction=0.3).measure_spin(spin, conf, rng)
    gone = c == 0
    assert 0.25 < gone.mean() < 0.35
    assert not got[gone].any()
    np.testing.assert_array_equal(got[~gone], spin[~gone])
    np.testing.assert_array_equal(c[~gone], conf[~gone])


def test_spin_decay_changes_only_flight():
    e = fx.make("spin_decay")
    assert changed_keys(e) == {"flight"}
    w = jnp.array([0.0, 500.0, 0.0])
    assert float(e.spin_derivative(jnp.zeros(3), vel=None, spin=w, t=0.0)[1]) < 0  # slows the spin down


def test_air_flow_changes_only_flight_and_varies_in_time():
    e = fx.make("air_flow")
    assert changed_keys(e) == {"flight"}
    a1 = e.air_velocity(jnp.zeros(3), pos=jnp.zeros(3), t=0.3)
    a2 = e.air_velocity(jnp.zeros(3), pos=jnp.zeros(3), t=1.7)
    assert not np.allclose(a1, a2)
    # the clock origin shifts the gusts: air at t with origin T equals air at t + T with origin 0
    shifted = e.replace(time_origin=jnp.asarray(1.4))
    np.testing.assert_allclose(shifted.air_velocity(jnp.zeros(3), pos=jnp.zeros(3), t=0.3), a2, rtol=1e-12)


def test_table_tilt_changes_bounces_not_flight():
    e = fx.make("table_tilt", slope=[0.008, -0.004], offset=0.001)
    assert changed_keys(e) == TABLE | {"surface"}
    h, n = table_stage.surface((e,), jnp.array([1.0, 0.5, 0.0]))
    np.testing.assert_allclose(float(h), 0.001 + 0.008 - 0.002, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(n), np.array([-0.008, 0.004, 1.0]) / np.sqrt(1 + 0.008**2 + 0.004**2))


def test_table_unevenness_changes_bounces_not_flight():
    e = fx.make("table_unevenness")
    assert changed_keys(e) == TABLE | {"surface"}
    # a bump: the surface rises at its centre by its amplitude
    bump = fx.make("table_unevenness", amplitude=[0.002, 0, 0, 0, 0, 0])
    h, n = table_stage.surface((bump,), jnp.array([0.9, 0.3, 0.0]))
    np.testing.assert_allclose(float(h), 0.002, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(n), [0.0, 0.0, 1.0], atol=1e-12)


def test_ball_variation_changes_the_ball_everywhere_but_the_table_surface():
    e = fx.make("ball_variation", d_radius=2e-4, d_mass=-3e-5)
    assert changed_keys(e) == {"ball", "flight"} | TABLE | RACKET_ALL
    radius, mass = ball_properties(PLAIN.replace(effects=(e,)))
    np.testing.assert_allclose([float(radius), float(mass)], [0.0202, 2.721e-3 - 3e-5], rtol=1e-12)


def test_worn_ball_changes_contacts_not_flight():
    e = fx.make("worn_ball", loss=0.05)
    assert changed_keys(e) == TABLE | RACKET_ALL
    base = base_probe()["table_slow"]
    worn = probe(PLAIN.replace(effects=(e,)))["table_slow"]
    assert worn[5] < base[5]  # lower rebound


def test_buckling_changes_only_fast_impacts():
    e = fx.make("buckling")  # onsets 5 m/s (table) and 15 m/s (racket)
    assert changed_keys(e) == {"table_fast", "racket_centre_fast"}
    assert probe(PLAIN.replace(effects=(e,)))["table_fast"][5] < base_probe()["table_fast"][5]


def test_racket_logo_changes_only_contacts_on_the_logo():
    e = fx.make("racket_logo")
    assert changed_keys(e) == {"racket_logo_slow"}
    assert float(e.weight(jnp.array([0.0, -0.065]))) == 1.0
    assert float(e.weight(jnp.array([0.0, 0.065]))) == 0.0  # towards the tip: no logo


def test_racket_edge_changes_only_contacts_beyond_8cm():
    e = fx.make("racket_edge")
    assert changed_keys(e) == {"racket_edge_slow"}
    assert float(e.weight(jnp.array([0.0, 0.079]))) == 0.0 and float(e.weight(jnp.array([0.0, 0.0815]))) == 1.0


def test_rubber_anisotropy_changes_racket_contacts_only():
    e = fx.make("rubber_anisotropy", anisotropy=0.1)
    assert changed_keys(e) == RACKET_ALL
    coef = racket_stage.ContactCoefficients(e_n=jnp.asarray(0.8), alpha=jnp.array([0.5, 0.5]), e_s=jnp.asarray(1.0))
    out = e.racket_coefficients(coef, d=jnp.zeros(2), vn=5.0, ut=jnp.zeros(2))
    np.testing.assert_allclose(np.asarray(out.alpha), [0.55, 0.45])


def test_air_density_scales_drag_magnus_and_buoyancy_in_flight_only():
    e = fx.make("air_density", d_rho=-0.2)
    assert changed_keys(e) == {"flight"}
    # closed form with constant coefficients: a = (1 + d) (drag + Magnus) + (1 - (1 + d) rho_a / rho_b) g
    cd, cm, d = 0.5, 0.2, -0.2
    model = PLAIN.replace(aero=PLAIN.aero.replace(drag=aero_stage.ConstantCoefficient(jnp.asarray(cd)),
                                                  magnus=aero_stage.ConstantCoefficient(jnp.asarray(cm))))
    radius, mass = ball_properties(model)
    pos, vel, spin = jnp.array([-0.5, 0.2, 0.3]), jnp.array([9.0, -1.0, 2.0]), jnp.array([-50.0, 400.0, 80.0])
    got = aero_stage.acceleration(model.aero, radius, mass, pos, vel, spin, 0.0, (e,))
    ratio = (1 + d) * float(model.aero.rho_air) * (4 / 3) * np.pi * float(radius) ** 3 / float(mass)
    v, w = np.asarray(vel), np.asarray(spin)
    want = (-(3 / (8 * float(radius))) * cd * ratio * np.linalg.norm(v) * v + cm * ratio * np.cross(w, v)
            + (1 - ratio) * np.asarray(model.aero.gravity))
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-12)
    # the drag table reads C_D at the Reynolds number of the denser / thinner air: nu / (1 + d)
    rho, nu = e.air_properties((PLAIN.aero.rho_air, PLAIN.aero.nu))
    np.testing.assert_allclose([float(rho), float(nu)], [1.204 * 0.8, 1.506e-5 / 0.8], rtol=1e-12)
    cd_thin, _ = aero_stage.coefficients(PLAIN.aero, vel, spin, radius, nu)
    cd_plain, _ = aero_stage.coefficients(PLAIN.aero, vel, spin, radius)
    assert float(cd_thin) != float(cd_plain)
    # the fused path reads the hooked density and viscosity (a CPU's kernel body; a GPU's Triton
    # kernel has no hooks: the reference path there)
    from ttsim_jax.kernel import fused

    dense = PLAIN.replace(effects=(e,))
    assert fused.in_flight(dense) and not fused.in_flight(PLAIN)
    params, _ = fused.pack(dense, 1e-3, None, jnp.float64)
    plain, _ = fused.pack(PLAIN, 1e-3, None, jnp.float64)
    np.testing.assert_allclose(float(params[2]), 0.8 * float(plain[2]), rtol=1e-12)  # rho_air / rho_ball
    np.testing.assert_allclose(float(params[3]), float(nu), rtol=1e-12)


def test_table_friction_changes_the_tangential_velocity_of_sliding_bounces_only():
    e = fx.make("table_friction", d_mu=0.3)
    # the slow bounce slides throughout; the fast one's contact point ends rolling (grip 2/5)
    assert changed_keys(e) == {"table_slow"}
    got, base = probe(PLAIN.replace(effects=(e,)))["table_slow"], base_probe()["table_slow"]
    assert got[3] < base[3] and got[4] != base[4]  # more friction: the contact point's slip brakes v_x harder
    assert got[5] == base[5] and np.array_equal(got[:3], base[:3])  # normal velocity, position unchanged
    assert float(table_stage.friction(PLAIN.table, 2.0, (e,))) == pytest.approx(0.25 * 1.3, rel=1e-12)
    # a ball sliding on the table decelerates by about mu (1 + d_mu) g per step
    radius, _ = ball_properties(PLAIN)
    pos, vel, spin = jnp.array([0.3, 0.0, radius - 1e-5]), jnp.array([3.0, 0.0, -0.01]), jnp.zeros(3)
    for eff, mu in (((), 0.25), ((e,), 0.325)):
        _, v, _ = table_stage.slide(PLAIN.table, radius, pos, vel, spin, eff)
        np.testing.assert_allclose(3.0 - float(v[0]), mu * 0.01, rtol=1e-9)


# ------------------------------------------------------------------------ gradients
def _grad_of_stages(effect):
    """Gradient of a scalar made of every stage's output w.r.t. the effect's parameters."""

    def loss(eff):
        out = probe_jax(PLAIN.replace(effects=(eff,)))
        return sum(jnp.sum(v**2) for v in out)

    return jax.grad(loss)(effect)


def probe_jax(model):
    radius, mass = ball_properties(model)
    f = aero_stage.derivative(model.aero, radius, mass, model.effects)
    y = (jnp.array([-0.5, 0.2, 0.3]), jnp.array([9.0, -1.0, 2.0]), jnp.array([-50.0, 400.0, 80.0]))
    outs = [jnp.concatenate(f(y, jnp.asarray(0.7))[1:])]
    for vz in (-9.0, -2.0):  # the contact point ends rolling, slides throughout
        outs += list(table_stage.table_contact(model.table, radius, jnp.array([0.9, 0.3, 0.02]), jnp.array([5.0, 0.5, vz]),
                                               jnp.array([20.0, -150.0, 30.0]), model.effects))
    for d in ((0.0, -0.0795), (0.0, 0.0805), (0.03, 0.02)):  # on the logo's and the rim's band edges
        outs.append(_racket_probe(model, jnp.asarray(d), 30.0))
    return outs


@pytest.mark.parametrize("name", SIM)
def test_gradients_through_each_effect_are_finite(name):
    cls = fx.effect_class(name)
    for inst in (cls.default(), cls.neutral()):
        g = _grad_of_stages(inst)
        leaves = jax.tree.leaves(g)
        assert all(np.all(np.isfinite(np.asarray(x))) for x in leaves), name
    assert any(np.any(np.asarray(x) != 0) for x in jax.tree.leaves(_grad_of_stages(cls.default()))), name


@pytest.mark.slow  # the reverse pass through every effect compiles for about two minutes
def test_rally_kernel_neutral_and_gradients():
    """Through simulate() with every in-simulator effect: at neutral values exactly the plain
    model's rally (contacts included); and one jax.grad, finite everywhere and nonzero for every
    effect (the balls hit the racket's centre, logo and rim fast, and bounce on the table)."""
    n = 300
    d = np.array([[0.02, 0.01], [0.0, -0.0795], [0.0, 0.0805]])
    hit = (np.asarray(R_POS) + d[:, :1] * np.asarray(R_ROT[:, 1]) + d[:, 1:] * np.asarray(R_ROT[:, 2])
           + 0.03 * np.asarray(R_ROT[:, 0]))
    # 0.3 m at 20 m/s: the ball drops 1.3 mm under gravity on the way, so start that much higher
    start = np.concatenate([hit + np.array([-0.3, 0.0, 0.0013]), [[-1.2, 0.1, 0.3]]])
    vel = np.concatenate([np.tile([20.0, 0.0, 0.0], (3, 1)), [[6.0, 0.2, -1.0]]])
    balls = Ball.create(start, vel, np.tile([0.0, 0.0, 30.0], (4, 1)))
    racket = Racket.create(R_POS, rot=R_ROT, face=(0.09, 0.09))
    sched = jax.tree.map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), racket)

    def run(model):
        # Euler and no rematerialisation keep the compiled gradient small (the hooks are the same
        # with any integrator; 300 steps of 4 balls need no checkpoints)
        state, r = rollout(model, init_state(balls), n, 1e-3, sched, integrator="euler", execution=Execution(remat=False))
        out = jnp.concatenate([state.ball.as_array().ravel(), r.events.post.vel.ravel(), r.events.time.ravel()])
        return jnp.sum(state.ball.vel**2) + jnp.sum(state.ball.spin**2) * 1e-4, (out, r.events.kind)

    plain, (plain_out, kinds) = run(PLAIN)
    kinds = np.asarray(kinds)
    assert (kinds[:3, 0] == 2).all() and kinds[3, 0] == 1  # racket contacts, a bounce
    contact = np.asarray(simulate(PLAIN, balls, n, racket=sched, integrator="euler").events.contact[:3, 0])
    np.testing.assert_allclose(contact, d, atol=5e-4)  # on the logo's and the rim's band edges

    # one compiled program for both calls (the effects' values change, not their structure)
    grad = jax.jit(jax.value_and_grad(lambda e: run(PLAIN.replace(effects=e)), has_aux=True))
    (value, (out, _)), _ = grad(tuple(fx.effect_class(n).neutral() for n in SIM))
    # exact up to the rounding of a differently fused (autodiff) program; the stage-level test above
    # is bit for bit
    np.testing.assert_allclose(np.asarray(out), np.asarray(plain_out), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(float(value), float(plain), rtol=1e-13)

    (_, _), g = grad(tuple(fx.effect_class(n).default() for n in SIM))
    for name, ge in zip(SIM, g):
        leaves = [np.asarray(x) for x in jax.tree.leaves(ge)]
        assert all(np.all(np.isfinite(x)) for x in leaves), name
        assert any(np.any(x != 0) for x in leaves), name


def test_every_parameter_declares_a_plausible_range_holding_its_neutral_and_typical_values():
    for name in SIM + REC:
        cls = fx.effect_class(name)
        assert cls.implausible(cls.default().to_dict()) == [], name
        assert cls.implausible(cls.neutral().to_dict()) == [], name


@pytest.mark.parametrize("name", SIM + REC)
def test_the_generator_draws_only_plausible_effects(name):
    cls = fx.effect_class(name)
    rng = np.random.default_rng(0)
    bad = [f for f in (cls.implausible(cls._draw(rng)) for _ in range(300)) if f]
    assert not bad, bad[:3]


def test_implausible_values_are_named_with_their_range():
    tilt = fx.effect_class("table_tilt")
    (b,) = tilt.implausible({"slope": [0.0164, -0.002], "offset": 0.0})  # 0.94 deg along x
    assert (b["param"], b["index"], b["value"], b["high"]) == ("slope", [0], 0.0164, 0.0131)
    air = fx.effect_class("air_flow")
    (b,) = air.implausible({"wind": [0.1, 0.0, 0.08]})  # an 8 cm/s indoor updraft
    assert (b["param"], b["index"]) == ("wind", [2])
    assert air.implausible({"wind": [0.58, 0.0, 0.0]})[0]["index"] == [0]  # a 0.58 m/s draught
    ball = fx.effect_class("ball_variation")
    assert [b["param"] for b in ball.implausible({"d_radius": 3.0e-4, "d_mass": 8.0e-5})] == ["d_mass"]  # 2.78 g


def test_a_parameter_without_a_plausible_range_is_refused():
    from flax import struct

    from ttsim_jax.effects.base import Effect, Param, register

    @struct.dataclass
    class Unbounded(Effect):
        k: jnp.ndarray
        NAME = "unbounded_test_effect"
        PARAMS = {"k": Param("1", 0.0, 0.1, "a gain")}

        def spin_derivative(self, value, **_):
            return value

    with pytest.raises(ValueError, match="plausible"):
        register(Unbounded)
    assert "unbounded_test_effect" not in fx.CATALOGUE
