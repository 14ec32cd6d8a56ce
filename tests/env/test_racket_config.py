"""A task chooses its racket: ``racket_config`` loads a fitted configuration into ReturnBall."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.return_ball import ReturnBall, jit_reset, jit_step
from ttsim_jax.params import ConfigError, available_rackets, load_model

OVERRIDES = {"shots.bank": 16, "shots.aim": False}


def test_return_ball_plays_with_every_fitted_racket():
    env = None
    for name in available_rackets():
        config = load_task_config("return_ball", dict(OVERRIDES, racket_config=name))
        assert config.racket_config == name
        params = ReturnBall(config, 2).default_params()
        fitted = load_model("conti2026", racket=name)
        assert float(params.model.racket.et0) == pytest.approx(float(fitted.racket.et0))
        assert params.model.residual is not None
        # the rubber lives in the parameters: the first environment's step plays the others (under one
        # name: the model's name is static, each name would compile the step again)
        params = params.replace(model=params.model.replace(name="rubber"))
        env = env or ReturnBall(config, 2)
        obs, state = jit_reset(env, jax.random.PRNGKey(0), params)
        for i in range(3):
            obs, state, reward, done, trunc, info = jit_step(env, jax.random.PRNGKey(i), state, jnp.zeros((2, 5)),
                                                             params)
        assert np.isfinite(np.asarray(obs)).all() and np.isfinite(np.asarray(reward)).all(), name


def test_an_unknown_racket_is_refused_at_load():
    with pytest.raises(ConfigError, match="unknown racket 'rubber_x'.*racket_01"):
        load_task_config("return_ball", dict(OVERRIDES, racket_config="rubber_x"))


def test_a_tracker_that_does_not_know_its_rubber_plans_with_the_models_racket():
    generic = load_model("conti2026")
    fitted = load_model("conti2026", racket="racket_10")
    for known, planned in ((True, fitted), (False, generic)):
        overrides = dict(OVERRIDES, racket_config="racket_10", **{"intercept.racket_known": known})
        params = ReturnBall(load_task_config("return_ball", overrides), 2).default_params()
        assert float(params.model.racket.e0) == pytest.approx(float(fitted.racket.e0))  # the rally: the rubber
        assert float(params.intercept.e_racket) == pytest.approx(float(planned.racket.e0))  # the plan
        assert float(params.intercept.contact.et0) == pytest.approx(float(planned.racket.et0))
