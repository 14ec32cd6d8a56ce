"""A task chooses its racket: ``racket_config`` loads a fitted configuration into ReturnBall."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.return_ball import ReturnBall, jit_reset, jit_step
from ttsim_jax.params import ConfigError, load_model

OVERRIDES = {"shots.bank": 16, "shots.aim": False}


def test_return_ball_plays_with_a_fitted_racket():
    config = load_task_config("return_ball", dict(OVERRIDES, racket_config="racket_05"))
    assert config.racket_config == "racket_05"
    env = ReturnBall(config, 2)
    params = env.default_params()
    fitted = load_model("conti2026", racket="racket_05")
    assert float(params.model.racket.et0) == pytest.approx(float(fitted.racket.et0))
    assert params.model.residual is not None
    obs, state = jit_reset(env, jax.random.PRNGKey(0), params)
    for i in range(5):
        obs, state, reward, done, trunc, info = jit_step(env, jax.random.PRNGKey(i), state, jnp.zeros((2, 5)), params)
    assert np.isfinite(np.asarray(obs)).all()


def test_an_unknown_racket_is_refused_at_load():
    with pytest.raises(ConfigError, match="unknown racket 'rubber_x'.*racket_01"):
        load_task_config("return_ball", dict(OVERRIDES, racket_config="rubber_x"))
