"""Gradients through the environment: ``jax.grad`` of an episode's return with respect to the
actions, through env steps and the kernel's contacts, is finite over a whole episode (its end
included) and is the return's central finite difference where the rally's events do not change.

Reverse passes through 20-150 environment steps, each compiling for one to three minutes on two
cores: run with ``-m slow``.
"""

import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax.env import SingleReturnBall, load_task_config

OVERRIDES = {"shots.bank": 32, "shots.aim": False}

# float32, as the environment runs by default (the suite runs in float64): in a process of its own
FLOAT32 = """
import sys
import jax, jax.numpy as jnp
sys.path.insert(0, {here!r})
from test_env_gradient import episode_return
from ttsim_jax.env import SingleReturnBall, load_task_config
env = SingleReturnBall(load_task_config("return_ball", {{"shots.bank": 32, "shots.aim": False}}))
g = jax.jit(jax.grad(episode_return(env)))(jnp.zeros((150, env.action_dim)))
assert g.dtype == jnp.float32, g.dtype
print("FINITE" if bool(jnp.isfinite(g).all()) else f"NOT FINITE: {{int(jnp.isnan(g).sum())}} NaN")
"""


def episode_return(env, remat: bool = False):
    """actions (T, 5) -> the summed reward of T steps of ``env`` (no reset) from its first shot;
    ``remat``: each step rematerialised in the reverse pass (``jax.checkpoint``), as
    ``examples/apg.py`` does, so the reverse pass keeps one step's intermediates, not T steps'
    (at T = 150 the compile sets the process's peak all the same)."""
    params = env.default_params()
    _, state = env.reset(jax.random.PRNGKey(0), params)

    def total(actions):
        def body(s, a):
            _, s, r, *_ = env.step_env(jax.random.PRNGKey(1), s, a, params)
            return s, r
        return jax.lax.scan(jax.checkpoint(body) if remat else body, state, actions)[1].sum()

    return total


@pytest.mark.slow
def test_the_gradient_through_a_whole_float32_episode_is_finite():
    """150 steps of the default (intercept) task in float32: the episode ends at step 121, and the
    steps after its end, where the tracker's square roots meet negative discriminants, gave NaN in
    every entry until those roots were made safe (``physics.numerics.safe_sqrt``)."""
    repo = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=str(repo) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("JAX_ENABLE_X64", None)
    script = FLOAT32.format(here=str(Path(__file__).resolve().parent))
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().splitlines()[-1] == "FINITE", done.stdout


@pytest.mark.slow
def test_the_gradient_is_the_returns_finite_difference():
    """The "accel" task, 150 steps, each rematerialised: d(return)/d(action) of entries early, midway
    and late in the episode within 2 % of the central difference (measured: 0.15-0.17 % off). The
    step is 1e-3 in [-1, 1] actions: the events stay the same, and the rewards, float32 whatever the
    default float, resolve the difference to about 1e-4."""
    env = SingleReturnBall(load_task_config("return_ball_accel", OVERRIDES))
    total = episode_return(env, remat=True)
    actions = jnp.zeros((150, env.action_dim), jnp.float64)
    grad = np.asarray(jax.jit(jax.grad(total))(actions))
    f = jax.jit(total)
    assert np.isfinite(grad).all()
    for k, j in ((0, 0), (5, 1), (60, 0), (100, 2), (140, 0)):
        e = jnp.zeros_like(actions).at[k, j].set(1e-3)
        fd = (float(f(actions + e)) - float(f(actions - e))) / 2e-3
        assert abs(grad[k, j]) > 1e-4, (k, j, grad[k, j])
        assert grad[k, j] == pytest.approx(fd, rel=0.02), (k, j, grad[k, j], fd)
