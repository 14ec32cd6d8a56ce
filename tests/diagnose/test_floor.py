"""The noise floor of each phase (:mod:`ttsim_jax.diagnose.floor`):

* the position noise estimator on synthetic parabolas with known noise (and missing frames);
* the variance of a contact's velocity estimate against repeated noisy fits;
* the spin noise estimator, and its refusal where each segment holds one estimate;
* against the truth: the generated clean dataset (tests/evaluate/data/clean: durr2026, no effect)
  with the generator's own position noise (:class:`~ttsim_jax.effects.PositionNoise`, the
  function the generator applies to what it writes) diagnosed with durr2026, the true model: its
  actual per-phase RMS error on the noisy record is the true floor, and the estimated floor is
  within 15 % of it (flight, table; the 15 racket contacts, one of which dominates, within 40 %);
* the diagnosis carries it (``out.floor``) and the report prints it, with no NaN anywhere.
"""

import json
import math
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.data import load
from ttsim_jax.data.contact_states import ContactFit, fit_contact_state
from ttsim_jax.diagnose import candidates as C
from ttsim_jax.diagnose import floor as F
from ttsim_jax.diagnose.phases import collect
from ttsim_jax.effects.record import PositionNoise

CLEAN = Path(__file__).resolve().parents[1] / "evaluate" / "data" / "clean"  # durr2026, no effect, no noise
STD = np.array([0.0015, 0.0015, 0.001])  # the generator's typical position noise [m]
SEEDS = (0, 1)
#: max_segments of Settings.quick: the compiled shapes of test_diagnose's clean run.
MAX_SEGMENTS = 96


def _parabolas(rng, n_seg=40, n=60, rate=200.0, sigma=(0.002, 0.0015, 0.001), drop=0.1, jitter=0.0):
    """Segments of free flight under gravity with Gaussian position noise; a share ``drop`` of the
    frames missing, the sample times jittered by up to ``jitter`` intervals."""
    g = np.array([0.0, 0.0, -9.81])
    out = []
    for _ in range(n_seg):
        t = (np.arange(n) + rng.uniform(-jitter, jitter, n)) / rate
        t = t[rng.uniform(size=n) >= drop]
        v0 = rng.uniform([-8, -2, 0], [8, 2, 4])
        p = np.array([0.0, 0.0, 1.0]) + t[:, None] * v0 + 0.5 * t[:, None] ** 2 * g
        out.append((t, p + rng.normal(size=p.shape) * np.asarray(sigma), np.zeros_like(p), np.ones(len(t))))
    return out


def test_position_sigma_on_noisy_parabolas():
    sigma = np.array([0.002, 0.0015, 0.001])
    for jitter in (0.0, 0.3):  # even sampling, and times jittered as in measured logs
        est = F.position_sigma(_parabolas(np.random.default_rng(3), sigma=sigma, jitter=jitter), seed=1)
        assert np.all(np.abs(est["sigma"] / sigma - 1.0) < 0.05), (jitter, est["sigma"])
        lo, hi = np.percentile(est["draws"], [2.5, 97.5], axis=0)
        assert np.all((lo < sigma) & (sigma < hi)), (jitter, lo, hi)
    # without noise the flight's own curvature does not leak into the third differences
    clean = F.position_sigma(_parabolas(np.random.default_rng(3), sigma=(0.0, 0.0, 0.0), jitter=0.3))
    assert np.max(clean["sigma"]) < 1e-7


def test_position_sigma_refuses_too_few_differences():
    est = F.position_sigma(_parabolas(np.random.default_rng(0), n_seg=1, n=6, drop=0.0))
    assert "reason" in est and "third differences" in est["reason"]


def test_velocity_variance_matches_repeated_fits():
    rng = np.random.default_rng(0)
    t = 1.0 - (np.arange(10)[::-1] + 0.3) / 200.0  # the 10 samples before a contact at t = 1 s
    sigma = 0.002
    v = [fit_contact_state(t, 0.5 * 9.81 * t[:, None] ** 2 + rng.normal(0, sigma, (len(t), 3)), 1.0, 2)[1]
         for _ in range(4000)]
    measured = np.var(np.asarray(v), axis=0)
    predicted = sigma**2 * F.velocity_variance(t, 1.0, 2)
    assert np.all(np.abs(measured / predicted - 1.0) < 0.08), (measured, predicted)


def test_spin_sigma():
    rng = np.random.default_rng(1)
    segs = []
    for _ in range(30):
        conf = rng.uniform(0.5, 1.0, 40)
        segs.append((None, None, rng.uniform(-200, 200, 3) + rng.normal(0, [10.0, 20.0, 5.0], (40, 3)), conf))
    est = F.spin_sigma(segs)
    assert np.all(np.abs(est["sigma"] / np.array([10.0, 20.0, 5.0]) - 1.0) < 0.1), est
    one = [(None, None, np.repeat(rng.normal(size=(1, 3)), 20, 0), np.ones(20)) for _ in range(5)]
    assert "one estimate per segment" in F.spin_sigma(one)["reason"]
    assert F.spin_sigma([(None, None, np.zeros((9, 3)), np.zeros(9))])["reason"] == "no spin is measured"
    assert F.mean_spin_variance_factor(np.ones(4)) == pytest.approx(0.25)


def _noisy(seed: int):
    ds = load(CLEAN)
    pos = PositionNoise(std=STD).observe_positions(ds.positions, np.random.default_rng(seed))
    obs = dict(ds.observations, x=pos[:, 0], y=pos[:, 1], z=pos[:, 2])
    return ds.replace(observations=obs)


@pytest.fixture(scope="module")
def truth_runs():
    model = load_model("durr2026", dtype=jnp.float32)
    runs = []
    for seed in SEEDS:
        ds = _noisy(seed)
        ph = collect(ds, model, ContactFit(), max_segments=MAX_SEGMENTS, seed=0)
        pb = C.problem(ph, model)
        runs.append(F.floors(ds, ph, pb, model, ContactFit()))
    return runs


@pytest.mark.parametrize("phase,tolerance", [("flight", 0.15), ("table", 0.15), ("racket", 0.40)])
def test_floor_matches_the_true_models_error(truth_runs, phase, tolerance):
    """The true model's RMS error on the noisy record (mean square over the noise draws) against
    the floor estimated from the record alone."""
    error = math.sqrt(np.mean([r[phase]["error"] ** 2 for r in truth_runs]))
    floor = math.sqrt(np.mean([r[phase]["floor"] ** 2 for r in truth_runs]))
    assert abs(floor / error - 1.0) < tolerance, (phase, floor, error)
    for r in truth_runs:
        assert np.all(np.abs(np.asarray(r[phase]["sigma_m"]) / STD - 1.0) < 0.1), r[phase]["sigma_m"]
        assert r[phase]["floor_ci95"][0] <= r[phase]["floor"] <= r[phase]["floor_ci95"][1]
        assert r[phase]["removable_ci95"][0] <= r[phase]["removable"] <= r[phase]["removable_ci95"][1]


def test_floor_in_the_diagnosis_and_report(tmp_path):
    from ttsim_jax.diagnose.diagnosis import Settings, diagnose
    from ttsim_jax.results import jsonable
    from ttsim_jax.diagnose.report import floor_lines, write_report

    model = load_model("durr2026", dtype=jnp.float32)
    out = diagnose(_noisy(0), model, Settings.quick(effects=("table_tilt",), steps=5))
    assert set(out.floor) == {"flight", "table", "racket"}
    for f in out.floor.values():
        assert set(f) >= {"error", "error_ci95", "floor", "floor_ci95", "removable", "removable_ci95", "sigma_m", "n"}
    write_report(out, tmp_path)
    text = (tmp_path / "diagnosis.json").read_text()
    json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in diagnosis.json"))
    report = (tmp_path / "report.md").read_text()
    assert "Noise floor" in report and "| flight | " in report and "nan" not in report.lower()
    # the detection limit of the one candidate, in its own parameter, in the report and the JSON
    lim = out.limits["candidates"]["table_tilt"]["table"]
    assert lim["size"] is None or (lim["size"] > 0 and len(lim["params"]["slope"]) == 2)
    assert "Detection limits" in report and "| table_tilt | table |" in report
    # a phase without a floor is a reason, never a number
    lines = floor_lines(dict(jsonable(out.floor), racket="no data: no racket states"))
    assert any("racket: no floor: no data" in line for line in lines)
