"""Report tables, figures and JSON from a Jacobian with known numbers; the command's user errors."""

import json

import numpy as np

from ttsim_jax.cli import main
from ttsim_jax.sensitivity import budgets, report
from ttsim_jax.sensitivity.cases import ShotSet
from ttsim_jax.sensitivity.jacobians import Jacobian
from ttsim_jax.state import Ball, Racket


def known_study(n=12):
    rng = np.random.default_rng(0)
    cols = [f"{g}[{i}]" for g in ("racket.pos", "racket.rot", "racket.vel", "ball.spin") for i in range(3)] + ["table.e0"]
    groups = np.array([c.split("[")[0] for c in cols], dtype=object)
    groups[-1] = "table.restitution"
    j = np.zeros((n, 2, len(cols)))
    j[:, 0, 3] = 1.0  # landing x: 1 m per rad of racket rotation about x ...
    j[:, 1, 4] = np.linspace(1.0, 3.0, n)  # ... landing y grows with the shot
    j[:, 0, 12] = 0.5  # 0.5 m per unit of e0
    nominal = np.zeros((n, len(cols)))
    nominal[:, 12] = 0.9
    jac = Jacobian("landing", ("landing_x", "landing_y"), rng.normal(size=(n, 2)), np.ones(n, bool),
                   np.tile([2, 1], (n, 1)), j, nominal, cols, groups)
    z = np.zeros((n, 3))
    shots = ShotSet(Ball(z, z, z), Racket(z, np.tile(np.eye(3), (n, 1, 1)), z, z, np.zeros((n, 2))),
                    label=np.array(["topspin_drive", "push"] * (n // 2)), speed=np.linspace(5, 20, n),
                    spin=np.linspace(-300, 600, n), contact=np.zeros((n, 2)))
    return jac, shots


def test_group_sensitivity_is_the_scaled_column_norm():
    jac, shots = known_study()
    scale = report.column_scales(jac)
    np.testing.assert_allclose(scale[12], 0.009)  # 1 % of e0
    sens = report.group_sensitivity(jac, scale)
    rot = scale[3]
    np.testing.assert_allclose(sens["racket.rot"], rot * np.sqrt(1.0 + np.linspace(1.0, 3.0, 12) ** 2))
    np.testing.assert_allclose(sens["table.restitution"], 0.5 * 0.009)
    np.testing.assert_allclose(sens["racket.pos"], 0.0)


def test_report_files_hold_the_numbers(tmp_path):
    jac, shots = known_study()
    scale = report.column_scales(jac)
    # shot 0's gradient is local in e0 only, shot 2's in the racket's orientation only
    local_e0, local_rot = np.arange(12) == 0, np.arange(12) == 2
    flags = dict(flag=local_e0 | local_rot, flip=np.zeros(12, bool), disagreement={},
                 groups={"table.restitution": local_e0, "racket.rot": local_rot})
    budget = budgets.linear_budget(jac, budgets.default_sources())
    summary = report.summarise(jac, shots, flags, budget, scale)
    # the racket's orientation is the only state source that moves the landing: 100 % of the variance
    assert summary["budget_by_type"]["push"]["share"]["racket orientation"] == 1.0
    assert "| racket.rot |" in summary["markdown"].split("## By shot type")[1].split("\n")[4]  # ranked first
    path = report.write_json(tmp_path / "s.json", meta=dict(model="known"), jac=jac, shots=shots, flags=flags,
                             summary=summary, scale=scale, budget=budget)
    doc = json.loads(path.read_text())
    assert doc["model"] == "known" and len(doc["shots"]) == 12
    assert doc["shots"][0]["flagged"] and not doc["shots"][1]["flagged"]
    np.testing.assert_allclose(doc["shots"][5]["jacobian"], jac.jac[5])
    np.testing.assert_allclose(doc["shots"][5]["budget"]["cov"], budget.cov[5])
    # a group's medians leave out only the shots flagged for that group (shots 0 and 2 are topspin
    # drives): shot 0 counts for the racket's orientation, shot 2 does not
    rot = summary["sensitivity"]["racket.rot"]
    np.testing.assert_allclose(doc["by_type"]["topspin_drive"]["racket.rot"], 1e3 * np.median(rot[[0, 4, 6, 8, 10]]))
    assert summary["local_by_group"] == {"table.restitution": 1, "racket.rot": 1}
    # the budget relies on the racket and spin inputs: shot 2 is out of it, shot 0 in
    assert budget.groups == ["racket.pos", "racket.rot", "racket.vel", "ball.spin"]
    assert summary["ok_budget"][0] and not summary["ok_budget"][2] and summary["ok_budget"].sum() == 11
    assert not summary["ok"][0] and not summary["ok"][2]
    for png in (report.heatmaps(jac, shots, summary["sensitivity"], summary["ok_group"], tmp_path / "h.png"),
                report.budget_bars(summary, budget.sources, tmp_path / "b.png")):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_command_refuses_bad_options_before_the_work(tmp_path, capsys):
    assert main(["sensitivity", "--types", "drive", "--out", str(tmp_path / "o")]) == 2
    assert "--types drive: unknown shot types" in capsys.readouterr().err
    assert main(["sensitivity", "--racket-pos-std", "-1", "--out", str(tmp_path / "o")]) == 2
    assert "--racket-pos-std -1: must be >= 0" in capsys.readouterr().err
    bad = tmp_path / "cov.json"
    bad.write_text(json.dumps({"parameters": ["table.nope"], "covariance": [[1.0]]}))
    assert main(["sensitivity", "--param-cov", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "unknown parameter 'table.nope'" in err
    assert not (tmp_path / "o").exists()


def test_parameter_scales_follow_each_value_not_the_group():
    """A group mixing magnitudes (C_D ~ 0.5 beside Reynolds numbers ~ 1e5) scales each parameter by
    its own value; only zeros take a share of the group's size."""
    jac, _ = known_study(2)
    jac.columns = jac.columns[:-1] + ["aero.drag.cd[0]", "aero.drag.re_ref[0]", "aero.drag.cd[1]"]
    jac.groups = np.concatenate([jac.groups[:-1], np.array(["aero.drag"] * 3, dtype=object)])
    jac.nominal = np.concatenate([jac.nominal[:, :-1], np.tile([0.5, 1e5, 0.0], (2, 1))], 1)
    scale = report.column_scales(jac)
    np.testing.assert_allclose(scale[-3:], [0.005, 1e3, 0.01 * 0.1 * np.sqrt((0.25 + 1e10) / 2)])
