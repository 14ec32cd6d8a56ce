"""The vector environment under gymnasium's conventions: next-step autoreset against same-step,
gymnasium's vector wrappers on it, checked actions, and the CleanRL-style example run briefly.

One compiled shape, the one ``test_return_ball.py`` steps: 8 environments of the "accel" task with
a bank of 64 unaimed shots; a zero action lets every ball go by, so episodes end within 2 s.
"""

import gymnasium
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode
from gymnasium.wrappers import vector as wrappers

import ttsim_jax  # noqa: F401  (registers the environments)
from ttsim_jax.env.gym import ActionError
from ttsim_jax.env.rally_rules import RUNNING

N = 8
TASK = "return_ball_accel"
OVERRIDES = {"shots.bank": 64, "shots.aim": False}
ZERO = np.zeros((N, 5), np.float32)
STEPS = 150  # a still racket misses every ball well before its 200-step limit


def make(mode=AutoresetMode.NEXT_STEP):
    return gymnasium.make_vec("ttsim/ReturnBall-v0", num_envs=N, task=TASK, overrides=OVERRIDES, autoreset_mode=mode)


@pytest.fixture(scope="module")
def runs():
    """The same seed and actions in both autoreset modes: (reset obs, step results) of each."""
    out = {}
    for mode in (AutoresetMode.SAME_STEP, AutoresetMode.NEXT_STEP):
        vec = make(mode)
        obs, _ = vec.reset(seed=3)
        out[mode] = [obs] + [vec.step(ZERO) for _ in range(STEPS)]
    return out


def test_next_step_shows_the_last_observation_then_restarts_in_the_next_step(runs):
    """Next-step autoreset, as gymnasium's own vector environments do it: the ending step returns
    the episode's last observation (same-step's ``final_obs``); the next step returns the new
    episode's first observation (same-step's observation of the ending step), reward 0, neither
    terminated nor truncated, and does not step that environment (its clock still reads 0 there
    and one period after)."""
    same, nxt = runs[AutoresetMode.SAME_STEP], runs[AutoresetMode.NEXT_STEP]
    period = 1.0 / 100.0
    done = np.array([s[2] | s[3] for s in same[1:]])
    first_end = int(np.argmax(done.any(1))) + 1
    assert 1 < first_end < STEPS - 2
    np.testing.assert_array_equal(same[0], nxt[0])
    for k in range(1, first_end):  # identical until an episode ends
        np.testing.assert_array_equal(same[k][0], nxt[k][0])
        np.testing.assert_array_equal(same[k][1], nxt[k][1])
    ended = np.flatnonzero(done[first_end - 1])
    _, _, term, trunc, info = same[first_end]
    obs, reward, n_term, n_trunc, n_info = nxt[first_end]
    assert "final_obs" not in n_info and "final_obs" in info
    np.testing.assert_array_equal(obs[ended], info["final_obs"][ended])
    np.testing.assert_array_equal(n_term | n_trunc, term | trunc)
    obs, reward, n_term, n_trunc, n_info = nxt[first_end + 1]
    np.testing.assert_array_equal(obs[ended], same[first_end][0][ended])  # the new episode's first observation
    assert (reward[ended] == 0.0).all() and not (n_term | n_trunc)[ended].any()
    assert (n_info["outcome"][ended] == RUNNING).all() and (n_info["landing_error"][ended] == -1.0).all()
    assert (obs[ended, -3] == 0.0).all()  # clock at 0: the waiting environment was not stepped
    np.testing.assert_allclose(nxt[first_end + 2][0][ended, -3], period, rtol=1e-6)
    # every episode of either mode ended as a miss or the opponent's fault, and as many ended in both
    ends = [sum(int((s[2] | s[3]).sum()) for s in r[1:first_end + 1]) for r in (same, nxt)]
    assert ends[0] == ends[1] >= 1


def test_record_episode_statistics_counts_each_episode_once_with_its_return_and_length():
    vec = wrappers.RecordEpisodeStatistics(make())
    vec.reset(seed=5)
    running = np.zeros(N)
    restart = np.zeros(N, bool)
    seen = 0
    for _ in range(STEPS):
        obs, reward, term, trunc, info = vec.step(ZERO)
        running = np.where(restart, 0.0, running) + reward  # a restarting step's reward is 0
        if "episode" in info:
            mask = info["_episode"]
            np.testing.assert_array_equal(mask, term | trunc)
            np.testing.assert_allclose(info["episode"]["r"][mask], running[mask], rtol=1e-5)
            # the episode's length is its clock in control steps: the restarting steps are not counted
            np.testing.assert_array_equal(info["episode"]["l"][mask], np.round(obs[mask, -3] * 100.0).astype(int))
            seen += int(mask.sum())
        restart = term | trunc
    assert seen >= N // 2


def test_gymnasiums_vector_wrappers_run_on_next_step_and_refuse_same_step():
    with pytest.raises(ValueError, match="Expected autoreset_mode to be NEXT_STEP or DISABLED, got .*SAME_STEP"):
        wrappers.NormalizeObservation(make(AutoresetMode.SAME_STEP))
    vec = wrappers.NormalizeReward(wrappers.ClipAction(wrappers.NormalizeObservation(
        wrappers.FlattenObservation(wrappers.RecordEpisodeStatistics(make())))))
    obs, _ = vec.reset(seed=0)
    assert obs.shape == (N, 25)
    big = np.full((N, 5), 3.0, np.float32)  # clipped to the action space by ClipAction
    for _ in range(60):
        obs, reward, term, trunc, info = vec.step(big)
        assert np.isfinite(obs).all() and np.isfinite(reward).all()
    inner = vec.env.env  # NormalizeObservation
    assert inner.obs_rms.count > 60 * N
    # normalised: the running mean of every entry that varies is near 0 in its own units
    varying = inner.obs_rms.var > 1e-6
    assert np.abs(obs[:, varying].mean(0)).max() < 5.0


def test_actions_are_checked_naming_the_space_and_the_environment():
    vec = make()
    vec.reset(seed=0)
    with pytest.raises(ActionError, match=r"action of shape \(8, 4\): the action space is Box\(-1.0, 1.0, \(8, 5\)"):
        vec.step(np.zeros((N, 4), np.float32))
    with pytest.raises(ActionError, match=r"action of shape \(5,\)"):
        vec.step(np.zeros(5, np.float32))
    bad = ZERO.copy()
    bad[3, 1] = np.nan
    bad[6, 0] = np.inf
    with pytest.raises(ActionError, match=r"environment\(s\) \[3, 6\] holds NaN or infinite"):
        vec.step(bad)
    # a refused action changes nothing: the next good step carries on
    obs, *_ = vec.step(np.full((N, 5), 1e300))  # finite, if beyond float32: clipped by the racket
    assert np.isfinite(obs).all()


def test_cleanrl_style_example_trains_a_few_updates(example, capsys, tmp_path):
    out = example("ppo_gymnasium").main(["--plot", str(tmp_path / "curve.png"), "--task", TASK, "--override", "shots.bank=64", "--override", "shots.aim=false",
                        "--num-envs", str(N), "--num-steps", "64", "--total-timesteps", str(2 * N * 64),
                        "--num-minibatches", "2", "--update-epochs", "1", "--eval-every", "0", "--eval-rounds", "1"])
    assert out["iterations"] == 2 and np.isfinite(out["loss"])
    assert out["episodes"] >= 1 and all(np.isfinite(out["returns"]))
    # the mean action evaluated on held-out episodes after training, beside the scripted stroke's
    assert 0.0 <= out["scripted_legal"] <= 1.0 and [s for s, _ in out["held_out_legal"]] == [2 * N * 64]
    text = capsys.readouterr().out
    assert "iteration 2/2" in text and "held-out legal (mean action)" in text and "nan" not in text
    assert (tmp_path / "curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


ASYNC = """
import sys
import gymnasium
import ttsim_jax
env = gymnasium.make_vec("ttsim/ReturnBall-v0", num_envs=2, vectorization_mode="async", task="return_ball_accel",
                         overrides={"shots.bank": 16, "shots.aim": False})
assert env.single_observation_space.shape == (25,)
if sys.argv[1] == "step":
    obs, _ = env.reset(seed=0)
    for _ in range(3):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert obs.shape == (2, 25) and reward.shape == (2,) and info["outcome"].shape == (2,)
env.close()
print("done")
"""


def _async(what: str, timeout: float):
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", ASYNC, what], capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0 and "done" in out.stdout, out.stdout[-2000:] + out.stderr[-3000:]
    # the workers are forked (the default start method) after this process made an environment for
    # the spaces: JAX warns when it forks with its backend's threads running, which the workers
    # would deadlock on
    assert "os.fork() was called" not in out.stderr, out.stderr[-3000:]


def test_async_vector_mode_forks_its_workers_before_jax_starts():
    _async("make", timeout=120)


@pytest.mark.slow
def test_async_vector_mode_steps():
    _async("step", timeout=900)
