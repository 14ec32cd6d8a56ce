"""The diagnosis on measured data without racket contacts (a few TT3D rallies: flights and one table
bounce each, no racket states, no measured spin): the racket and landing phases are reported as
"no data" with their reason, never as a number, no number of the report is NaN, and the bounces,
whose incoming spin is unknown, are compared in their normal velocity only. Needs
../shared/data/real."""

import json
import math
import shutil
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.data.importers import import_source
from ttsim_jax.diagnose.diagnosis import Settings, diagnose
from ttsim_jax.diagnose.report import write_report

TT3D = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "tt3d"
FILES = 12


def _reject(value):
    raise ValueError(f"non-finite number {value} in diagnosis.json")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    if not TT3D.is_dir():
        pytest.skip(f"the public measured data is not here ({TT3D})")
    src = tmp_path_factory.mktemp("tt3d")
    for f in sorted(TT3D.glob("[0-9]*.csv"))[:FILES]:
        shutil.copy(f, src / f.name)
    ds = import_source(src, "tt3d")
    model = load_model("conti2026", dtype=jnp.float32)
    keep = {}
    out = diagnose(ds, model, Settings.quick(effects=("table_tilt",), steps=5, landing=True), keep=keep)
    folder = tmp_path_factory.mktemp("report")
    write_report(out, folder, data="tt3d", model="conti2026")
    return out, keep["problem"], folder


def test_phases_without_data_are_no_data(run):
    out, _, folder = run
    assert set(out.where) == {"flight", "table"}
    assert set(out.no_data) == {"racket", "landing"}
    assert "racket states" in out.no_data["racket"] and "racket" in out.no_data["landing"]
    report = (folder / "report.md").read_text()
    assert "| racket | 0 | 0 | no data | - |" in report and "| landing | 0 | 0 | no data | - |" in report
    assert "nan" not in report.lower()


def test_the_diagnosis_is_typed_and_its_json_is_the_file(run):
    """``diagnose`` returns a ``Diagnosis`` whose verdict is a ``Verdict``; ``to_json()`` is what
    ``diagnosis.json`` holds (the verdict as a dict, the sections that do not apply left out), and
    the report renders the same from either."""
    from ttsim_jax.diagnose import Diagnosis, Verdict
    from ttsim_jax.diagnose.report import markdown

    out, _, folder = run
    assert isinstance(out, Diagnosis) and isinstance(out.verdict, Verdict)
    assert out.verdict.explained == (out.verdict.level == "explained")
    body = out.to_json()
    stored = json.loads((folder / "diagnosis.json").read_text())
    assert body == stored
    assert stored["verdict"]["text"] == out.verdict.text and stored["verdict"]["level"] == out.verdict.level
    assert "arrays" not in stored and "histories" not in stored and "loss_history" in stored
    assert out.spin_correction is None and "spin_correction" not in stored  # no measured spin to correct
    assert markdown(out, "tt3d", "conti2026") == markdown(stored, "tt3d", "conti2026")
    assert markdown(out, "tt3d", "conti2026") == (folder / "report.md").read_text()


def test_no_nan_in_the_json(run):
    out, _, folder = run
    d = json.loads((folder / "diagnosis.json").read_text(), parse_constant=_reject)
    assert d["no_data"] == out.no_data
    for p in ("flight", "table"):
        assert math.isfinite(d["where"][p]["mean"]) and d["where"][p]["n"] > 0
    # one throw per session: the per-session effects would be fitted with one shared set
    assert d["pooled_sessions"] is True


def test_bounces_without_spin_compare_the_normal_velocity_only(run):
    out, problem, _ = run
    n = out.counts["table"]
    e = np.asarray(problem.base["table"])[:n]
    assert n >= FILES // 2
    assert np.all(e[:, :2] == 0.0) and np.all(e[:, 3:] == 0.0)
    assert np.all(np.abs(e[:, 2]) > 0.0)


def test_thin_sessions_pool_the_per_session_effects():
    from ttsim_jax.diagnose import candidates as C

    def problem(per_session):
        sessions = np.repeat(np.arange(10), per_session)
        data = {"flight": {"session": sessions, "train": np.ones(len(sessions))}}
        return C.Problem(data=data, phases=("flight",), n_sessions=10, sessions=np.arange(10))

    assert C.pooled(problem(2)) and not C.pooled(problem(C.MIN_SESSION_ITEMS))
    assert C.spec("air_flow")[0].per_session and not C.spec("air_flow", pooled=True)[0].per_session
