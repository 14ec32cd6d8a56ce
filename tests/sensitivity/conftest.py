"""Shots shared by the sensitivity tests (float64, 2 ms steps).

Two smooth returns (a topspin drive and a backspin push); ``test_jacobians.py`` adds the drive
moved sideways onto the table's side edge (an event flip) and owns the one compiled reverse pass.
"""

import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.sensitivity.cases import shots_from_states

DT = 2e-3
N_STEPS = 350  # 0.7 s of flight after the contact
SMOOTH = [0, 1]
EDGE = 2


@pytest.fixture(scope="module")
def cfg():
    """The step, horizon and which shot of ``jac_all`` is which."""
    return dict(dt=DT, n_steps=N_STEPS, smooth=SMOOTH, edge=EDGE)


@pytest.fixture(scope="module")
def model():
    return load_model("conti2026", dtype=jnp.float64)


@pytest.fixture(scope="module")
def shots(model):
    pos = np.array([[-1.6, 0.0, 0.25], [-1.5, 0.2, 0.2]])
    vel_in = np.array([[-6.0, 0.2, 1.0], [-4.0, -0.3, 0.5]])
    spin_in = np.array([[0.0, -100.0, 0.0], [0.0, 80.0, 20.0]])
    vel_out = np.array([[8.0, 0.3, 1.8], [4.5, -0.2, 2.2]])
    spin_out = np.array([[0.0, 150.0, 10.0], [0.0, -100.0, 0.0]])
    d = np.array([[0.01, -0.01], [-0.02, 0.005]])
    return shots_from_states(model, pos, vel_in, spin_in, vel_out, spin_out, d, dt=DT,
                             label=np.array(["topspin_drive", "push"]))
