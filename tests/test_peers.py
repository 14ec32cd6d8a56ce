"""The peers benchmark's plain scan and numba loop agree with the rally kernel on a few shots.

The benchmark runs in float32 with JAX's default (32-bit) types, so these tests switch off the
suite's float64 mode while they run.
"""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jax
import jax.numpy as jnp

from benchmarks import peers
from ttsim_jax import load_model
from ttsim_jax.policies import tracking_rackets
from ttsim_jax.state import Ball

N_STEPS = 100
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def float32_mode():
    with jax.enable_x64(False):
        yield


@pytest.fixture(scope="module")
def setup():
    with jax.enable_x64(False):
        return _setup()


def _setup():
    model = load_model("conti2026", dtype=jnp.float32)
    # balls that bounce on the table (first four) or reach a tracking racket (last four) in 100 steps
    pos = np.array([[-0.6, 0.1, 0.2], [-0.2, -0.3, 0.12], [0.3, 0.2, 0.15], [-1.0, 0.0, 0.2],
                    [1.5, 0.1, 0.3], [1.2, -0.2, 0.4], [-1.4, 0.0, 0.3], [1.0, 0.3, 0.2]])
    vel = np.array([[12.0, 0.5, -2.0], [6.0, 1.0, -1.0], [4.0, -0.5, -3.0], [20.0, 0.0, -4.0],
                    [10.0, 0.0, 1.0], [14.0, 1.0, 0.0], [-12.0, 0.5, 1.0], [18.0, -2.0, 0.5]])
    spin = np.array([[0.0, 300.0, 0.0], [0.0, -200.0, 50.0], [100.0, 0.0, -100.0], [0.0, 800.0, 0.0],
                     [0.0, 100.0, 0.0], [0.0, -300.0, 100.0], [0.0, -400.0, 0.0], [50.0, 500.0, 0.0]])
    shots = Ball(*(a.astype(np.float32) for a in (pos, vel, spin)))
    balls = Ball(*(jnp.asarray(a) for a in (shots.pos, shots.vel, shots.spin)))
    kernel = {cfg: [np.asarray(a) for a in peers.kernel_rollout(model, balls, N_STEPS, peers.DT, pol)]
              for cfg, pol in (("table", None), ("rackets", tracking_rackets()))}
    return model, balls, shots, kernel


def test_shots_exercise_contacts(setup):
    _, balls, _, kernel = setup
    assert np.isfinite(kernel["table"][1][:, 0]).sum() >= 4  # first bounces to compare
    # the rackets send some balls back
    assert np.sum(np.linalg.norm(kernel["table"][0] - kernel["rackets"][0], axis=-1) > 0.1) >= 2


@pytest.mark.parametrize("cfg", ["table", "rackets"])
def test_plain_scan_agrees_with_kernel(setup, cfg):
    model, balls, _, kernel = setup
    pol = tracking_rackets() if cfg == "rackets" else None
    pos, first = (np.asarray(a) for a in peers.plain_rollout(model, balls, N_STEPS, peers.DT, pol))
    k_pos, k_first = kernel[cfg]
    # no time of impact: a bounce is up to one step late, a few cm at the end for fast balls
    assert np.max(np.linalg.norm(pos - k_pos, axis=-1)) < 0.05
    both = np.isfinite(first[:, 0]) & np.isfinite(k_first[:, 0])
    assert both.sum() == np.isfinite(k_first[:, 0]).sum()
    if cfg == "table":  # the interpolated landing point is sub-millimetre
        assert np.max(np.linalg.norm(first[both] - k_first[both], axis=-1)) < 1e-3


@pytest.mark.parametrize("cfg", ["table", "rackets"])
def test_numba_agrees_with_kernel(setup, cfg):
    pn = pytest.importorskip("benchmarks.peers_numba", reason="numba not installed (pip install -e .[bench])")
    model, _, shots, kernel = setup
    params = pn.pack_params(model, tracking_rackets().params)
    state, status, first = pn.rollout_cpu(params, shots, N_STEPS, peers.DT, cfg == "rackets")
    k_pos, k_first = kernel[cfg]
    # the same times of impact; 1 mm: the hand-written table bounce leaves out the residual's fade at low horizontal speed
    # and its energy bound (physics/table.py), which move a grazing bounce by a fraction of a mm
    assert np.max(np.linalg.norm(state[:, :3] - k_pos, axis=-1)) < 1e-3
    np.testing.assert_array_equal(np.isfinite(first[:, 0]), np.isfinite(k_first[:, 0]))
    ok = np.isfinite(k_first[:, 0])
    assert np.max(np.linalg.norm(first[ok] - k_first[ok], axis=-1)) < 1e-5


def test_numba_stays_float32():
    pn = pytest.importorskip("benchmarks.peers_numba", reason="numba not installed (pip install -e .[bench])")
    import numba

    pn.rollout_cpu(pn.pack_params(load_model("conti2026", dtype=jnp.float32), tracking_rackets().params),
                   peers._shots(1)[1], 1, peers.DT, True)
    disp = pn._run_ball_cpu
    assert disp.signatures
    for sig in disp.signatures:
        typemap = disp.overloads[sig].type_annotation.typemap
        assert not [name for name, t in typemap.items() if t == numba.float64]


def test_cuda_loop_matches_cpu_loop_in_the_simulator(setup, tmp_path):
    """The CUDA kernel, run by numba's CUDA simulator (no GPU needed), equals the CPU loop."""
    pn = pytest.importorskip("benchmarks.peers_numba", reason="numba not installed (pip install -e .[bench])")
    model, _, shots, _ = setup
    params = pn.pack_params(model, tracking_rackets().params)
    np.savez(tmp_path / "in.npz", pos=shots.pos, vel=shots.vel, spin=shots.spin, **params)
    script = f"""
import numpy as np
from benchmarks import peers_numba as pn
from ttsim_jax.state import Ball
d = np.load({str(tmp_path / "in.npz")!r})
params = {{k: d[k] for k in ("scalars", "re_ref", "sp", "cd", "v_ref", "mag", "residual", "rot")}}
assert pn.cuda_available()
state, status, first = pn.rollout_cuda(params, Ball(d["pos"], d["vel"], d["spin"]), {N_STEPS}, {peers.DT}, True)
np.savez({str(tmp_path / "out.npz")!r}, state=state, status=status, first=first)
"""
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1", PYTHONPATH=str(REPO))
    subprocess.run([sys.executable, "-c", script], env=env, check=True, timeout=300)
    out = np.load(tmp_path / "out.npz")
    state, status, first = pn.rollout_cpu(params, shots, N_STEPS, peers.DT, True)
    np.testing.assert_allclose(out["state"], state, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(out["status"], status)
