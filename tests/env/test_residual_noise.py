"""Residual-network noise as domain randomisation (``[residual]`` of a task file): the draw acts on
the racket contacts only, differs from key to key, and vanishes with the network's predicted
standard deviations; the section's errors name the file and the key. One compiled environment:
8 environments in intercept mode with a small untrained network, played with action 0."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.return_ball import ReturnBall, jit_reset, jit_step_env
from ttsim_jax.params import ConfigError
from ttsim_jax.physics.network import ResidualConfig, init_model
from ttsim_jax.physics.network_checkpoint import save_residual

N = 8
TINY = ResidualConfig(trunk=(16, 16), head_width=8, n_clusters=20, dropout=0.1)
QUIET = {"shots.bank": 64, "shots.aim": True, "observation.noise_pos": 0.0, "observation.noise_vel": 0.0}


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    path = tmp_path_factory.mktemp("net") / "tiny.ttres"
    net = init_model(TINY, jax.random.key(0))
    # inputs scaled into the untrained network's range, no attenuation: a correction at every contact
    n = TINY.n_inputs
    save_residual(path, net.replace(x_min=jnp.full(n, -1e3, jnp.float32), x_max=jnp.full(n, 1e3, jnp.float32),
                                    beta_coef=jnp.array([1.0, 0.0, 0.0], jnp.float32)))
    env = ReturnBall(load_task_config("return_ball", {**QUIET, "residual.checkpoint": str(path),
                                                                "residual.sample": True}), N)
    return env, env.default_params()


def play(env, params, key):
    """Ball states after every control step and the step of each environment's first contact."""
    _, state = jit_reset(env, jax.random.PRNGKey(5), params)
    balls, first = [], np.full(N, -1)
    for i in range(env.max_steps):
        _, state, _, term, trunc, info = jit_step_env(env, jax.random.fold_in(key, i), state, jnp.zeros((N, 5)),
                                                      params)
        balls.append(np.concatenate([np.asarray(state.rally.ball.vel), np.asarray(state.rally.ball.spin)], -1))
        first = np.where((first < 0) & np.asarray(info["contact"]), i, first)
        if (np.asarray(term) | np.asarray(trunc)).all():
            break
    return np.stack(balls), first


def test_sampled_correction_changes_the_contacts_only_and_vanishes_with_sigma(env):
    env, params = env
    (a, hit_a), (b, hit_b) = play(env, params, jax.random.PRNGKey(1)), play(env, params, jax.random.PRNGKey(2))
    assert np.isfinite(a).all() and np.isfinite(b).all()
    np.testing.assert_array_equal(hit_a, hit_b)  # the same path up to each contact
    hit = np.flatnonzero(hit_a >= 0)
    assert len(hit) >= 4
    for e in range(N):
        until = hit_a[e] if hit_a[e] >= 0 else min(len(a), len(b))
        np.testing.assert_array_equal(a[:until, e], b[:until, e])  # nothing random before the contact
    for e in hit:  # each environment's contact drew its own correction
        assert np.abs(a[hit_a[e], e] - b[hit_a[e], e]).max() > 1e-3
    # the network's standard deviations at zero: the keys no longer matter (same compiled step)
    net = params.model.residual
    sharp = params.replace(model=params.model.replace(residual=net.replace(sigma_scale=jnp.zeros_like(net.sigma_scale))))
    (c, _), (d, _) = play(env, sharp, jax.random.PRNGKey(1)), play(env, sharp, jax.random.PRNGKey(2))
    np.testing.assert_array_equal(c, d)
    assert not np.array_equal(c[:len(a)], a[:len(c)])


@pytest.mark.parametrize("overrides, match", [
    ({"residual.sample": True}, r"\[residual\] sample = true needs a network"),
    ({"residual.checkpoint": "nope.ttres"}, r"\[residual\] checkpoint = 'nope.ttres': no such file"),
    ({"residual.sample": 1}, r"\[residual\] sample = 1: expected true or false"),
])
def test_bad_residual_section_is_refused_naming_file_and_key(overrides, match):
    with pytest.raises(ConfigError, match=match) as err:
        load_task_config("return_ball", overrides)
    assert "return_ball.toml" in str(err.value)
