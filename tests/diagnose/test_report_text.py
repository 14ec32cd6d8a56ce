"""The report's text: one unit per quantity (flight errors in mm, velocities in m/s, in the
verdict as in the tables), fitted parameters rounded and named, never a cut-off JSON string."""

import numpy as np

from ttsim_jax.diagnose.report import params_text
from ttsim_jax.diagnose.where import shown


def test_errors_are_shown_in_the_units_of_the_tables():
    assert shown("flight", 0.00439) == "4.39 mm" and shown("landing", 0.6) == "600 mm"
    assert shown("table", 1.2512) == "1.25 m/s" and shown("racket", 0.379) == "0.379 m/s"


def test_fitted_parameters_are_rounded_named_by_session_and_unused_terms_left_out():
    params = {"air_flow": {"0": {"wind": np.array([0.3855113595724106, -0.10195768810808659, 0.019994240812957288]),
                                 "gust_amp": np.zeros((3, 3)), "gust_freq": np.zeros(3)},
                           "1": {"wind": np.array([0.28, -0.02, 0.03]), "gust_amp": np.zeros((3, 3)),
                                 "gust_freq": np.zeros(3)}}}
    text = params_text(params, "air_flow")
    assert text == "wind (session 0) = [0.386, -0.102, 0.02]; wind (session 1) = [0.28, -0.02, 0.03]"
    assert params_text({"spin_decay": {"rate": 0.08346954882144927, "quadratic": 0.0001597048044204712}},
                       "spin_decay") == "rate = 0.0835; quadratic = 0.00016"
    # many sessions: cut at whole items, with a count of the rest, and one line (a table cell)
    many = {"air_density": {str(s): {"d_rho": 0.01 * (s + 1)} for s in range(40)}}
    text = params_text(many, "air_density", limit=100)
    assert text.endswith("more in diagnosis.json") and "\n" not in text and len(text) < 160
    assert text.startswith("d_rho (session 0) = 0.01; d_rho (session 1) = 0.02;")
    assert params_text({"table_tilt": {"angle": np.zeros(2)}}, "table_tilt") == "none"
