"""The reality generator: determinism, validity of what it writes, the effects it applies to the
record (each one alone changes the record, never the truth), its configuration and command, and
the bundled sample dataset."""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Racket, load_model
from ttsim_jax import effects as fx
from ttsim_jax.cli import main as generate_main
from ttsim_jax.data import load, problems, validate
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics.rotations import matrix_to_quat
from ttsim_jax.reality import (
    GeneratorError,
    generate,
    invert_contact,
    load_truth,
    make_config,
    rerecord,
    sample_contact_points,
    write,
)

SAMPLE = Path(__file__).resolve().parents[2] / "ttsim_jax" / "data" / "sample"
SIM = ",".join(fx.names("simulator"))
TINY = dict(games=2, rallies_per_game=(1, 1), lanes=2)


def tiny(effects, seed=0):
    return generate(make_config(effects=effects, seed=seed, **TINY), progress=False)


@pytest.fixture(scope="module")
def runs():
    """Generated once per module: every run shares one set of compiled kernels (same in-simulator
    effects); the record effects, one at a time, are the "all" games recorded again."""
    out = {"all": tiny("all"), "all_again": tiny("all"), "seed1": tiny("all", seed=1), "sim": tiny(SIM)}
    for name in fx.names("record"):
        out[name] = rerecord(out["all"], SIM + "," + name)
    return out


def tables_equal(a, b) -> bool:
    for name, ta in a.tables().items():
        tb = b.table(name)
        if set(ta) != set(tb):
            return False
        for col in ta:
            if len(ta[col]) != len(tb[col]) or not np.array_equal(ta[col], tb[col]):
                return False
    return True


def truth_equal(a, b) -> bool:
    for ta, tb in ((a.truth_events, b.truth_events), (a.truth_rackets, b.truth_rackets)):
        for col in ta:
            x, y = np.asarray(ta[col]), np.asarray(tb[col])
            if x.shape != y.shape or not np.array_equal(x, y, equal_nan=x.dtype != object):
                return False
    return True


# ------------------------------------------------------------------------ determinism, validity
def test_same_seed_same_dataset_other_seed_other_dataset(runs):
    a, b, c = runs["all"], runs["all_again"], runs["seed1"]
    assert tables_equal(a.dataset, b.dataset) and truth_equal(a, b)
    assert a.truth["sessions"] == b.truth["sessions"] and a.truth["effects"] == b.truth["effects"]
    assert not tables_equal(a.dataset, c.dataset)
    assert a.truth["effects"]["spin_decay"]["params"] != c.truth["effects"]["spin_decay"]["params"]


def test_generated_data_passes_validation_and_round_trips(runs, tmp_path):
    gen = runs["all"]
    ds = gen.dataset
    validate(ds)
    assert problems(ds) == []
    c = gen.truth["counts"]
    kinds = set(ds.events["kind"])
    assert {"table", "racket", "other", "out"} <= kinds
    assert c["robot_racket_contacts"] == len(ds.rackets["event_id"]) > 0
    # every robot contact has a racket state; the opponent's contacts are 'other' events
    racket_ids = ds.events["event_id"][ds.events["kind"] == "racket"]
    assert set(ds.rackets["event_id"]) == set(racket_ids)
    te = gen.truth_events
    assert set(te["player"][ds.events["kind"] == "racket"]) == {"robot"}
    assert set(te["player"][(ds.events["kind"] == "other") & (te["true_kind"] != "toss")]) <= {"opponent"}
    # 200 Hz: observations on a 5 ms clock (the tracker's: skewed by the clock_rate effect), racket contacts
    # between frames
    clock = gen.truth["effects"]["clock_rate"]["params"]
    t = (ds.observations["t"] - clock["latency"]) / (1.0 + clock["rate"])
    same = ds.observations["session_id"][1:] == ds.observations["session_id"][:-1]
    steps = np.round(np.diff(t)[same] / 0.005, 6)
    assert np.all(steps == np.round(steps)) and np.median(steps) == 1
    # spin with confidences for segments; truth of every racket contact (both players)
    assert np.all((ds.segments["spin_conf"] >= 0) & (ds.segments["spin_conf"] <= 1))
    assert len(gen.truth_rackets["event_id"]) == c["robot_racket_contacts"] + c["opponent_racket_contacts"]
    out = write(gen, tmp_path / "gen")
    back = load(out)
    assert tables_equal(back, ds)
    truth = load_truth(out)
    assert truth.info["counts"] == gen.truth["counts"]
    assert len(truth.observations["t"]) == len(ds.observations["t"])
    assert truth.effect_params("racket_logo") == gen.truth["effects"]["racket_logo"]["params"]
    assert truth.effect_params("air_flow", 1) == gen.truth["sessions"][1]["effects"]["air_flow"]
    with pytest.raises(FileExistsError):
        write(gen, out)


def test_recording_again_equals_generating_with_those_effects(runs):
    """rerecord skips the simulation and gives what generate gives with the same effects."""
    direct, again = runs["sim"], rerecord(runs["all"], SIM)
    assert tables_equal(direct.dataset, again.dataset) and truth_equal(direct, again)
    for col in direct.truth_observations:
        np.testing.assert_array_equal(direct.truth_observations[col], again.truth_observations[col])
    assert direct.truth["effects"] == again.truth["effects"] and direct.truth["counts"] == again.truth["counts"]
    assert not tables_equal(runs["all"].dataset, again.dataset)  # the source is left as it was
    with pytest.raises(GeneratorError, match="only record effects may change"):
        rerecord(runs["all"], "position_noise")


# ------------------------------------------------------------------------ record effects, one each
def _truth_same_as_without_record_effects(runs, name):
    base, gen = runs["sim"], runs[name]
    assert truth_equal(base, gen), f"{name} changed the truth"
    return base, gen


def test_racket_state_error_changes_recorded_rackets_not_truth(runs):
    base, gen = _truth_same_as_without_record_effects(runs, "racket_state_error")
    for col in ("session_id", "t", "x", "y", "z"):
        np.testing.assert_array_equal(base.dataset.observations[col], gen.dataset.observations[col])
    rb, rg = base.dataset.rackets, gen.dataset.rackets
    for col in ("x", "vx", "qw", "d_z"):
        assert not np.allclose(rb[col], rg[col])
    dpos = np.hypot(np.hypot(rb["x"] - rg["x"], rb["y"] - rg["y"]), rb["z"] - rg["z"])
    assert 0.001 < np.median(dpos) < 0.05  # about a centimetre
    # without the effect the record is the truth
    tr = base.truth_rackets
    robot = tr["player"] == "robot"
    np.testing.assert_allclose(rb["x"], tr["x"][robot])
    np.testing.assert_allclose(rb["d_z"], tr["d_z"][robot], atol=1e-6)  # float32 simulation


def test_position_noise_changes_observations_not_truth(runs):
    base, gen = _truth_same_as_without_record_effects(runs, "position_noise")
    ob, og = base.dataset.observations, gen.dataset.observations
    np.testing.assert_array_equal(ob["t"], og["t"])
    err = og["x"] - ob["x"]
    assert 2e-4 < np.std(err) < 5e-3
    np.testing.assert_array_equal(base.truth_observations["x"], gen.truth_observations["x"])
    np.testing.assert_allclose(ob["x"], base.truth_observations["x"])


def test_spin_noise_changes_spin_estimates_not_truth(runs):
    base, gen = _truth_same_as_without_record_effects(runs, "spin_noise")
    sb, sg = base.dataset.segments, gen.dataset.segments
    np.testing.assert_array_equal(sb["segment_id"], sg["segment_id"])
    assert np.all(sb["spin_conf"] == 1.0) and np.any(sg["spin_conf"] < 0.5)
    assert not np.allclose(sb["spin_y"], sg["spin_y"])
    np.testing.assert_array_equal(base.dataset.observations["x"], gen.dataset.observations["x"])


def test_spin_calibration_miscalibrates_the_recorded_spin_not_truth(runs):
    base, gen = _truth_same_as_without_record_effects(runs, "spin_calibration")
    p = gen.truth["effects"]["spin_calibration"]["params"]
    sb, sg = base.dataset.segments, gen.dataset.segments
    w = lambda seg: np.stack([np.asarray(seg[f"spin_{a}"]) for a in "xyz"], 1)  # noqa: E731
    expect = (1.0 + p["scale"]) * w(sb) @ fx.rotation_matrix(np.asarray(p["rotation"])).T
    np.testing.assert_allclose(w(sg), expect, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(sb["spin_conf"], sg["spin_conf"])  # nothing in the record tells
    np.testing.assert_array_equal(base.dataset.observations["x"], gen.dataset.observations["x"])


def test_spin_unmeasured_records_no_spin_not_truth(runs):
    base, gen = _truth_same_as_without_record_effects(runs, "spin_unmeasured")
    sg, og = gen.dataset.segments, gen.dataset.observations
    assert not np.any(sg["spin_conf"]) and not np.any(og["spin_conf"])
    assert not any(np.any(sg[f"spin_{a}"]) or np.any(og[f"spin_{a}"]) for a in "xyz")
    np.testing.assert_array_equal(base.dataset.observations["x"], gen.dataset.observations["x"])
    assert np.any(base.dataset.segments["spin_y"])


def test_clock_rate_skews_every_recorded_time_not_truth(runs):
    base, gen = _truth_same_as_without_record_effects(runs, "clock_rate")
    p = gen.truth["effects"]["clock_rate"]["params"]
    assert p["rate"] != 0.0 and p["latency"] != 0.0

    def skewed(t):
        return np.asarray(t) * (1.0 + p["rate"]) + p["latency"]

    db, dg = base.dataset, gen.dataset
    np.testing.assert_allclose(dg.observations["t"], skewed(db.observations["t"]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(dg.events["t"], skewed(db.events["t"]), rtol=0, atol=1e-12)
    for col in ("t_start", "t_end"):  # the segments follow the recorded times
        np.testing.assert_allclose(dg.segments[col], skewed(db.segments[col]), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(db.observations["x"], dg.observations["x"])
    np.testing.assert_array_equal(db.rackets["vx"], dg.rackets["vx"])
    # the truth keeps the true clock
    np.testing.assert_array_equal(gen.truth_observations["t"], db.observations["t"])
    np.testing.assert_array_equal(gen.truth_events["t"], db.events["t"])


def test_camera_scale_scales_recorded_positions_about_the_table_centre_not_truth(runs):
    base, gen = _truth_same_as_without_record_effects(runs, "camera_scale")
    k = 1.0 + gen.truth["effects"]["camera_scale"]["params"]["scale"]
    assert k != 1.0
    db, dg = base.dataset, gen.dataset
    for col in ("x", "y", "z"):
        np.testing.assert_allclose(dg.observations[col], k * db.observations[col], rtol=1e-12, atol=0)
        np.testing.assert_allclose(dg.events[col], k * db.events[col], rtol=1e-12, atol=0)
        np.testing.assert_array_equal(gen.truth_observations[col], base.truth_observations[col])
    np.testing.assert_array_equal(db.observations["t"], dg.observations["t"])
    np.testing.assert_array_equal(db.rackets["x"], dg.rackets["x"])  # the robot's racket is not triangulated


def test_missing_frames_drops_observations_not_truth(runs):
    base, gen = _truth_same_as_without_record_effects(runs, "missing_frames")
    nb, ng = len(base.dataset.observations["t"]), len(gen.dataset.observations["t"])
    assert 0.8 * nb < ng < nb
    assert set(gen.dataset.observations["t"]) <= set(base.dataset.observations["t"])


# ------------------------------------------------------------------------ pieces
def test_racket_inversion_is_exact_for_the_plain_model():
    m = load_model("conti2026")
    rng = np.random.default_rng(0)
    n = 64
    pos = np.array([1.8, 0.1, 0.3]) + rng.uniform(-0.3, 0.3, (n, 3))
    v_in = np.stack([rng.uniform(3, 20, n), rng.normal(0, 1, n), rng.normal(0, 3, n)], -1)
    w_in = rng.normal(0, 300, (n, 3))
    v_out = np.stack([-rng.uniform(3, 30, n), rng.normal(0, 2, n), rng.normal(1, 3, n)], -1)
    w_out = rng.normal(0, 400, (n, 3))
    d = sample_contact_points(rng, n, (0.08, 0.09), (0.6, 0.28, 0.12))
    roll, ang = rng.uniform(-1.7, 1.7, n), rng.normal(0, 4, (n, 3))
    inv = jax.jit(jax.vmap(invert_contact, in_axes=(None, None, None, 0, 0, 0, 0, 0, 0, 0, 0)))
    rk = inv(m.racket, m.ball.radius, m.ball.mass, *map(jnp.asarray, (pos, v_in, w_in, v_out, w_out, d, roll, ang)))

    def forward(p, r, v, w, bp, bv, bw):
        racket = Racket(pos=p, rot=r, vel=v, ang_vel=w, face=jnp.array([0.08, 0.09]))
        vv, ww, st = racket_stage.racket_contact(m.racket, racket, m.ball.radius, m.ball.mass, bp, bv, bw)
        return vv, st["d"], st["v"][0]

    v, dd, vn = jax.jit(jax.vmap(forward))(rk["pos"], rk["rot"], rk["vel"], rk["ang_vel"], *map(jnp.asarray, (pos, v_in, w_in)))
    np.testing.assert_allclose(np.asarray(v), v_out, atol=1e-9)
    np.testing.assert_allclose(np.asarray(dd), d, atol=1e-12)
    assert np.all(np.asarray(vn) < 0)  # the ball arrives at the front face
    rot = np.asarray(rk["rot"])
    np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), np.broadcast_to(np.eye(3), (n, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)


def test_contact_points_cover_every_band_inside_the_face():
    d = sample_contact_points(np.random.default_rng(1), 3000, (0.08, 0.09), (0.6, 0.28, 0.12))
    r = np.linalg.norm(d, axis=-1)
    frac = [np.mean(r < 0.05), np.mean((r >= 0.05) & (r < 0.08)), np.mean(r >= 0.08)]
    np.testing.assert_allclose(frac, [0.6, 0.28, 0.12], atol=0.03)
    assert np.all((d[:, 0] / 0.08) ** 2 + (d[:, 1] / 0.09) ** 2 <= 1.0)
    assert np.mean(fx.make("racket_logo").weight(jnp.asarray(d.T)) > 0.5) > 0.02  # the logo gets hits


def test_quaternions_are_unit_and_match_the_matrices():
    rot = np.asarray(fx.rotation_matrix(np.random.default_rng(2).normal(size=(50, 3)) * 2.0))
    q = matrix_to_quat(rot)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    w, x, y, z = q.T
    back = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)
    np.testing.assert_allclose(back, rot, atol=1e-12)


def test_config_file_and_its_errors(tmp_path):
    f = tmp_path / "gen.toml"
    f.write_text('[generator]\ngames = 3\nrallies_per_game = [2, 4]\n\n[effects]\nenabled = ["air_flow", "racket_logo"]\n\n'
                 '[effects.air_flow]\nwind = [0.3, 0.0, 0.0]\n')
    cfg = make_config("paper", f, seed=5)
    assert (cfg.games, cfg.rallies_per_game, cfg.seed) == (3, (2, 4), 5)
    assert cfg.effects == ("air_flow", "racket_logo") and cfg.effect_params["air_flow"]["wind"] == [0.3, 0.0, 0.0]
    f.write_text("[generator]\ngamez = 3\n")
    with pytest.raises(GeneratorError, match=r"gen.toml: key 'generator.gamez' = 3: unknown setting"):
        make_config(config_file=f)
    f.write_text("[effects.air_flow]\nspeed = 2.0\n")
    with pytest.raises(GeneratorError, match=r"gen.toml: \[effects.air_flow\]: unknown parameter 'speed' = 2.0"):
        make_config(config_file=f)
    with pytest.raises(GeneratorError, match="key 'games' = 0"):
        make_config(games=0)
    with pytest.raises(GeneratorError, match="unknown effect 'wind'"):
        make_config(effects="wind")


def test_generate_command_writes_a_dataset_and_prints_the_truth(tmp_path, capsys):
    cfg = tmp_path / "one.toml"
    cfg.write_text("[generator]\nrallies_per_game = [1, 1]\nlanes = 2\n")  # TINY: the fixture's compiled shapes
    out = tmp_path / "ds"
    assert generate_main(["generate", "--out", str(out), "--games", "2", "--config", str(cfg), "--effects", SIM
                          + ",position_noise", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "table contacts:" in text and "racket_logo (dataset): grip_loss=" in text and "air_flow (session)" in text
    validate(load(out))
    assert (out / "truth.json").is_file() and (out / "truth_rackets.parquet").is_file()
    assert generate_main(["generate", "--out", str(out), "--games", "1", "--quiet"]) == 2  # exists: needs --force
    assert generate_main(["generate", "--out", str(tmp_path / "x"), "--effects", "windy", "--quiet"]) == 2
    assert "unknown effect 'windy'" in capsys.readouterr().err


# ------------------------------------------------------------------------ the bundled sample
def test_sample_dataset_loads_validates_and_is_documented():
    readme = (SAMPLE / "README.md").read_text()
    dirs = [p for p in SAMPLE.iterdir() if (p / "metadata.json").is_file()]
    assert len(dirs) == 1
    path = dirs[0]
    assert f"--out ttsim_jax/data/sample/{path.name}" in readme and "--seed 0" in readme
    ds = load(path)
    assert problems(ds) == []
    truth = load_truth(path)
    assert truth.info["counts"]["robot_racket_contacts"] == len(ds.rackets["event_id"]) > 20
    assert truth.info["counts"]["table_contacts"] == int(np.sum(ds.events["kind"] == "table"))
    # made with the effects the catalogue had then, named in the README's command
    assert set(truth.info["effects"]) <= set(fx.names())
    assert f"--effects {','.join(truth.info['effects'])}" in readme
    size = sum(f.stat().st_size for f in path.iterdir())
    assert size < 5e6
    assert json.loads((path / "metadata.json").read_text())["frame"] == "ttsim-table-centre-v1"


@pytest.mark.slow
def test_no_generated_segment_is_a_ball_frozen_at_the_net():
    """A ball whose chunk of simulation began as it passed through the net's top was refused by the
    kernel's start check (its centre within the net's band) and stayed frozen there, observed as a
    flight segment until the flight's time limit (seed 0 of 14 selfcheck-size games: one segment of
    2,017, RMSE 1.24 m under the true model); the tracker now loses it there. Every generated
    segment is a free flight (validation's acceleration check)."""
    from ttsim_jax import effects as fx
    from ttsim_jax.data.speeds import non_flights

    air = {k: np.broadcast_to(p.neutral, p.shape).tolist() for k, p in fx.effect_class("air_flow").PARAMS.items()}
    air["wind"] = [0.0, 0.1, 0.0]
    cfg = make_config(games=14, seed=0, effects=["air_flow", "position_noise"], max_flight_time=1.5,
                      effect_params={"air_flow": air, "position_noise": {"std": [0.0015, 0.0015, 0.001]}},
                      truth_observations=False)
    ds = generate(cfg, progress=False).dataset
    assert len(ds.segments["segment_id"]) > 2000
    assert non_flights(ds).tolist() == []
