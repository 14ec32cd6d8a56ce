"""Error budgets: linear propagation with known numbers, sampling, source files (Monte Carlo through
the simulator is checked in ``test_jacobians.py``, beside the compiled Jacobian it needs)."""

import json

import numpy as np
import pytest

from ttsim_jax.sensitivity import budgets
from ttsim_jax.sensitivity.jacobians import Jacobian


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
