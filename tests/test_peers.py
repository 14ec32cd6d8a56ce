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


def test_lean_loop_agrees_with_kernel(setup):
    """The lean loop (plane z = r, linear time of impact) meets the table where the kernel does."""
    pn = pytest.importorskip("benchmarks.peers_numba", reason="numba not installed (pip install -e .[bench])")
    model, _, shots, kernel = setup
    params = pn.pack_params(model, tracking_rackets().params)
    state, status, first = pn.rollout_cpu(params, shots, N_STEPS, peers.DT, False, lean=True)
    k_pos, k_first = kernel["table"]
    np.testing.assert_array_equal(np.isfinite(first[:, 0]), np.isfinite(k_first[:, 0]))
    ok = np.isfinite(k_first[:, 0])
    # the linear zero of the height on a path curved by at most |a| dt^2 / 8 (a few um at 1 ms): a
    # bounce found at a step's end point instead would be up to |v| dt (1-2 cm) off
    assert np.max(np.linalg.norm(first[ok] - k_first[ok], axis=-1)) < 3e-5
    assert np.max(np.linalg.norm(state[:, :3] - k_pos, axis=-1)) < 3e-5
    with pytest.raises(ValueError, match="no rackets"):
        pn.rollout_cpu(params, shots, 1, peers.DT, True, lean=True)


def test_bracketed_tables_equal_the_kernels_flight():
    """One RK4 step of the hand-written stages, tables read as ramps or by bracketing, equals
    ``aero.flight_step`` over speeds and spins that reach every part of the C_D and C_M tables
    (below the first and beyond the last reference, Sp beyond its last breakpoint, both C_M branches)."""
    pn = pytest.importorskip("benchmarks.peers_numba", reason="numba not installed (pip install -e .[bench])")
    from numba import njit

    from ttsim_jax.physics import aero

    model = load_model("conti2026", dtype=jnp.float32)
    p = pn.pack_params(model, tracking_rackets().params)
    rng = np.random.default_rng(3)
    n, dt = 64, np.float32(0.01)
    unit = lambda: (lambda u: u / np.linalg.norm(u, axis=-1, keepdims=True))(rng.normal(size=(n, 3)))  # noqa: E731
    vel = (unit() * rng.uniform(0.5, 40.0, (n, 1))).astype(np.float32)
    spin = (unit() * rng.uniform(0.0, 1000.0, (n, 1))).astype(np.float32)
    pos = np.zeros((n, 3), np.float32)
    step = jax.jit(jax.vmap(lambda v, w: aero.flight_step(model.aero, model.ball.radius, model.ball.mass,
                                                          jnp.zeros(3, jnp.float32), v, w, 0.0, dt)[1]))
    dv_ref = np.asarray(step(vel, spin)) - vel
    for bracket in (False, True):
        rk4 = pn.make_stages(njit, bracket=bracket)[3]
        got = np.array([rk4(p["scalars"], p["re_ref"], p["sp"], p["cd"], p["v_ref"], p["mag"], *pos[i], *vel[i],
                            *spin[i], dt)[3:] for i in range(n)]) - vel
        # float32 rounding of v1 - v0 at |v| <= 40 m/s; a C_D or C_M off by 1 % moves dv by more
        np.testing.assert_allclose(got, dv_ref, rtol=2e-3, atol=2e-5, err_msg=f"bracket={bracket}")


def test_targets_divide_by_the_chosen_loop():
    """Each configuration's kernel (and the fused kernel) over numba's or the lean loop's flight + table."""
    rate = lambda x: {"ball_steps_per_s": x}  # noqa: E731
    report = {"configs": {
        "table": {"results": [{"batch": 8, "peers": {"kernel": rate(2.0), "kernel_fused": rate(6.0), "numba": rate(4.0),
                                                    "numba_lean": rate(8.0)}}]},
        "rackets": {"results": [{"batch": 8, "peers": {"kernel": rate(1.0), "numba": rate(3.0)}}]}}}
    assert peers.targets(report) == [{"batch": 8, "table": 0.5, "table_fused": 1.5, "rackets": 0.25}]
    assert peers.targets(report, "numba_lean") == [{"batch": 8, "table": 0.25, "table_fused": 0.75, "rackets": 0.125}]


@pytest.mark.parametrize("lean", [False, True])
def test_numba_stays_float32(lean):
    pn = pytest.importorskip("benchmarks.peers_numba", reason="numba not installed (pip install -e .[bench])")
    import numba

    pn.rollout_cpu(pn.pack_params(load_model("conti2026", dtype=jnp.float32), tracking_rackets().params),
                   peers._shots(1)[1], 1, peers.DT, not lean, lean=lean)
    disp = pn._run_lean_cpu if lean else pn._run_ball_cpu
    assert disp.signatures
    for sig in disp.signatures:
        typemap = disp.overloads[sig].type_annotation.typemap
        assert not [name for name, t in typemap.items() if t == numba.float64]


def test_cuda_loop_matches_cpu_loop_in_the_simulator(setup, tmp_path):
    """The CUDA kernels (full with rackets, lean), run by numba's CUDA simulator (no GPU needed),
    equal the CPU loops."""
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
balls = Ball(d["pos"], d["vel"], d["spin"])
state, status, first = pn.rollout_cuda(params, balls, {N_STEPS}, {peers.DT}, True)
lean_state, lean_status, lean_first = pn.rollout_cuda(params, balls, {N_STEPS}, {peers.DT}, False, lean=True)
np.savez({str(tmp_path / "out.npz")!r}, state=state, status=status, first=first, lean_state=lean_state,
         lean_status=lean_status, lean_first=lean_first)
"""
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1", PYTHONPATH=str(REPO))
    subprocess.run([sys.executable, "-c", script], env=env, check=True, timeout=300)
    out = np.load(tmp_path / "out.npz")
    for prefix, lean in (("", False), ("lean_", True)):
        state, status, first = pn.rollout_cpu(params, shots, N_STEPS, peers.DT, not lean, lean=lean)
        np.testing.assert_allclose(out[prefix + "state"], state, rtol=0, atol=1e-5)
        np.testing.assert_array_equal(out[prefix + "status"], status)
        np.testing.assert_allclose(out[prefix + "first"], first, rtol=0, atol=1e-5)
