"""Measured shots for ReturnBall's bank: DeepMind's post-hit states read into the world frame (a
hand-worked state), every one sent towards +x by a half turn that leaves the physics alone, a
held-out split that keeps blocks of ids whole, bad rows refused by file, row and key, the task
options checked at load time and the rates of ``ttsim play`` per shot type."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.data.errors import DataError
from ttsim_jax.data.post_hit_states import BLOCK, held_out, read_post_hit_states
from ttsim_jax.env.bank import shot_bank
from ttsim_jax.env.config import load_task_config
from ttsim_jax.params import ConfigError
from ttsim_jax.rl.ppo import LEGAL, SHOT_FAULT, summarise


def state(i, pos, vel, spin):
    return dict(id=i, **{f"pos_{a}": float(v) for a, v in zip("xyz", pos)},
                **{f"vel_{a}": float(v) for a, v in zip("xyz", vel)},
                **{f"w_vel_{a}": float(v) for a, v in zip("xyz", spin)})


@pytest.fixture
def folder(tmp_path):
    # DeepMind's frame: x across the table, y along it. A serve from their +y end towards -y, and
    # two rally balls: one from the -y end (towards +y), one from the +y end.
    serves = [state(0, (0.28, 1.48, 0.41), (-0.33, -4.66, -2.28), (1.9, 5.5, 10.8))]
    rallies = [state(2704, (0.2, -1.3, 0.4), (0.5, 6.0, 1.0), (60.0, -5.0, 7.0)),
               state(2705, (0.06, 0.88, 0.52), (0.78, -5.55, 0.52), (62.8, -5.84, -7.62))]
    (tmp_path / "serves.json").write_text(json.dumps(serves))
    (tmp_path / "rallies.json").write_text(json.dumps(rallies))
    return tmp_path


def test_states_are_read_into_the_world_frame_and_sent_towards_plus_x(folder):
    s = read_post_hit_states(folder)
    assert list(s.kind) == ["serve", "rally", "rally"] and list(s.id) == [0, 2704, 2705]
    # from the -x end already: ours = (their y, -their x, z), no half turn
    np.testing.assert_allclose(s.pos[1], [-1.3, -0.2, 0.4])
    np.testing.assert_allclose(s.vel[1], [6.0, -0.5, 1.0])
    np.testing.assert_allclose(s.spin[1], [-5.0, -60.0, 7.0])
    # from the +x end: (0.88, -0.06, 0.52) moving -x, turned half a turn about z
    np.testing.assert_allclose(s.pos[2], [-0.88, 0.06, 0.52])
    np.testing.assert_allclose(s.vel[2], [5.55, 0.78, 0.52])
    np.testing.assert_allclose(s.spin[2], [5.84, 62.8, -7.62])  # 63 rad/s of topspin along +x
    assert list(s.mirrored) == [True, False, True]
    assert (s.vel[:, 0] > 0).all()
    # proper rotations: speeds, spin rates and the angle between spin and velocity unchanged
    raw = json.loads((folder / "rallies.json").read_text())[1]
    v0 = np.array([raw["vel_x"], raw["vel_y"], raw["vel_z"]])
    w0 = np.array([raw["w_vel_x"], raw["w_vel_y"], raw["w_vel_z"]])
    assert np.dot(s.vel[2], s.spin[2]) == pytest.approx(np.dot(v0, w0))
    np.testing.assert_allclose(np.cross(s.spin[2], s.vel[2])[2], np.cross(w0, v0)[2])  # Magnus lift alike


def test_the_held_out_split_is_a_fifth_in_whole_blocks_and_fixed():
    ids = np.arange(20_000)
    test = held_out(ids)
    assert 0.18 < test.mean() < 0.22
    blocks = test.reshape(-1, BLOCK)
    assert (blocks.all(1) | ~blocks.any(1)).all()  # a block lies on one side whole
    np.testing.assert_array_equal(held_out(ids[::-1]), test[::-1])
    half = held_out(ids, 0.5)
    assert 0.45 < half.mean() < 0.55 and (half | ~test).all()  # a larger share holds the smaller one


@pytest.mark.parametrize("edit, match", [
    (lambda r: r.pop("vel_y"), r"row 1, column 'vel_y'.*missing key"),
    (lambda r: r.update(w_vel_z="fast"), r"row 1, column 'w_vel_z', value 'fast'.*finite number"),
    (lambda r: r.update(vel_x=4000.0), r"row 1, column 'vel_x'.*above 40 m/s"),
])
def test_a_bad_row_is_refused_naming_file_row_and_key(folder, edit, match):
    rows = json.loads((folder / "rallies.json").read_text())
    edit(rows[1])
    (folder / "rallies.json").write_text(json.dumps(rows))
    with pytest.raises(DataError, match=r"rallies\.json.*" + match):
        read_post_hit_states(folder)
    (folder / "serves.json").unlink()
    with pytest.raises(DataError, match="no serves.json here"):
        read_post_hit_states(folder)


def test_task_options_are_checked_at_load_time(folder, tmp_path):
    # a task file of its own: the measured types by default, the folder beside the file
    (tmp_path / "real.toml").write_text('[shots]\nsource = "measured"\nmeasured = "."\n')
    c = load_task_config(tmp_path / "real.toml")
    assert c.shots.types == ("serve", "rally") and c.shots.measured == str(folder)
    # the bundled task names the sampler's types: switched to measured shots, they are refused
    with pytest.raises(ConfigError, match=r"types = \['serve', 'topspin_drive'.*known for source = 'measured'"):
        load_task_config("return_ball", {"shots.source": "measured", "shots.measured": str(folder)})
    for overrides, match in (({"shots.source": "measured", "shots.types": ["rally"]}, "needs measured"),
                             ({"shots.source": "measured", "shots.measured": str(tmp_path / "nope")}, "no such folder"),
                             ({"shots.source": "measured", "shots.measured": str(folder), "shots.types": ["push"]},
                              r"types = \['push'\].*known for source = 'measured': \['serve', 'rally'\]"),
                             ({"shots.source": "film"}, "source = 'film'"),
                             ({"shots.split": "dev"}, "split = 'dev'")):
        with pytest.raises(ConfigError, match=match):
            load_task_config("return_ball", overrides)


def test_the_measured_bank_holds_its_split_in_a_seeded_order(folder):
    model = load_model("conti2026")
    over = {"shots.source": "measured", "shots.measured": str(folder), "shots.bank": 8, "shots.split": "all",
            "shots.types": ["serve", "rally"]}
    bank, types = shot_bank(model, load_task_config("return_ball", over))
    assert bank.pos.shape == (8, 3) and bank.pos.dtype == np.float32
    assert set(types.tolist()) == {0, 1}  # indexes into ("serve", "rally")
    # every bank row is one of the three states, with its own type
    s = read_post_hit_states(folder)
    for p, t in zip(bank.pos, types):
        k = int(np.argmin(np.linalg.norm(s.pos - p, axis=1)))
        assert np.allclose(s.pos[k], p, atol=1e-6) and ("serve", "rally")[t] == s.kind[k]
    again, _ = shot_bank(model, load_task_config("return_ball", over))
    np.testing.assert_array_equal(again.pos, bank.pos)
    other, _ = shot_bank(model, load_task_config("return_ball", {**over, "shots.seed": 5}))
    assert not np.array_equal(other.pos, bank.pos)
    # a speed limit that leaves nothing is refused, naming it
    with pytest.raises(ConfigError, match="max_speed = 1.0"):
        shot_bank(model, load_task_config("return_ball", {**over, "shots.max_speed": 1.0}))


def test_play_summary_gives_the_rate_per_shot_type():
    outcome = np.array([LEGAL, LEGAL, 0, SHOT_FAULT, LEGAL, 0])
    result = dict(outcome=outcome, shot_type=np.array([0, 0, 0, 0, 1, 1]), landing_error=np.where(outcome == LEGAL, 0.1, -1.0),
                  **{"return": np.zeros(6)})
    s = summarise(result, ("serve", "rally"))
    assert s["by_type"]["serve"] == {"episodes": 3, "legal_rate": pytest.approx(2 / 3), "opponent_missed": 0.25}
    assert s["by_type"]["rally"] == {"episodes": 2, "legal_rate": 0.5, "opponent_missed": 0.0}
    assert s["legal_rate"] == pytest.approx(3 / 5)


@pytest.mark.realdata
def test_deepmind_states_read_whole_with_a_fifth_held_out(real_data):
    folder = real_data / "deepmind_states"
    if not folder.is_dir():
        pytest.skip(f"DeepMind's post-hit states are not in {folder} (set TTSIM_REAL_DATA)")
    s = read_post_hit_states(folder)
    serve, rally = s.kind == "serve", s.kind == "rally"
    assert serve.sum() == 2704 and rally.sum() == 13088  # SOURCES.md
    assert np.median(np.linalg.norm(s.vel[rally], axis=1)) == pytest.approx(5.5, abs=0.1)
    assert (s.vel[:, 0] > 0).all()
    assert np.median(s.pos[serve, 0]) < -1.2  # served from behind the -x end
    for k in (serve, rally):
        assert 0.17 < s.test[k].mean() < 0.23
    model = load_model("conti2026")
    bank, types = shot_bank(model, load_task_config("return_ball", {
        "shots.source": "measured", "shots.measured": str(folder), "shots.split": "test", "shots.types": ["serve", "rally"]}))
    test_pos = s.pos[s.test].astype(np.float32)
    assert bank.pos.shape == (4096, 3) and 0.1 < types.mean() < 0.95
    assert all(np.isclose(test_pos, p, atol=1e-6).all(1).any() for p in bank.pos[:64])  # drawn from the held-out
