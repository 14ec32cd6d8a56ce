"""Aerodynamic identification (ttsim_jax.fit.flightfit, ttsim_jax.fit.aero_forms) on synthetic segments
from known parameters: the per-segment fit, the regression into the paper's forms, the config."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.fit import flightfit as A
from ttsim_jax.fit import segment_batches as B
from ttsim_jax.reality.synthetic_segments import synthetic_segments
from ttsim_jax.fit import aero_forms as F
from ttsim_jax.physics import aero as P

NOISE = 0.002  # m per axis: paper-like tracking noise (the paper's fits reach ~8 mm RMSE in 3-D)


@pytest.fixture(scope="module")
def model():
    return load_model("conti2026")


@pytest.fixture(scope="module")
def constant(model):
    """48 segments, each with its own constant (C_D, C_M); the last 6 without spin."""
    rng = np.random.default_rng(1)
    n = 48
    coef = np.stack([rng.uniform(0.4, 0.6, n), rng.uniform(0.05, 0.3, n)], 1)
    coef[-6:, 1] = 0.0  # no Magnus force: these fly as if without spin
    times, pos, spins, states = synthetic_segments(model.aero, model.ball.radius, model.ball.mass, n, seed=3,
                                                     coefficients=coef, noise=NOISE)
    spins[-6:] = 0.0
    return coef, times, pos, spins, states, A.fit_segments(times, pos, spins)


@pytest.fixture(scope="module")
def tabulated(model):
    """256 segments flown with the paper's C_D and C_M tables, fitted per segment."""
    times, pos, spins, _ = synthetic_segments(model.aero, model.ball.radius, model.ball.mass, 256, seed=5,
                                                speed=(3.0, 18.0), spin_rate=(20.0, 700.0), noise=NOISE)
    return spins, A.fit_segments(times, pos, spins)  # 16 groups of 16: the compiled shape of `constant`


def test_constant_coefficients_recovered(constant):
    coef, _, _, spins, states, fit = constant
    spun = np.linalg.norm(spins, axis=1) > 0
    assert np.all(np.abs(fit.cd - coef[:, 0]) < 0.02)
    assert np.all(np.abs(fit.cm[spun] - coef[spun, 1]) < 0.02)
    assert np.all(np.abs(fit.theta[:, :3] - states[:, :3]) < 0.005)
    assert np.all(np.abs(fit.theta[:, 3:6] - states[:, 3:6]) < 0.1)
    # Residuals are the noise: RMSE of 3-D errors ~ sqrt(3) sigma.
    np.testing.assert_allclose(np.median(fit.rmse), np.sqrt(3) * NOISE, rtol=0.15)


def test_standard_errors_are_calibrated(constant):
    coef, _, _, spins, _, fit = constant
    spun = np.linalg.norm(spins, axis=1) > 0
    z = np.abs(np.r_[(fit.cd - coef[:, 0]) / fit.stderr[:, 6], (fit.cm - coef[:, 1])[spun] / fit.stderr[spun, 7]])
    assert 0.55 <= np.mean(z < 1.0) <= 0.85  # ~68 % for a calibrated Gaussian
    assert np.mean(z < 3.0) >= 0.95


def test_without_spin_magnus_is_left_alone(constant):
    _, _, _, spins, _, fit = constant
    still = np.linalg.norm(spins, axis=1) == 0
    np.testing.assert_allclose(fit.cm[still], A.CM_0, atol=1e-6)
    assert np.all(fit.stderr[still, 7] > 1.0)
    assert np.all(fit.stderr[~still, 7] < 0.02)


def test_padding_and_batch_company_do_not_change_a_fit(constant):
    _, times, pos, spins, _, fit = constant
    # Segment 0 among copies of the shortest segment: a batch of the same shape whose integration
    # stops at segment 0's own length instead of the longest segment's.
    short = int(np.argmin([len(t) for t in times]))
    assert len(times[short]) < len(times[0]) < max(len(t) for t in times)
    rows = [0] + [short] * (len(times) - 1)
    company = A.fit_segments([times[i] for i in rows], [pos[i] for i in rows], spins[rows])
    np.testing.assert_allclose(company.theta[0], fit.theta[0], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(company.theta[1], fit.theta[short], rtol=1e-4, atol=1e-5)


def test_groups_hold_similar_lengths_and_every_segment_once():
    """The grouping of fit_segments: one shape per capacity, balanced groups sorted by length."""
    rng = np.random.default_rng(0)
    lengths = np.r_[rng.integers(3, 250, 200), 300, 700, 2]  # two longer capacities; one too short
    times = [np.arange(n) / 100.0 for n in lengths]
    positions = [np.zeros((n, 3)) for n in lengths]
    calls = list(B.grouped_batches(times, positions, np.zeros((len(lengths), 3)), batch=64, group=16))
    seen = [i for idx, *_ in calls for i in idx]
    assert sorted(seen) == sorted(np.flatnonzero(lengths >= 3).tolist())
    shapes = {}
    fill = []
    for idx, rows, (tau, pos, mask, spin), n_max in calls:
        shapes.setdefault(tau.shape[2], set()).add(tau.shape[1:])
        g, r = tau.shape[:2]
        assert g * r <= 64 and r <= 16 and len(n_max) == g
        expected = np.zeros(g * r)
        expected[rows] = lengths[idx]
        np.testing.assert_array_equal(mask.reshape(g * r, -1).sum(1), expected)  # each segment in its row
        for j in range(g):
            own = [lengths[i] for i, k in zip(idx, rows) if k // r == j]
            assert n_max[j] == (max(own) if own else 0)
            if own and tau.shape[2] == 256:
                fill.append(len(own))
    assert all(len(v) == 1 for v in shapes.values())  # one group shape, one compilation, per capacity
    assert max(fill) - min(fill) <= 1  # groups split evenly, not full groups and a remainder
    # Sorted: a group's segments are no longer than the next group's.
    order = [lengths[i] for idx, *_ in calls for i in idx]
    assert order == sorted(order)


def test_fit_agrees_with_scipy_least_squares(model, constant):
    """The batched solver's optimum is scipy's (least_squares, method 'lm', float64, same residual)."""
    from scipy.optimize import least_squares

    _, times, pos, spins, _, fit = constant
    air = A.Air.from_model(model, jnp.float64)
    residual = jax.jit(A.residual)
    for i in range(0, 42, 3):  # spun segments (the last six fly without spin)
        args = [jnp.asarray(a[0], jnp.float64) for a in B.pack(times, pos, spins, [i], 256, 1, np.float64)]
        fun = lambda th: np.asarray(residual(jnp.asarray(th), *args, len(times[i]), air))  # noqa: E731
        sol = least_squares(fun, fit.theta[i], method="lm", xtol=1e-12, ftol=1e-12)
        # Within 2 % of a standard error (float32 itself leaves about 1 %): stopping on the
        # predicted reduction leaves nothing of consequence (a tolerance of 1e-4 leaves 4 %).
        assert np.all(np.abs(fit.theta[i, 6:] - sol.x[6:]) < 0.02 * fit.stderr[i, 6:]), (i, fit.theta[i], sol.x)
        np.testing.assert_allclose(fit.rmse[i], np.sqrt(sol.fun @ sol.fun / len(times[i])), rtol=1e-4)


def test_normal_equations_match_the_residuals_jacobian(model, constant):
    _, times, pos, spins, _, fit = constant
    air = A.Air.from_model(model)
    tau, p, m, s = (jnp.asarray(a[0]) for a in B.pack(times, pos, spins, [0], B.capacity(len(times[0])), 1))
    n = len(times[0])
    theta = jnp.asarray(fit.theta[0], jnp.float32) + jnp.array([0.01, 0, 0, 0.1, 0, 0, 0.05, 0.02], jnp.float32)
    residual = jax.jit(A.residual)
    cost, jtj, jtr, vel = jax.jit(A.normal_equations)(theta, tau, p, m, s, n, air)
    jac, r, vel_ref = jax.jit(A.jacobian)(theta, tau, p, m, s, n, air)
    # two programs (one under forward mode), which XLA may contract into multiply-adds differently:
    # within an ulp or two of a float32 position of a few metres
    np.testing.assert_allclose(r, residual(theta, tau, p, m, s, n, air), rtol=0, atol=5e-7)
    np.testing.assert_allclose(cost, r @ r, rtol=1e-4)
    np.testing.assert_allclose(jtj, jac.T @ jac, rtol=1e-3, atol=1e-4 * float(jnp.max(jnp.abs(jtj))))
    np.testing.assert_allclose(jtr, jac.T @ r, rtol=1e-3, atol=1e-4 * float(jnp.max(jnp.abs(jtr))))
    np.testing.assert_allclose(vel, vel_ref, atol=1e-5)
    # The forward-mode Jacobian against central differences in float64.
    th64 = np.asarray(theta, np.float64)
    air64 = A.Air.from_model(model, jnp.float64)
    args64 = [jnp.asarray(a, jnp.float64) for a in (tau, p, m, s)]
    for j, eps in ((4, 1e-5), (6, 1e-6), (7, 1e-6)):
        e = np.zeros(8)
        e[j] = eps
        fd = (residual(th64 + e, *args64, n, air64) - residual(th64 - e, *args64, n, air64)) / (2 * eps)
        np.testing.assert_allclose(jac[:, j], fd, rtol=2e-3, atol=1e-4 * np.max(np.abs(fd)))


def test_effective_speeds_are_the_papers(constant):
    _, _, _, spins, _, fit = constant
    v = fit.velocities[0].astype(np.float64)
    speed = np.linalg.norm(v, axis=1)
    sin = np.linalg.norm(np.cross(v, spins[0]), axis=1) / (speed * np.linalg.norm(spins[0]))
    np.testing.assert_allclose(fit.v_eff_drag[0], np.sum(speed**3) / np.sum(speed**2), rtol=1e-5)
    np.testing.assert_allclose(fit.v_eff_magnus[0], np.sum(speed**2 * sin) / np.sum(speed * sin), rtol=1e-5)
    (sp, wt), = F.force_weights(fit.velocities[:1], spins[:1], "magnus")
    np.testing.assert_allclose(np.sum(sp * wt), fit.v_eff_magnus[0], rtol=1e-5)


def _magnus(table, model, speed, spin_rate):
    """The Magnus form at many (speed, spin rate) points."""
    f = jax.jit(jax.vmap(lambda v, w: P.magnus_table(table, v, w, model.ball.radius, model.aero.nu)))
    return np.asarray(f(jnp.asarray(speed), jnp.asarray(spin_rate)))


def _flat_priors(model):
    mg = model.aero.magnus
    drag = model.aero.drag.replace(cd=jnp.full_like(model.aero.drag.cd, 0.5))
    magnus = mg.replace(m1=jnp.zeros_like(mg.m1), s=jnp.full_like(mg.s, 0.2), a=jnp.zeros_like(mg.a),
                        b=jnp.zeros_like(mg.b), c=jnp.full_like(mg.c, 0.2))
    return drag, magnus


def test_drag_table_recovered_where_data_exists(model, tabulated):
    spins, fit = tabulated
    drag0, _ = _flat_priors(model)
    samples = F.force_weights(fit.velocities, spins, "drag")
    w = np.linalg.norm(spins, axis=1)
    truth = np.asarray(model.aero.drag.cd)
    errors = {}
    for assoc in F.ASSOCIATIONS:
        res = F.fit_drag_table(drag0, fit.cd, fit.stderr[:, 6], samples, w, model.ball.radius, model.aero.nu,
                               association=assoc)
        supported = res.support >= 9.0
        assert supported.sum() >= 10
        errors[assoc] = np.abs(res.values["cd"] - truth)[supported]
        # Entries without data stay near the flat prior, far from the truth's ridge and trough.
        assert np.all(np.abs(res.values["cd"][res.support < 0.5] - 0.5) < 0.03)
    assert errors["averaged"].max() < 0.02
    # Crediting a segment with the form at its single effective speed misses the trough by more.
    assert errors["v_eff"].max() > errors["averaged"].max()


def test_magnus_form_recovered_from_exact_coefficients(model, tabulated):
    """The regression alone: coefficients equal to the true form at the segments' (v_eff, w)."""
    spins, fit = tabulated
    _, magnus0 = _flat_priors(model)
    mg = model.aero.magnus
    w = np.linalg.norm(spins, axis=1)
    cm_true = _magnus(mg, model, fit.v_eff_magnus, w)
    samples = F.force_weights(fit.velocities, spins, "magnus")
    res = F.fit_magnus_table(magnus0, cm_true, np.full(len(w), 1e-3), samples, w, association="v_eff",
                             alpha=1e-3, continuity=1.0)
    fitted = mg.replace(**{k: jnp.asarray(v) for k, v in res.values.items()})
    cm_fit = _magnus(fitted, model, fit.v_eff_magnus, w)
    assert np.percentile(np.abs(cm_fit - cm_true), 90) < 0.02


def test_magnus_form_end_to_end(model, tabulated):
    spins, fit = tabulated
    _, magnus0 = _flat_priors(model)
    mg = model.aero.magnus
    w = np.linalg.norm(spins, axis=1)
    res = F.fit_magnus_table(magnus0, fit.cm, fit.stderr[:, 7], F.force_weights(fit.velocities, spins, "magnus"), w,
                             association="averaged")
    fitted = mg.replace(**{k: jnp.asarray(v) for k, v in res.values.items()})
    # At the reference speeds most segments fly at, over the spin rates they have.
    lam = F._speed_weights(np.asarray(mg.v_ref), fit.v_eff_magnus)
    checked = 0
    for k, v in enumerate(np.asarray(mg.v_ref)):
        near = lam[:, k] > 0.5
        if near.sum() < 70:
            continue
        grid = np.linspace(*np.percentile(w[near], [5, 95]), 40)
        err = _magnus(fitted, model, np.full_like(grid, v), grid) - _magnus(mg, model, np.full_like(grid, v), grid)
        assert np.max(np.abs(err)) < 0.02, (v, np.max(np.abs(err)))
        checked += 1
    assert checked >= 2


def test_export_config_is_loadable(model, tmp_path):
    from ttsim_jax.params import resolve_model_path

    cd = np.asarray(model.aero.drag.cd) + 0.01
    values = {k: np.asarray(getattr(model.aero.magnus, k)) * 1.1 for k in F.MAGNUS_FITTED}
    out = F.export_config(resolve_model_path("conti2026"), tmp_path / "fitted.toml", cd, values, name="fitted",
                          source='fit of "x"')
    loaded = load_model(out)
    assert loaded.name == "fitted"
    np.testing.assert_allclose(np.asarray(loaded.aero.drag.cd), cd, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(loaded.aero.magnus.b), values["b"], rtol=1e-5)
    np.testing.assert_allclose(np.asarray(loaded.table.e0), np.asarray(model.table.e0))
    with pytest.raises(KeyError, match="aero.lift"):
        F.replace_sections("[aero]\nx = 1\n", {"aero.lift": ""})
