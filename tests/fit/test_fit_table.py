"""Table contact identification recovers known parameters from synthetic bounces.

The truth is conti2026's restitution law and residual matrices, keeping only the entries a fit
can see at this noise: an entry whose effect on the bounces (|entry| x RMS of its feature) is below
0.01 m/s (velocity rows) or 1 rad/s (spin rows) is set to zero, as are the entries that act on
nothing (dA_vv[2, 2] is e0's column; (R v)_y = 0). One shape (N bounces) for every fit.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.fit import table as T
from ttsim_jax.reality import synthetic_stages as S
from ttsim_jax.physics import table as tbl

N = 2000
NOISE_VEL, NOISE_SPIN = 0.05, 5.0  # m/s, rad/s: states estimated from ~2 mm positions at 200 Hz


def _blocks(full):
    return np.stack([full[:3, :3], full[:3, 3:6], full[3:, :3], full[3:, 3:6]])


@pytest.fixture(scope="module")
def truth():
    model = load_model("conti2026")
    res = np.asarray(model.table.residual, np.float64).copy()
    res[0, 2, 2] = 0.0
    res[0, :, 1] = res[2, :, 1] = 0.0
    table = model.table.replace(residual=jnp.asarray(res, jnp.float32))
    clean = S.synthetic_bounces(table, 0.02, N, seed=3)
    v, w = clean["true_vel_in"], clean["true_spin_in"]
    heading = v[:, :2] / np.linalg.norm(v[:, :2], axis=1, keepdims=True)
    local = [np.linalg.norm(v[:, :2], axis=1), 0.0 * v[:, 0], v[:, 2],  # R v, R w: the residual's features
             heading[:, 0] * w[:, 0] + heading[:, 1] * w[:, 1], heading[:, 0] * w[:, 1] - heading[:, 1] * w[:, 0],
             w[:, 2]]
    rms = np.sqrt(np.mean(np.stack(local, 1) ** 2, axis=0))
    full = np.zeros((6, 6))
    full[:3, :3], full[:3, 3:], full[3:, :3], full[3:, 3:] = res
    effect = np.abs(full) * rms[None, :]
    full[:3][effect[:3] < 0.01] = 0.0
    full[3:][effect[3:] < 1.0] = 0.0
    res = _blocks(np.concatenate([full, np.zeros((6, 1))], 1))
    table = model.table.replace(residual=jnp.asarray(res, jnp.float32))
    return model, table, res


@pytest.fixture(scope="module")
def noisy_fit(truth):
    model, table, _ = truth
    data = S.synthetic_bounces(table, 0.02, N, seed=1, noise_vel=NOISE_VEL, noise_spin=NOISE_SPIN)
    fit = T.fit_table(data["vel_in"], data["spin_in"], data["vel_out"], data["spin_out"], model)
    print(f"\ntable fit ({N} bounces, noise {NOISE_VEL} m/s, {NOISE_SPIN} rad/s): e0 {fit.e0:.4f} +- "
          f"{fit.stderr_e0:.4f} (true {float(table.e0):.4f}), e1 {fit.e1:.4f} +- {fit.stderr_e1:.4f} "
          f"(true {float(table.e1):.4f})\n" + fit.summary())
    return fit, data


def test_restitution_within_0_01(truth, noisy_fit):
    _, table, _ = truth
    fit, _ = noisy_fit
    assert abs(fit.e0 - float(table.e0)) < 0.01
    assert abs(fit.e1 - float(table.e1)) < 0.01
    # The reported uncertainty is honest: the errors are a few standard errors at most.
    assert abs(fit.e0 - float(table.e0)) < 4 * fit.stderr_e0
    assert abs(fit.e1 - float(table.e1)) < 4 * fit.stderr_e1


def test_sparsity_pattern_recovered(truth, noisy_fit):
    _, _, res = truth
    fit, _ = noisy_fit
    assert 8 <= int((res != 0).sum()) < 29  # sparse among the 29 identifiable entries, not trivially so
    np.testing.assert_array_equal(fit.pattern, res != 0)
    # Non-zero entries near their true values (relative to the largest entry of their matrix).
    for k in range(4):
        scale = np.max(np.abs(res[k]))
        np.testing.assert_allclose(fit.residual[k], res[k], atol=0.15 * scale)
    assert fit.lambdas[fit.lambda_index] >= fit.lambdas[fit.lambda_min_index]  # 1se: the sparser side
    assert np.all(np.isnan(fit.stderr[~fit.pattern])) and np.all(fit.stderr[fit.pattern] > 0)


def test_noiseless_bounces_give_the_exact_model_and_skip_bounded_ones(truth):
    """Without noise the fit is exact, which needs the bounces where the simulator bounds the
    residual left out: the fit finds them from its own matrices."""
    model, table, res = truth
    data = S.synthetic_bounces(table, 0.02, N, seed=2)
    assert np.all(data["weight"] == 1.0)  # the residual creates no energy on rally-like bounces
    # so the first 100 become grazing drives with backspin (10-16 m/s, v_z -0.25 to -0.1 m/s), on
    # most of which the raw residual would create energy and the simulator bounds it
    rng = np.random.default_rng(5)
    heading, vh = rng.uniform(-np.pi, np.pi, 100), rng.uniform(10.0, 16.0, 100)
    c, s = np.cos(heading), np.sin(heading)
    vel = np.stack([vh * c, vh * s, rng.uniform(-0.25, -0.1, 100)], 1)
    w_loc = np.stack([rng.uniform(-150, 150, 100), rng.uniform(-550, -400, 100), rng.uniform(-300, 300, 100)], 1)
    spin = np.stack([w_loc[:, 0] * c - w_loc[:, 1] * s, w_loc[:, 0] * s + w_loc[:, 1] * c, w_loc[:, 2]], 1)

    def bounce(v, w):
        base_v, base_w, dv, dw = tbl.residual_terms(table, 0.02, v, w)
        lam = tbl.residual_bound(table.kappa, 0.02, v, w, base_v, base_w, dv, dw)
        return (*tbl.local_contact(table, 0.02, v, w), lam)

    graze = jax.vmap(bounce)(jnp.asarray(vel, jnp.float32), jnp.asarray(spin, jnp.float32))
    for k, x in zip(("vel_in", "spin_in", "vel_out", "spin_out", "weight"), (vel, spin, *graze)):
        data[k] = np.concatenate([np.asarray(x, np.float64), data[k][100:]])
    assert np.sum(data["weight"] < 0.999) > 10  # the draw includes bounded bounces
    fit = T.fit_table(data["vel_in"], data["spin_in"], data["vel_out"], data["spin_out"], model)
    assert fit.n_bounded == int(np.sum(data["weight"] < 0.999))
    np.testing.assert_array_equal(fit.used, data["weight"] >= 0.999)
    assert abs(fit.e0 - float(table.e0)) < 1e-3 and abs(fit.e1 - float(table.e1)) < 1e-4
    np.testing.assert_allclose(fit.residual, res, atol=2e-3 * np.max(np.abs(res)), rtol=1e-2)


def test_sections_round_trip_through_a_config(truth, noisy_fit, tmp_path):
    from ttsim_jax.fit.aero_forms import write_config
    from ttsim_jax.params import resolve_model_path

    model, _, _ = truth
    fit, _ = noisy_fit
    out = write_config(resolve_model_path("conti2026"), tmp_path / "t.toml", T.table_sections(model.table, fit),
                       name="t", source="test")
    loaded = load_model(out)
    np.testing.assert_allclose(float(loaded.table.e0), fit.e0, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(loaded.table.residual), fit.residual, rtol=1e-5, atol=1e-12)
    assert float(loaded.table.mu) == pytest.approx(float(model.table.mu))


def test_bad_input_is_refused(truth):
    model = truth[0]
    v = np.ones((20, 3))
    bad = v.copy()
    bad[3, 1] = np.inf
    with pytest.raises(ValueError, match=r"spin_out .*rows \[3\]"):
        T.fit_table(v, v, v, bad, model)
    with pytest.raises(ValueError, match="at least 10"):
        T.fit_table(v[:6], v[:6], v[:6], v[:6], model)


def test_a_restitution_above_one_is_held_at_the_bound(truth):
    """Bounces whose e_n extrapolates to e0 = 1.06 at v_z = 0 (the bounces themselves, v_z from -7 to
    -2.5 m/s, have e_n 0.71-0.93; no residual matrices): a free fit finds e0 > 1, a bounce that
    gains energy; the fit holds e0 at e_max = 1 and refits e1 there (the least-squares optimum on
    the bound)."""
    model, table, _ = truth
    steep = table.replace(e0=jnp.asarray(1.06, jnp.float32), e1=jnp.asarray(0.05, jnp.float32),
                          residual=jnp.zeros_like(table.residual))
    data = S.synthetic_bounces(steep, 0.02, N, seed=4, noise_vel=NOISE_VEL, noise_spin=NOISE_SPIN)
    fit = T.fit_table(data["vel_in"], data["spin_in"], data["vel_out"], data["spin_out"], model)
    assert fit.unconstrained["e0"] == pytest.approx(1.06, abs=0.02)
    assert fit.e0 == pytest.approx(float(model.table.e_max), abs=1e-6) and fit.stderr_e0 == 0.0
    assert fit.bounds == ["e0 <= e_max = 1"] and "held at a physical bound" in fit.summary()
    vz = data["vel_in"][:, 2]
    e_n = fit.e0 + fit.e1 * vz
    assert np.all((e_n >= 0.0) & (e_n <= 1.0))
    # on the bound, e1 is the least-squares fit of v_z+ = -(1 + e1 v_z) v_z over the bounces used
    used = fit.used
    vzo = data["vel_out"][used, 2]
    e1_closed = -np.sum((vzo + vz[used]) * vz[used] ** 2) / np.sum(vz[used] ** 4)
    assert fit.e1 == pytest.approx(e1_closed, abs=1e-6)
