"""The ball axis sharded over 4 forced host devices gives the unsharded results, the sampled
residual network's draws at a racket policy's contacts included (run in a subprocess: the device
count is fixed when JAX starts)."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

SCRIPT = textwrap.dedent("""
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    assert jax.device_count() == 4, jax.devices()
    from ttsim_jax import Ball, init_state, load_model, per_ball_axes, rollout
    from ttsim_jax.kernel.sharding import sharded_rollout

    rng = np.random.default_rng(0)
    n = 32
    balls = Ball.create(np.stack([rng.uniform(-1.6, -1.2, n), rng.uniform(-.5, .5, n), rng.uniform(.1, .4, n)], -1),
                        np.stack([rng.uniform(3, 12, n), rng.uniform(-1, 1, n), rng.uniform(-2, 2, n)], -1),
                        rng.uniform(-400, 400, (n, 3)))
    from ttsim_jax.physics.events import RACKET
    from ttsim_jax.physics.network import ResidualConfig, init_model
    from ttsim_jax.policies import tracking_rackets

    # a sampled residual network at the rackets of a policy: a ball's draw depends on the key, its
    # step and its id, never on which device holds it
    net = init_model(ResidualConfig(trunk=(16, 16), head_width=8, n_clusters=4), jax.random.key(0))
    net = net.replace(beta_coef=jnp.array([1.0, 0.0, 0.0]), y_scale=jnp.full(6, 0.3))
    m = load_model("conti2026").replace(residual=net)
    e0 = jnp.linspace(0.85, 0.99, n)
    mb = m.replace(table=m.table.replace(e0=e0))
    axes = per_ball_axes(m, "table.e0")
    policy, key = tracking_rackets(), jax.random.key(5)
    s1, o1 = rollout(mb, init_state(balls), 600, 1e-3, policy, model_axes=axes, sample_key=key)
    s2, o2 = sharded_rollout(mb, init_state(balls), 600, 1e-3, policy, model_axes=axes, sample_key=key)
    assert len(s2.ball.pos.sharding.device_set) == 4
    np.testing.assert_allclose(np.asarray(s2.ball.as_array()), np.asarray(s1.ball.as_array()), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(o2.events.kind), np.asarray(o1.events.kind))
    np.testing.assert_allclose(np.asarray(o2.events.post.vel), np.asarray(o1.events.post.vel), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(o2.events.sigma), np.asarray(o1.events.sigma), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(s2.status), np.asarray(s1.status))
    assert int((np.asarray(o1.events.kind) > 0).sum()) >= n // 2
    assert int((np.asarray(o1.events.kind) == RACKET).sum()) >= 4, np.asarray(o1.events.kind)
    assert float(np.abs(np.asarray(o1.events.sigma)).max()) > 0.0  # the network was sampled
    # resumes from a sharded state (same length: the compiled programs are reused)
    s3, _ = sharded_rollout(mb, s2, 600, 1e-3, policy, model_axes=axes, sample_key=key)
    s4, _ = rollout(mb, s1, 600, 1e-3, policy, model_axes=axes, sample_key=key)
    np.testing.assert_allclose(np.asarray(s3.ball.as_array()), np.asarray(s4.ball.as_array()), rtol=1e-12, atol=1e-12)
    print("SHARDED-OK", int((np.asarray(o1.events.kind) > 0).sum()))
""")


def test_sharded_equals_unsharded_on_four_host_devices():
    flags = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()  # keeps conftest's
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu",
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "SHARDED-OK" in proc.stdout


IMPORT_SCRIPT = textwrap.dedent("""
    import importlib, importlib.util, pkgutil
    import jax
    import ttsim_jax
    OPTIONAL = {"ttsim_jax.env.brax_env": "brax"}  # modules of an optional dependency: theirs
    for m in pkgutil.walk_packages(ttsim_jax.__path__, "ttsim_jax."):
        if m.name.endswith("__main__") or (m.name in OPTIONAL and importlib.util.find_spec(OPTIONAL[m.name]) is None):
            continue
        importlib.import_module(m.name)
    jax.config.update("jax_num_cpu_devices", 4)  # refused once a JAX backend has started
    print("DEVICES", jax.device_count())
""")


def test_importing_the_package_leaves_the_device_count_to_the_user():
    """Importing any module of the package starts no JAX backend (no device arrays at import), so a
    user can still choose, after ``import ttsim_jax``, how many host devices to shard over."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("XLA_FLAGS", None)
    proc = subprocess.run([sys.executable, "-c", IMPORT_SCRIPT], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "DEVICES 4" in proc.stdout, proc.stdout
