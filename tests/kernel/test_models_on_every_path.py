"""Every bundled model gives the same rollout on every execution path: the reference step, the fused
path that ``fused="auto"`` takes from a batch and a length where it pays, the Pallas kernel (in
interpret mode, as Triton runs it on a GPU) and the ball axis sharded over four host devices.

The fused path's kernel reads each model's coefficients through its own code
(:mod:`ttsim_jax.kernel.fused_params`), so the comparisons are made per model: a model whose
coefficients are packed or read wrongly (nakashima2011's constant drag once read its Magnus
constant) differs here from the reference path by centimetres.
"""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Execution, init_state, load_model, rollout
from ttsim_jax.bundled import config_dir
from ttsim_jax.kernel import fused
from ttsim_jax.kernel.rollout import FUSED_AUTO_MIN_BATCH_CPU, FUSED_AUTO_MIN_STEPS_CPU, fused_pays
from ttsim_jax.physics import aero
from test_fused import _assert_same_rollout
from test_rollout import shots, two_rackets

REPO = Path(__file__).resolve().parents[2]
MODELS = sorted(p.stem for p in (config_dir() / "models").glob("*.toml"))
# the least batch and length at which the default execution takes the fused path on a CPU
B_AUTO, N_AUTO = FUSED_AUTO_MIN_BATCH_CPU, FUSED_AUTO_MIN_STEPS_CPU


def covered(model) -> bool:
    return fused.unsupported(model, None, integrator="rk4", policy=None, rackets_batched=False) is None


COVERED = [m for m in MODELS if covered(load_model(m))]


def test_every_bundled_model_is_listed():
    assert {"conti2026", "durr2026", "nakashima2011"} <= set(MODELS) and len(MODELS) >= 6
    assert len(one_per_reading(COVERED)) == 3  # constant, Dürr's and the tables


@pytest.fixture(scope="module")
def state():
    return init_state(shots(B_AUTO, seed=3))


@pytest.fixture(scope="module")
def references(state):
    """name -> the reference path's rollout of ``state`` (computed once a model, shared by the tests)."""
    done = {}

    def of(name):
        if name not in done:
            done[name] = rollout(load_model(name), state, N_AUTO, 1e-3, two_rackets(N_AUTO),
                                 execution=Execution(fused=False))
        return done[name]
    return of


def kernel_reading(name) -> tuple[str, str]:
    """How the kernel reads a model's coefficients: its drag and Magnus model kinds."""
    a = load_model(name).aero
    return fused.DRAG_KINDS[type(a.drag)], fused.MAGNUS_KINDS[type(a.magnus)]


def one_per_reading(names):
    """The first model of each :func:`kernel_reading` (the others compile the same programs)."""
    firsts = {}
    for name in names:
        firsts.setdefault(kernel_reading(name), name)
    return list(firsts.values())


@pytest.mark.slow  # the constant and table readings run by default, sharded: test_sharded_fused_path_equals_the_reference
@pytest.mark.parametrize("name", COVERED)
def test_default_path_equals_the_reference_path(name, state, references):
    """At the batch and length from which ``fused="auto"`` flies the fused kernel, the default
    execution (then the fused path) gives the reference step's events and states for every bundled
    model the kernel covers."""
    model = load_model(name)
    ref = references(name)
    default = rollout(model, state, N_AUTO, 1e-3, two_rackets(N_AUTO))
    assert jax.default_backend() != "cpu" or fused_pays(B_AUTO, n_steps=N_AUTO)
    _assert_same_rollout(ref, default, 1e-9)
    kinds = np.asarray(ref[1].events.kind)
    assert (kinds > 0).sum() > B_AUTO  # bounces and racket hits: the events' states are compared too


@pytest.mark.parametrize("name", [m for m in MODELS if m not in COVERED])
def test_models_the_kernel_does_not_cover_run_the_reference_path(name):
    """The default execution of a model the kernel does not cover is the reference step (the
    fused path's gate says why), and ``fused=True`` is refused, naming the coefficient model."""
    model = load_model(name)
    assert "coefficient" in fused.unsupported(model, None, integrator="rk4", policy=None, rackets_batched=False)
    with pytest.raises(ValueError, match="does not cover coefficient models"):
        rollout(model, init_state(shots(4, seed=3)), 10, 1e-3, execution=Execution(fused=True))


@pytest.mark.parametrize("name", COVERED)
def test_pallas_kernel_flies_as_the_reference_flight_step(name):
    """The Pallas kernel in interpret mode against the reference stage's RK4 step
    (:func:`ttsim_jax.physics.aero.flight_step`, code of its own), for balls in free flight high
    above the near half (short of the net): positions, velocities and spins equal after the steps the kernel took."""
    model = load_model(name)
    b, steps, dt = 40, 24, 1e-3
    rng = np.random.default_rng(7)
    ball = shots(b, seed=8)
    ball = ball.replace(pos=jnp.asarray(np.stack([rng.uniform(-1.3, -0.8, b), rng.uniform(-0.5, 0.5, b),
                                                  rng.uniform(0.6, 0.9, b)], -1)))
    params, layout = fused.pack(model, jnp.asarray(dt), None, ball.pos.dtype)
    out, n = fused.fly(params, layout, ball, jnp.full(b, steps, jnp.int32), substeps=steps, block=16, interpret=True)
    assert (np.asarray(n) == steps).all()  # nothing near them: every ball took every step

    def one(pos, vel, spin):
        def body(k, y):
            return aero.flight_step(model.aero, model.ball.radius, model.ball.mass, *y, k * dt, dt)
        return jax.lax.fori_loop(0, steps, body, (pos, vel, spin))

    pos, vel, spin = jax.vmap(one)(ball.pos, ball.vel, ball.spin)
    np.testing.assert_allclose(np.asarray(out.pos), np.asarray(pos), rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(np.asarray(out.vel), np.asarray(vel), rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(np.asarray(out.spin), np.asarray(spin), rtol=1e-11, atol=1e-11)
    # drag and Magnus are in it: the same balls without air are centimetres per second away
    vacuum = model.replace(aero=model.aero.replace(rho_air=jnp.zeros_like(model.aero.rho_air)))
    _, bare, _ = jax.vmap(lambda p, v, w: jax.lax.fori_loop(
        0, steps, lambda k, y: aero.flight_step(vacuum.aero, model.ball.radius, model.ball.mass, *y, k * dt, dt),
        (p, v, w)))(ball.pos, ball.vel, ball.spin)
    assert float(jnp.median(jnp.linalg.norm(bare - vel, axis=1))) > 0.01


SHARDED = textwrap.dedent("""
    import sys
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    assert jax.device_count() == 4, jax.devices()
    sys.path[:0] = {tests!r}
    from ttsim_jax import Execution, init_state, load_model
    from ttsim_jax.kernel.sharding import sharded_rollout
    from test_rollout import shots, two_rackets

    state = init_state(shots({b}, seed=3))
    ref = np.load({refs!r})
    # 1e-6: each device's quarter of the batch is rounded a little differently (another block of
    # the ordinary step), which one grazing contact in 1,024 amplifies to 1e-7
    for name in {names!r}:
        s, o = sharded_rollout(load_model(name), state, {n}, 1e-3, two_rackets({n}), execution=Execution(fused=True))
        assert len(s.ball.pos.sharding.device_set) == 4
        np.testing.assert_array_equal(np.asarray(s.status), ref[name + ".status"], err_msg=name)
        np.testing.assert_array_equal(np.asarray(o.events.kind), ref[name + ".kind"], err_msg=name)
        np.testing.assert_allclose(np.asarray(s.ball.as_array()), ref[name + ".ball"], rtol=1e-6, atol=1e-6, err_msg=name)
        np.testing.assert_allclose(np.asarray(o.events.post.as_array()), ref[name + ".post"], rtol=1e-6, atol=1e-6,
                                   err_msg=name)
        print("SHARDED-OK", name)
""")


@pytest.mark.parametrize("names", [
    # by default the constant reading (nakashima2011's, where the drag once read Magnus's constant;
    # the tables' sharded path is tests/kernel/test_sharding.py's, their fused path test_fused.py's);
    # with -m slow the tables and Dürr's reading too, and then every bundled model
    pytest.param([n for n in one_per_reading(COVERED) if kernel_reading(n)[1] == "constant"], id="constant"),
    pytest.param(one_per_reading(COVERED), id="each-reading", marks=pytest.mark.slow),
    pytest.param(COVERED, id="every-model", marks=pytest.mark.slow)])
def test_sharded_fused_path_equals_the_reference(names, references, tmp_path):
    """The fused path sharded over 4 forced host devices (a subprocess: the device count is fixed
    when JAX starts; each device flies a quarter of the batch) gives the unsharded reference path's
    rollout, model by model: by default the constant reading, with ``-m slow`` the tables' and
    Dürr's readings too and every bundled model the kernel covers."""
    refs = {}
    for name in names:
        s, o = references(name)
        refs.update({name + ".status": np.asarray(s.status), name + ".kind": np.asarray(o.events.kind),
                     name + ".ball": np.asarray(s.ball.as_array()), name + ".post": np.asarray(o.events.post.as_array())})
    np.savez(tmp_path / "references.npz", **refs)
    tests = [str(Path(__file__).parent), str(Path(__file__).parents[1])]
    script = SHARDED.format(tests=tests, b=B_AUTO, n=N_AUTO, names=names, refs=str(tmp_path / "references.npz"))
    flags = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu",
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert [line.split()[1] for line in proc.stdout.splitlines() if line.startswith("SHARDED-OK")] == names
