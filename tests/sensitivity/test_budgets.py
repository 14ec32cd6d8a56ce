"""Error budgets: linear propagation against Monte Carlo through the simulator; source files."""

import json

import numpy as np
import pytest

from ttsim_jax.sensitivity import budgets
from ttsim_jax.sensitivity.jacobians import Jacobian


@pytest.mark.slow
def test_linear_budget_matches_monte_carlo_on_smooth_shots(model, jac_all, cfg):
    shots, jac = jac_all
    smooth = shots.take(np.array(cfg["smooth"]))
    sub = Jacobian(jac.target, jac.components, jac.values[cfg["smooth"]], jac.valid[cfg["smooth"]], jac.sequence[cfg["smooth"]],
                   jac.jac[cfg["smooth"]], jac.nominal[cfg["smooth"]], jac.columns, jac.groups)
    sources = budgets.default_sources()
    lin = budgets.linear_budget(sub, sources)
    mc = budgets.monte_carlo(model, smooth, sub, sources, 1000, dt=cfg["dt"], n_steps=cfg["n_steps"], seed=1, batch=256)
    assert np.all(mc["kept"] >= 0.99)  # the event sequence (racket, then table) holds: smooth shots
    lin_std = np.sqrt(np.einsum("bkk->b", lin.cov))
    mc_std = np.sqrt(np.einsum("bkk->b", mc["cov"]))
    assert np.all(lin_std > 1e-3)  # millimetres of spread, not a degenerate case
    np.testing.assert_allclose(mc_std, lin_std, rtol=0.10)
    # per axis too (x: depth, y: sideways)
    np.testing.assert_allclose(mc["std"], lin.std, rtol=0.10)
    # shares add up to one; the racket's orientation dominates a drive's sideways landing spread
    np.testing.assert_allclose(np.nansum(lin.share, 0), 1.0)


def test_linear_budget_closed_form():
    """J C J^T per source with known numbers; the shares are the traces' parts."""
    cols = ["racket.pos[0]", "racket.pos[1]", "racket.pos[2]", "ball.spin[0]", "ball.spin[1]", "ball.spin[2]"]
    j = np.zeros((1, 2, 6))
    j[0, 0, 0], j[0, 1, 1] = 2.0, 1.0  # landing x moves 2x racket x, y 1x racket y
    j[0, 0, 4] = 1e-3  # landing x moves 1 mm per rad/s of spin y
    nominal = np.array([[0, 0, 0, 0, 100.0, 0]])
    jac = Jacobian("landing", ("landing_x", "landing_y"), np.zeros((1, 2)), np.ones(1, bool), np.zeros((1, 2), int),
                   j, nominal, cols, np.array(["racket.pos"] * 3 + ["ball.spin"] * 3, dtype=object))
    sources = budgets.default_sources(racket_pos=0.003 * np.sqrt(3), racket_vel=0, racket_rot_deg=0, spin_rel=0.1,
                                      spin_abs=5.0)
    b = budgets.linear_budget(jac, sources)
    assert b.sources == ["racket position", "spin estimate"]
    var_r = np.array([[4 * 9e-6, 0], [0, 9e-6]])
    var_s = np.array([[1e-6 * (100 + 25), 0], [0, 0]])  # (0.1 * 100)^2 + 5^2 rad^2/s^2 on spin y
    np.testing.assert_allclose(b.parts[0, 0], var_r, atol=1e-15)
    np.testing.assert_allclose(b.parts[1, 0], var_s, atol=1e-15)
    total = np.trace(var_r) + np.trace(var_s)
    np.testing.assert_allclose(b.share[:, 0], [np.trace(var_r) / total, np.trace(var_s) / total])
    # samples drawn from the same sources have that covariance in the input columns
    x = budgets.sample_inputs(jac, sources, 20000, np.random.default_rng(0))[0]
    np.testing.assert_allclose(np.std(x[:, 0]), 0.003, rtol=0.03)
    np.testing.assert_allclose(np.std(x[:, 4]), np.sqrt(125.0), rtol=0.03)


@pytest.mark.parametrize("doc, needle", [
    ({"parameters": ["table.e9"], "covariance": [[1.0]]}, "unknown parameter 'table.e9'"),
    ({"parameters": ["table.e0"], "covariance": [[1.0, 0.0]]}, "shape (1, 2)"),
    ({"parameters": ["table.e0", "table.mu"], "covariance": [[1.0, 2.0], [2.0, 1.0]]}, "not positive semi-definite"),
    ({"parameters": ["table.e0", "table.mu"], "covariance": [[1.0, 0.1], [0.2, 1.0]]}, "not symmetric"),
    ({"covariance": [[1.0]]}, "'parameters' and 'covariance'"),
])
def test_parameter_covariance_file_errors_name_file_and_key(tmp_path, doc, needle):
    path = tmp_path / "cov.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError) as e:
        budgets.parameter_source(path, ["table.e0", "table.mu", "aero.drag.cd[0,0]"])
    assert str(path) in str(e.value) and needle in str(e.value)


def test_parameter_covariance_file_is_a_source(tmp_path):
    path = tmp_path / "cov.json"
    path.write_text(json.dumps({"parameters": ["table.mu", "table.e0"], "covariance": [[4e-4, 0.0], [0.0, 1e-4]]}))
    s = budgets.parameter_source(path, ["table.e0", "table.mu"])
    assert s.columns == ("table.mu", "table.e0") and s.cov[0, 0] == 4e-4
