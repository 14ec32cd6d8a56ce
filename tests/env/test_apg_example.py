"""``examples/apg.py``'s starting policy: the PD it writes as a linear map of the observation, and
that map carried onto normalised observations unchanged (the example's run, which compiles a
reverse pass through whole episodes for minutes, is measured in docs/functional-env.md)."""

import numpy as np
import pytest

from ttsim_jax.env import SingleReturnBall, load_task_config


@pytest.fixture(scope="module")
def env_params():
    env = SingleReturnBall(load_task_config("return_ball_accel", {"shots.bank": 8, "shots.aim": False,
                                                                  "observation.plan": True}))
    return env, env.default_params()


def test_the_tracker_start_is_a_pd_to_the_predicted_hit_point(example, env_params):
    apg = example("apg")
    env, params = env_params
    coef, const = (np.asarray(a) for a in apg.tracker_gains(env, params, omega=12.0, omega_angle=20.0))
    names = env.observation_names
    obs = np.zeros(env.obs_dim, np.float32)
    hit, rk = np.array([1.5, 0.2, 0.4]), np.array([1.9, -0.1, 0.3])
    for k, axis in enumerate("xyz"):
        obs[names.index(f"plan.hit_pos.{axis}")] = hit[k]
        obs[names.index(f"racket.pos.{axis}")] = rk[k]
    obs[names.index("plan.exists")] = 1.0
    obs[names.index("racket.vel.y")] = 0.2  # 2 m/s: the observation holds velocities / 10
    obs[names.index("racket.pitch")] = 0.1
    pre = obs @ coef + const
    accel = float(params.limits.max_accel)
    want = (144.0 * (hit - rk) - 24.0 * np.array([0.0, 2.0, 0.0])) / accel  # omega^2 e - 2 omega v
    np.testing.assert_allclose(pre[:3], want, rtol=1e-5)
    assert pre[3] == pytest.approx(-400.0 * 0.1 / float(params.limits.max_angle_accel), rel=1e-5) and pre[4] == 0
    # no hit predicted: the plan reads 0 and the PD drives the racket to its rest position
    obs[[names.index(f"plan.hit_pos.{a}") for a in "xyz"] + [names.index("plan.exists")]] = 0.0
    obs[names.index("racket.vel.y")] = 0.0
    np.testing.assert_allclose((obs @ coef + const)[:3], 144.0 * (np.asarray(params.start) - rk) / accel, rtol=1e-5,
                               atol=1e-6)
    # on normalised observations the same action
    rng = np.random.default_rng(0)
    mean, scale = rng.normal(size=env.obs_dim).astype(np.float32), rng.uniform(0.1, 3, env.obs_dim).astype(np.float32)
    w, b = apg.normalised((coef, const), (mean, scale))
    x = rng.normal(size=(5, env.obs_dim)).astype(np.float32)
    np.testing.assert_allclose(((x - mean) / scale) @ np.asarray(w) + np.asarray(b), x @ coef + const, rtol=1e-4,
                               atol=1e-4)
