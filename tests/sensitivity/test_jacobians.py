"""Jacobians through the rally kernel against central finite differences (float64): reverse and
forward mode, every target, shots from a dataset; the flags on gradients that hold only locally;
the linear error budget against Monte Carlo.

Every test here shares the module's three compiled programs (every target is read from one
program): the reverse pass of ``jac_all`` (three shots), the forward outcomes at a batch of 256 rows
(finite differences, flags, Monte Carlo) and forward mode for the three shots.
"""

import json

import numpy as np
import pytest

from ttsim_jax.data.io import save
from ttsim_jax.reality import synthetic_contact_dataset
from ttsim_jax.physics.events import RACKET, TABLE
from ttsim_jax.sensitivity import budgets
from ttsim_jax.sensitivity.cases import contact_time, dataset_shots
from ttsim_jax.sensitivity.jacobians import (STATE_GROUPS, finite_differences, flatten_inputs,
                                             group_directions, horizon_plan, jacobian, layout_of, local_flags,
                                             outcomes)
from ttsim_jax.sensitivity.report import column_scales
from ttsim_jax.sensitivity.study import StudyConfig, check_locality

# the module's fixture compiles the reverse pass through the kernel (minutes on 2 cores)
pytestmark = pytest.mark.slow

BATCH = 256  # rows per compiled forward call, for every finite difference and sample here
MODEL_GROUPS = {"aero.drag", "aero.magnus", "table.restitution", "table.residual", "racket.params"}


@pytest.fixture(scope="module")
def jac_all(model, shots, cfg):
    """(shot set with the edge shot appended, its reverse-mode Jacobian of the landing point).

    The edge shot is the drive moved sideways so that it lands with its centre 2 mm inside the
    table's side edge plus a radius: it touches the edge, and a small change of the racket's
    orientation makes it miss the table. Flight does not depend on y, so moving the ball and the
    racket sideways moves the landing by the same amount.
    """
    first = outcomes(model, shots, flatten_inputs(model, shots, layout_of(model)), target="landing",
                     dt=cfg["dt"], n_steps=cfg["n_steps"], batch=BATCH)
    edge = shots.take(np.array([0, 1, 0]))
    shift = model.table.width / 2 + float(model.ball.radius) - 0.002 - first.values[0, 1]
    edge.ball.pos[2, 1] += shift
    edge.racket.pos[2, 1] += shift
    edge.label[2] = "edge"
    return edge, jacobian(model, edge, target="landing", dt=cfg["dt"], n_steps=cfg["n_steps"], mode="rev")


def _scale(jac):
    return np.maximum(np.abs(jac.nominal).mean(0), 1e-3)


def _check_against_differences(model, shots, jac, cfg, shot_index):
    """The Jacobian along a random direction of every input group agrees with central differences
    (float64) within 1 % on the given shots; returns how many (group, shot) pairs really move."""
    dirs = group_directions(jac, np.random.default_rng(0), _scale(jac))
    names = list(dirs)
    d = np.stack([dirs[g] for g in names])
    fd, same, _ = finite_differences(model, shots, jac.nominal, d, [1e-6], target=jac.target, dt=cfg["dt"],
                                     n_steps=cfg["n_steps"], batch=BATCH)
    assert same[:, :, shot_index].all()
    ad = np.einsum("bkc,dbc->dbk", jac.jac, d)
    # 1 % of the size of the terms: columns moving the target in opposite ways may nearly cancel
    size = np.einsum("bkc,dbc->dbk", np.abs(jac.jac), np.abs(d))
    moving = 0
    for i, g in enumerate(names):
        for b in shot_index:
            f, a = fd[0, i, b], ad[i, b]
            assert np.all(np.isfinite(a))
            if g in ("table.geometry", "constants") and np.max(np.abs(f)) < 1e-9:
                continue
            np.testing.assert_allclose(a, f, rtol=0, atol=1e-2 * np.max(np.maximum(size[i, b], np.abs(f))) + 1e-9,
                                       err_msg=f"{jac.target}: {g}, shot {b}")
            moving += np.max(np.abs(f)) > 1e-6
    return names, moving


def test_shots_hit_the_racket_then_land(jac_all, cfg):
    shots, jac = jac_all
    assert jac.valid.all()
    assert (jac.sequence == [RACKET, TABLE]).all()
    # the moved shot lands on the side edge (centre beyond the playing surface's side), a few cm
    # further on than the drive it was moved from (it falls below the surface before touching the edge)
    assert jac.values[cfg["edge"], 1] > 0.7625 and abs(jac.values[cfg["edge"], 0] - jac.values[0, 0]) < 0.05


def test_jacobian_matches_central_differences_for_every_input_group(model, jac_all, cfg):
    shots, jac = jac_all
    names, moving = _check_against_differences(model, shots, jac, cfg, cfg["smooth"])
    assert set(STATE_GROUPS) <= set(names) and MODEL_GROUPS <= set(names)
    # every state group and the model groups that shape the flight really move the landing point
    assert moving >= 2 * (len(STATE_GROUPS) - 1) + 6


@pytest.mark.parametrize("target", ["landing_time", "bounce_speed"])
def test_other_event_targets_match_central_differences(model, jac_all, cfg, target):
    """Landing time and the speed after the bounce come from the landing's program: the same
    compiled reverse pass, another row of weights."""
    shots, landing = jac_all
    jac = jacobian(model, shots, target=target, dt=cfg["dt"], n_steps=cfg["n_steps"], mode="rev")
    assert jac.jac.shape == (3, 1, landing.jac.shape[2]) and jac.valid.all()
    names, moving = _check_against_differences(model, shots, jac, cfg, cfg["smooth"])
    assert moving >= 2 * (len(STATE_GROUPS) - 1) + 6
    # plausible values: drag only slows the ball, so it needs longer than the distance to its landing
    # at its speed off the racket; it still moves after the bounce
    if target == "landing_time":
        contact = shots.ball.pos + contact_time(cfg["dt"]) * shots.ball.vel
        dist = np.linalg.norm(landing.values - contact[:, :2], axis=-1)
        assert np.all((jac.values[:, 0] > dist / shots.speed) & (jac.values[:, 0] < 1.5 * dist / shots.speed))
    else:
        assert np.all((jac.values[:, 0] > 1.0) & (jac.values[:, 0] < 2 * shots.speed))


def test_shorter_horizon_gives_the_full_horizons_jacobian(model, jac_all, cfg):
    """Shots run through a horizon just past their landing (horizons of 50 steps, 0.1 s) have the
    Jacobian, values and events they have through the full one (the module's shots land between
    two thirds of the horizon and the end, so ``jac_all`` ran them through all of it)."""
    shots, full = jac_all
    assert (full.horizon == cfg["n_steps"]).all()
    first = outcomes(model, shots, full.nominal, target="landing", dt=cfg["dt"], n_steps=cfg["n_steps"], batch=BATCH)
    (rows, horizon), = horizon_plan(first.steps, first.valid, cfg["n_steps"], len(shots), 7)
    assert sorted(rows.tolist()) == [0, 1, 2] and horizon < cfg["n_steps"]
    short = jacobian(model, shots, target="landing", dt=cfg["dt"], n_steps=cfg["n_steps"], buckets=7)
    assert (short.horizon == horizon).all()
    np.testing.assert_array_equal(short.valid, full.valid)
    np.testing.assert_array_equal(short.sequence, full.sequence)
    np.testing.assert_allclose(short.values, full.values, rtol=0, atol=1e-12)
    np.testing.assert_allclose(short.jac, full.jac, rtol=1e-9, atol=1e-12 * np.abs(full.jac).max())
    assert np.abs(full.jac).max() > 0.1


def test_forward_mode_agrees_with_reverse_mode(model, jac_all, cfg):
    shots, rev = jac_all
    fwd = jacobian(model, shots, target="landing", dt=cfg["dt"], n_steps=cfg["n_steps"], mode="fwd")
    np.testing.assert_array_equal(fwd.valid, rev.valid)
    np.testing.assert_array_equal(fwd.sequence, rev.sequence)
    np.testing.assert_allclose(fwd.values, rev.values, rtol=0, atol=1e-12)
    # two exact derivatives of one float64 program: equal to rounding, on every column of every shot
    scale = np.abs(rev.jac).max((0, 1))
    np.testing.assert_allclose(fwd.jac, rev.jac, rtol=1e-7, atol=1e-9 * scale.max())
    assert np.abs(rev.jac).max() > 0.1


def test_net_clearance_in_forward_mode_matches_central_differences(model, jac_all, cfg):
    """The net clearance from the same program as the landing, in forward mode (the compilation of
    the forward-mode test)."""
    shots, _ = jac_all
    jac = jacobian(model, shots, target="net_clearance", dt=cfg["dt"], n_steps=cfg["n_steps"], mode="fwd")
    assert jac.valid.all()
    # the drives (edge shot included: flight does not depend on y) pass the net some 10-40 cm
    # above it, the push lower
    assert np.all((jac.values[:, 0] > 0.0) & (jac.values[:, 0] < 0.5))
    assert jac.values[0, 0] == pytest.approx(jac.values[cfg["edge"], 0], abs=1e-9)
    _, moving = _check_against_differences(model, shots, jac, cfg, range(3))
    # the table's restitution and residual do not act before the net, nor does the racket's spin
    assert moving >= 3 * (len(STATE_GROUPS) - 1) + 3 * 3


def test_racket_orientation_column_is_a_rotation(jac_all, cfg):
    """d landing / d rotation vector about the face normal is a spin of the face about that normal,
    which changes neither the contact point's velocity nor the normal: its column is tiny against
    the tilt columns."""
    shots, jac = jac_all
    rot = jac.group("racket.rot")[cfg["smooth"]]  # (2, k, 3), world-frame rotation vector
    normal = shots.racket.rot[cfg["smooth"]][:, :, 0]
    about_normal = np.einsum("bkc,bc->bk", rot, normal)
    tilt = np.linalg.norm(rot, axis=-1)
    assert np.all(np.abs(about_normal) < 0.2 * tilt)


def test_edge_shot_is_flagged_smooth_shots_are_not(model, jac_all, cfg):
    shots, jac = jac_all
    scale = column_scales(jac)
    probe = {g: scale for g in ("racket.pos", "racket.rot", "racket.vel", "ball.spin")}
    flags = local_flags(model, shots, jac, probe, dt=cfg["dt"], n_steps=cfg["n_steps"], batch=BATCH)
    assert flags["flag"].tolist() == [False, False, True]
    assert flags["flip"][cfg["edge"]] and not flags["flip"][cfg["smooth"]].any()
    # the flag is what finite differences at two step sizes say, checked here on the raw differences
    dirs = group_directions(jac, np.random.default_rng(0), scale)
    fd, same, _ = finite_differences(model, shots, jac.nominal, dirs["racket.rot"][None], [1.0, 1.0 / 8.0],
                                     target="landing", dt=cfg["dt"], n_steps=cfg["n_steps"], batch=BATCH)
    gap = np.abs(fd[0, 0] - fd[1, 0]).max(-1) / np.abs(fd[1, 0]).max(-1)
    assert gap[cfg["edge"]] > 0.05 or not same[:, 0, cfg["edge"]].all()
    assert np.all(gap[cfg["smooth"]] < 0.05)


def test_study_check_flags_by_group_where_two_step_sizes_disagree(jac_all, cfg):
    """The command's check (float64, every group, parameters probed at a tenth of a typical change):
    per group and shot, a flag where the differences at the two steps disagree by more than 5 %,
    and only there or where the event sequence changes; a shot is flagged when any group flags it."""
    shots, jac = jac_all
    study = StudyConfig(model="conti2026", dt=cfg["dt"], chunk=BATCH)
    flags = check_locality(study, jac, shots, column_scales(jac), cfg["n_steps"])
    groups, flip = flags["groups"], flags["flip"]
    assert set(groups) == set(jac.groups)
    per = np.stack([groups[g] for g in groups])
    np.testing.assert_array_equal(flags["flag"], per.any(0) | flip | ~jac.valid)
    assert flags["flag"][cfg["edge"]] and flip[cfg["edge"]] and groups["racket.rot"][cfg["edge"]]
    for g in STATE_GROUPS:  # the smooth shots' state inputs act smoothly
        assert not groups[g][cfg["smooth"]].any(), g
    for g in groups:
        gap = flags["disagreement"][g]
        np.testing.assert_array_equal(groups[g] & ~flip, (gap > 0.05) & ~flip, err_msg=g)
        assert np.all(groups[g][gap > 0.05])


def test_linear_budget_matches_monte_carlo_on_smooth_shots(model, jac_all, cfg):
    shots, jac = jac_all
    sub = jac.take(np.array(cfg["smooth"]))
    sources = budgets.default_sources()
    lin = budgets.linear_budget(sub, sources)
    mc = budgets.monte_carlo(model, shots.take(np.array(cfg["smooth"])), sub, sources, 1000, dt=cfg["dt"],
                             n_steps=cfg["n_steps"], seed=1, batch=BATCH)
    assert np.all(mc["kept"] >= 0.99)  # the event sequence (racket, then table) holds: smooth shots
    lin_std = np.sqrt(np.einsum("bkk->b", lin.cov))
    mc_std = np.sqrt(np.einsum("bkk->b", mc["cov"]))
    assert np.all(lin_std > 1e-3)  # millimetres of spread, not a degenerate case
    np.testing.assert_allclose(mc_std, lin_std, rtol=0.10)
    # per axis too (x: depth, y: sideways)
    np.testing.assert_allclose(mc["std"], lin.std, rtol=0.10)
    np.testing.assert_allclose(np.nansum(lin.share, 0), 1.0)


def test_command_takes_shots_from_a_dataset(model, jac_all, cfg, tmp_path):
    """``ttsim sensitivity --data``: the shots are the dataset's racket contacts (its racket states,
    the fitted incoming ball); three of them make the module's compiled shape."""
    from ttsim_jax.cli import main

    ds, truth = synthetic_contact_dataset(6, seed=3)
    path = save(ds, tmp_path / "contacts")
    shots = dataset_shots(model, path, dt=cfg["dt"], limit=3)
    assert len(shots) == 3 and shots.source == str(path)
    xyz = lambda table, prefix="": np.stack([table[prefix + a] for a in "xyz"], 1)[:3]  # noqa: E731
    np.testing.assert_allclose(shots.racket.pos, xyz(ds.rackets), atol=1e-12)
    np.testing.assert_allclose(shots.racket.vel, xyz(ds.rackets, "v"), atol=1e-12)
    np.testing.assert_allclose(shots.ball.vel, truth["vel_in"][:3], atol=0.06)  # the quadratic fit
    np.testing.assert_allclose(shots.ball.spin, truth["spin_in"][:3], atol=1e-3)
    np.testing.assert_allclose(shots.ball.pos + contact_time(cfg["dt"]) * shots.ball.vel, xyz(ds.events), atol=1e-9)
    out = tmp_path / "study"
    assert main(["sensitivity", "--data", str(path), "--shots", "3", "--dt", str(cfg["dt"]), "--horizon", "0.7",
                 "--chunk", "3", "--float64", "--no-check", "--out", str(out)]) == 0
    doc = json.loads((out / "sensitivity.json").read_text())
    assert doc["source"] == str(path) and doc["n_steps"] == cfg["n_steps"] and len(doc["shots"]) == 3
    want = outcomes(model, shots, flatten_inputs(model, shots, layout_of(model)), target="landing", dt=cfg["dt"],
                    n_steps=cfg["n_steps"], batch=BATCH)
    assert want.valid.any()  # at least one contact sends the ball onto the table
    assert [s["valid"] for s in doc["shots"]] == want.valid.tolist()
    for row, v, ok in zip(doc["shots"], want.values, want.valid):
        np.testing.assert_allclose(row["values"], v, atol=1e-9)
        j = np.asarray(row["jacobian"])
        assert (np.abs(j).max() > 0.01) if ok else not j.any()
    assert (out / "report.md").exists() and (out / "heatmaps.png").exists()
    report = (out / "report.md").read_text()  # --no-check: nothing claims the gradients were checked
    assert "hold beyond the point" not in report.replace("not checked to hold beyond the point", "")
    assert "--no-check" in report
