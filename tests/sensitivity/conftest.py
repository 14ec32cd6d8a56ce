"""Shots shared by the sensitivity tests (float64, 2 ms steps, one compiled shape per function).

Two smooth returns (a topspin drive and a backspin push) and the drive moved sideways so that it
lands with its centre 2 mm inside the table's side edge plus a radius: it touches the edge, and a
small change of the racket's orientation makes it miss the table (an event flip). Flight does not
depend on y, so moving the ball and the racket sideways moves the landing by the same amount.
"""

import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.sensitivity.cases import shots_from_states
from ttsim_jax.sensitivity.jacobians import jacobian

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
    smooth = shots_from_states(model, pos, vel_in, spin_in, vel_out, spin_out, d, dt=DT,
                               label=np.array(["topspin_drive", "push"]))
    return smooth


@pytest.fixture(scope="module")
def jac_all(model, shots):
    """(shot set with the edge shot appended, its reverse-mode Jacobian)."""
    from ttsim_jax.sensitivity.jacobians import outcomes, flatten_inputs, layout_of

    # where the drive lands, then the same drive moved sideways onto the side edge
    first = outcomes(model, shots, flatten_inputs(model, shots, layout_of(model)), target="landing", dt=DT,
                     n_steps=N_STEPS, batch=256)
    edge = shots.take(np.array([0, 1, 0]))
    shift = model.table.width / 2 + float(model.ball.radius) - 0.002 - first.values[0, 1]
    edge.ball.pos[2, 1] += shift
    edge.racket.pos[2, 1] += shift
    edge.label[2] = "edge"
    return edge, jacobian(model, edge, target="landing", dt=DT, n_steps=N_STEPS, mode="rev")
