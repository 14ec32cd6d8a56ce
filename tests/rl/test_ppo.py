"""PPO: GAE against its recursion written out, running statistics against numpy, and a short
training run (16 environments) that improves on its initial random policy, checkpoints atomically
and resumes exactly; the CLI's ``train ppo`` on the same settings (one compiled chunk shape)."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ttsim_jax.rl
from ttsim_jax.cli import main
from ttsim_jax.params import ConfigError
from ttsim_jax.rl.checkpoint import CheckpointError, read_checkpoint, restore_runner
from ttsim_jax.rl.config import load_ppo_config, parse_ppo_config
from ttsim_jax.rl.normalise import RunningStats
from ttsim_jax.rl.ppo import _program_key, gae, optimizer
from ttsim_jax.rl.training import CHECKPOINT, CURVE, METRICS, train

# the motion penalty dominates this task's reward: a quick, sure signal for a short run
TASK = """
model = "conti2026"
[shots]
bank = 64
aim = false
[reward]
motion = 1.0
approach = 0.0
[randomisation]
"table.e0" = [0.94, 0.99]
"""

PPO = """
task = "task.toml"
[network]
hidden = [32, 32]
[ppo]
num_envs = 16
num_steps = 16
update_epochs = 2
num_minibatches = 2
learning_rate = 3e-3
[train]
total_env_steps = 10240
time_limit_s = 600.0
updates_per_chunk = 10
eval_every_chunks = 0
eval_envs = 0
checkpoint_every_chunks = 1
"""


def test_gae_matches_its_recursion():
    rng = np.random.default_rng(0)
    t, n, gamma, lam = 7, 3, 0.9, 0.8
    values, rewards = rng.normal(size=(t, n)), rng.normal(size=(t, n))
    dones = rng.random((t, n)) < 0.3
    last = rng.normal(size=n)
    adv, ret = gae(jnp.asarray(values), jnp.asarray(rewards), jnp.asarray(dones), jnp.asarray(last), gamma, lam)
    expect = np.zeros((t, n))
    running, nxt = np.zeros(n), last
    for k in reversed(range(t)):
        live = 1.0 - dones[k]
        delta = rewards[k] + gamma * nxt * live - values[k]
        running = delta + gamma * lam * live * running
        expect[k], nxt = running, values[k]
    np.testing.assert_allclose(np.asarray(adv), expect, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(ret), expect + values, rtol=1e-6)


def test_running_stats_match_numpy():
    rng = np.random.default_rng(1)
    batches = [rng.normal(3.0, 2.0, size=(50, 4)), rng.normal(-1.0, 0.5, size=(30, 4))]
    stats = RunningStats.create(4)
    for b in batches:
        stats = stats.update(jnp.asarray(b, jnp.float32))
    both = np.concatenate(batches)
    np.testing.assert_allclose(np.asarray(stats.mean), both.mean(0), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(stats.var), both.var(0), rtol=1e-3)


def test_bad_ppo_config_is_refused():
    with pytest.raises(ConfigError, match="num_minibatches"):
        parse_ppo_config("[ppo]\nnum_envs = 10\nnum_steps = 1\nnum_minibatches = 3\n", "x.toml")
    with pytest.raises(ConfigError, match="x.toml.*learning_rate"):
        parse_ppo_config("[ppo]\nlearning_rate = -1.0\n", "x.toml")


@pytest.mark.parametrize("anneal", [False, True])
def test_learning_rate_falls_linearly_to_zero_over_the_run_when_annealed(anneal):
    config = parse_ppo_config(f"[ppo]\nnum_envs = 4\nnum_steps = 4\nnum_minibatches = 2\nupdate_epochs = 2\n"
                              f"learning_rate = 0.01\nanneal_lr = {str(anneal).lower()}\n"
                              "[train]\ntotal_env_steps = 40\n", "x.toml")
    # the optimiser as the compiled update builds it, from the config without its run limits
    opt = optimizer(_program_key(config))
    params = jnp.zeros(())
    state = opt.init(params)
    steps = []
    for _ in range(10):
        # a constant gradient makes Adam's normalised step exactly one: the update is the step size
        update, state = opt.update(jnp.asarray(0.1), state, params)
        steps.append(-float(update))
    # 40 steps / 16 per update = 2 updates of 2 epochs x 2 minibatches: 8 optimiser steps
    expect = 0.01 * np.clip(1.0 - np.arange(10) / 8, 0.0, None) if anneal else np.full(10, 0.01)
    np.testing.assert_allclose(steps, expect, rtol=1e-4, atol=1e-9)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("ppo")
    (root / "task.toml").write_text(TASK)
    (root / "ppo.toml").write_text(PPO)
    return root


@pytest.fixture(scope="module")
def runs(files):
    config = load_ppo_config(files / "ppo.toml")
    # the public entry point, given the file as `ttsim train ppo --config` is
    straight = ttsim_jax.rl.train(files / "ppo.toml", files / "straight", progress=None)
    half = dataclasses.replace(config, train=dataclasses.replace(config.train, total_env_steps=5120))
    train(half, files / "resumed", progress=None)
    first = read_checkpoint(files / "resumed" / CHECKPOINT)
    resumed = train(config, files / "resumed", resume=True, progress=None)
    return config, straight, first, resumed


@pytest.mark.slow
def test_short_run_improves_on_the_random_policy(files, runs):
    history = json.loads((files / "straight" / METRICS).read_text())
    assert len(history) == 4
    # the first chunk's policy is the initial, random one (a Gaussian of std 0.6 around zero);
    # 40 updates cut its motion penalty by about a tenth
    first, last = history[0]["reward_mean"], history[-1]["reward_mean"]
    assert last > first + 0.05 * abs(first)
    assert (files / "straight" / CURVE).stat().st_size > 1000


@pytest.mark.slow
def test_resume_continues_exactly(files, runs):
    config, straight, first, resumed = runs
    assert len(first["history"]) == 2
    a = read_checkpoint(files / "straight" / CHECKPOINT)
    b = read_checkpoint(files / "resumed" / CHECKPOINT)
    assert [h["env_steps"] for h in b["history"]] == [h["env_steps"] for h in a["history"]]
    for x, y in zip(jax.tree.leaves(a["runner"]["params"]), jax.tree.leaves(b["runner"]["params"])):
        np.testing.assert_array_equal(x, y)
    assert int(b["runner"]["update"]) == 40


@pytest.mark.slow
def test_cli_refuses_to_overwrite_and_resumes(files, runs, capsys):
    out = files / "straight"
    assert main(["train", "ppo", "--config", str(files / "ppo.toml"), "--out", str(out)]) == 2
    assert "--resume" in capsys.readouterr().err
    # already at its total: resuming runs nothing more and reports where it stands
    assert main(["train", "ppo", "--config", str(files / "ppo.toml"), "--out", str(out), "--resume", "--quiet"]) == 0
    assert "10,240 environment steps" in capsys.readouterr().out
    (files / "bad.msgpack").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="bad.msgpack"):
        read_checkpoint(files / "bad.msgpack")
    assert main(["play", "--policy", str(files / "bad.msgpack")]) == 2
    # a policy of racket accelerations is not played on a task of the intercept mode
    assert main(["play", "--policy", str(out / CHECKPOINT), "--task", "return_ball"]) == 2
    assert "action = 'intercept'" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_plays_a_checkpoint(files, runs, capsys):
    """``ttsim play`` of the short run's checkpoint on its own task (as many episodes as it trained
    environments: the training shape is reused) prints the evaluation as JSON and draws rallies."""
    plot, gif = files / "rallies.png", files / "rally.gif"
    assert main(["play", "--policy", str(files / "straight" / CHECKPOINT), "--episodes", "16", "--json",
                 "--plot", str(plot), "--gif", str(gif)]) == 0
    text = capsys.readouterr().out
    s = json.loads(text[:text.rindex("}") + 1])
    assert 1 <= s["episodes"] <= 16 and 0.0 <= s["legal_rate"] <= 1.0
    assert sum(s["outcomes"].values()) == pytest.approx(1.0)
    assert s["task"].endswith("task.toml") and s["env_steps_trained"] == 10240
    assert plot.stat().st_size > 1000
    from PIL import Image

    with Image.open(gif) as im:
        assert im.n_frames > 1 and im.size == (640, 560)


def test_a_checkpoint_of_other_shapes_than_its_task_now_is_refused_naming_the_leaf():
    """A task whose observation grew since training: the restored arrays are checked against the
    fresh runner's shapes, not handed to the network."""
    template = {"params": {"dense": {"kernel": jax.ShapeDtypeStruct((33, 64), jnp.float32)}}}
    payload = {"runner": {"params": {"dense": {"kernel": np.zeros((25, 64), np.float32)}}}}
    with pytest.raises(CheckpointError, match=r"old.msgpack: \['params'\]\['dense'\]\['kernel'\] has shape "
                                              r"\(25, 64\) in the checkpoint, \(33, 64\) for its task"):
        restore_runner(template, payload, "old.msgpack")
    same = {"runner": {"params": {"dense": {"kernel": np.ones((33, 64), np.float32)}}}}
    assert restore_runner(template, same, "new.msgpack")["params"]["dense"]["kernel"].shape == (33, 64)


def test_a_checkpoint_from_before_the_plan_in_the_state_restores_with_zeros_there():
    """Checkpoints written before the environment state carried the tracker's plan (derived state)
    or the episode's target still restore: zeros for the plan, which a resumed run recomputes and
    ``ttsim play`` does not read; the fresh state's target (the task's fixed one)."""
    from flax import serialization

    from ttsim_jax.env.config import load_task_config
    from ttsim_jax.env.return_ball import ReturnBall

    env = ReturnBall(load_task_config("return_ball", {"shots.bank": 8, "shots.aim": False}), 4)
    params = env.default_params()
    state = jax.eval_shape(lambda k: env.reset(k, params)[1], jax.random.PRNGKey(0))
    assert state.plan.shape == (4, 8)
    template = {"env_state": state}
    old = jax.tree.map(lambda s: np.ones(s.shape, s.dtype), serialization.to_state_dict(template))
    del old["env_state"]["plan"], old["env_state"]["target"]
    restored = restore_runner(template, {"runner": old}, "old.msgpack")
    np.testing.assert_array_equal(restored["env_state"].plan, np.zeros((4, 8), np.float32))
    np.testing.assert_array_equal(restored["env_state"].t, np.ones(4, np.int32))
    # nor the episode's target (every task had a fixed one then): a resumed run's template gives it
    np.testing.assert_array_equal(restored["env_state"].target, np.zeros((4, 2), np.float32))
    concrete = {"env_state": state.replace(target=jnp.tile(params.target, (4, 1)))}
    restored = restore_runner(concrete, {"runner": old}, "old.msgpack")
    np.testing.assert_array_equal(restored["env_state"].target, np.tile(np.asarray(params.target), (4, 1)))


def test_train_is_callable_from_the_package():
    """``ttsim_jax.rl.train`` is the trainer ``ttsim train ppo`` runs, also once its module is
    imported (the module is ``training``, so the name is not shadowed)."""
    import ttsim_jax.rl.training

    assert ttsim_jax.rl.train is ttsim_jax.rl.training.train is train
    assert ttsim_jax.rl.load_ppo_config is load_ppo_config
    with pytest.raises(ValueError, match="overrides apply to a config read from a file"):
        train(load_ppo_config(), "unused", overrides={"train.seed": 1})


def test_bundled_policy_is_small_restores_for_its_task_and_names_its_config():
    """The policy ``ttsim play`` plays by default: a few hundred kB at most, its runner restores
    against a fresh one of its config (a small unaimed bank: the shapes do not depend on it), and
    its config is the shipped configs/ppo/return_ball_small.toml, so it can be trained again."""
    from ttsim_jax.env.config import load_task_config
    from ttsim_jax.env.return_ball import ReturnBall
    from ttsim_jax.params import config_dir
    from ttsim_jax.rl import ppo
    from ttsim_jax.rl.checkpoint import BUNDLED_POLICY

    assert BUNDLED_POLICY.stat().st_size < 300_000
    payload = read_checkpoint(BUNDLED_POLICY)
    config = parse_ppo_config(payload["config"], payload["config_source"])
    shipped = load_ppo_config(config_dir() / "ppo" / "return_ball_small.toml")
    assert dataclasses.replace(config, source="", text="") == dataclasses.replace(shipped, source="", text="")
    assert payload["config_source"] == "configs/ppo/return_ball_small.toml"  # no path of the machine it came from
    env = ReturnBall(load_task_config(config.task, {"shots.bank": 8, "shots.aim": False}), config.ppo.num_envs)
    params = env.default_params()
    template = jax.eval_shape(lambda k: ppo.init_runner(env, params, config, k), jax.random.PRNGKey(0))
    runner = restore_runner(template, payload, BUNDLED_POLICY)
    assert int(runner.update) * config.batch_size == payload["history"][-1]["env_steps"] > 0


@pytest.mark.slow
def test_cli_plays_the_bundled_policy_without_a_policy_option(capsys):
    """``ttsim play`` out of the box: the bundled policy on the default task returns most shots
    (the tracker's own stroke returns about 88 %; a random constant stroke adjustment far fewer)."""
    assert main(["play", "--episodes", "64", "--seed", "3", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["episodes"] >= 50 and s["legal_rate"] >= 0.7
    assert s["task"].endswith("return_ball.toml") and s["env_steps_trained"] > 1_000_000
