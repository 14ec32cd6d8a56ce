"""The diagnosis and the record's spin, on the bundled buckling dataset (conti2026 + buckling, no
noise; tests/diagnose/data/README.md):

* recorded without any spin (as most trackers record), the flights fly their latent spin
  (``Settings.spin = "auto"``), the report counts them, and buckling is still found;
* with every measured spin 25 % high, the record section's spin check says so, its correction is
  accepted and buckling is found on the corrected record;
* with the spin true and the model's air 25 % denser than the record's, the flights read as a spin
  20 % high, but the correction makes the bounces worse: it is refused, and the air is found.
"""

import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.data import load
from ttsim_jax.diagnose.diagnosis import Settings, diagnose
from ttsim_jax.diagnose.report import markdown

from test_diagnose import BUCKLING, CANDIDATES


def with_spin(ds, factor: float, conf=None):
    """``ds`` with every recorded spin times ``factor`` (and its confidence set to ``conf``)."""
    tables = {}
    for name in ("segments", "observations"):
        t = dict(getattr(ds, name))
        for a in "xyz":
            t[f"spin_{a}"] = np.asarray(t[f"spin_{a}"]) * factor
        if conf is not None:
            t["spin_conf"] = np.full(len(t["spin_conf"]), conf)
        tables[name] = t
    return ds.replace(**tables)


@pytest.fixture(scope="module")
def model():
    return load_model("conti2026", dtype=jnp.float32)


@pytest.fixture(scope="module")
def unmeasured(model):
    return diagnose(with_spin(load(BUCKLING), 0.0, conf=0.0), model, Settings.quick(effects=CANDIDATES, spin_check=True))


@pytest.fixture(scope="module")
def reads_high(model):
    return diagnose(with_spin(load(BUCKLING), 1.25), model, Settings.quick(effects=CANDIDATES, spin_check=True))


@pytest.fixture(scope="module")
def dense_air(model):
    denser = model.replace(aero=model.aero.replace(rho_air=model.aero.rho_air * 1.25))
    return diagnose(load(BUCKLING), denser, Settings.quick(effects=("buckling", "air_density"), spin_check=True))


def test_a_record_without_spin_flies_latent_spin_and_still_finds_the_cause(unmeasured):
    src = unmeasured.spin_sources
    assert src["measured"] == 0 and src["latent"] >= 0.9 * unmeasured.counts["flight"], src
    assert unmeasured.candidates[0]["name"] == "buckling" and unmeasured.candidates[0]["significant"]
    assert "skipped" in unmeasured.record["spin_check"]  # nothing measured to check
    text = markdown(unmeasured)
    assert f"latent {src['latent']}" in text and "read as spin" in text


@pytest.mark.slow  # 25 s: a second diagnosis; the evaluation's latent-against-zero test stays in the default run
def test_latent_spin_flies_closer_than_spin_zero(model, unmeasured):
    """The same record flown at spin 0 (``--spin zero``): its flights miss by more."""
    zero = diagnose(with_spin(load(BUCKLING), 0.0, conf=0.0), model,
                    Settings.quick(effects=("spin_decay",), spin="zero"))
    assert zero.spin_sources == {"measured": 0, "latent": 0, "zero": zero.counts["flight"]}
    assert unmeasured.where["flight"]["mean"] < 0.5 * zero.where["flight"]["mean"]


def test_a_spin_reading_high_is_named_corrected_and_the_cause_still_found(reads_high):
    """The spin check reads the record's spin 25 % high; its correction (the spin times 0.8) is the
    first candidate, on the record: accepted (the flights fly closer), every later stage works on
    the corrected record, and buckling is found as on the record with its true spin."""
    sc = reads_high.record["spin_check"]
    assert abs(sc["reads"] - 1.25) < 0.05, sc["summary"]
    assert any(f.startswith("spin reads") and f.endswith("high") for f in sc["findings"]), sc["findings"]
    corr = reads_high.spin_correction
    assert corr["accepted"] and corr["applied"] == [f"size multiplied by {sc['scale']:.2f}"]
    assert corr["heldout"]["ci95"][0] > 50.0 and corr["heldout"]["after_rms"] < 0.5 * corr["heldout"]["before_rms"]
    v = reads_high.verdict
    assert v.effects[:2] == ["spin_record", "buckling"], v.effects
    assert "corrected as the spin check reads it" in v.text and "spin check" in v.text
    text = markdown(reads_high)
    assert "spin_check: " in text and "- spin correction: " in text


def test_thinner_air_that_reads_as_spin_is_not_put_on_the_record(dense_air):
    """Thinner air than modelled bends the flights as a spin read high would, and the spin check
    reads it so; but the bounces take the measured spin through the contact laws, not the air, and
    the correction moves them away from the record: refused, the verdict names the air (and the
    record's buckling), not the spin."""
    sc = dense_air.record["spin_check"]
    assert any(f.startswith("spin reads") and f.endswith("high") for f in sc["findings"]), sc["findings"]
    corr = dense_air.spin_correction
    assert corr["heldout"]["ci95"][0] > 0  # the flights alone would have taken it
    assert not corr["accepted"] and "table" in corr["contradicted"], corr
    assert corr["contacts"]["table"]["after_rms"] > 2 * corr["contacts"]["table"]["before_rms"]
    v = dense_air.verdict
    assert "spin_record" not in v.effects and {"air_density", "buckling"} <= set(v.effects), v.effects
    assert "The bounces agree with the measured spin" in v.text and "correct the record's spin" not in v.text
    # without the joint fit (quick settings) the before/after holds both, each in its own phases
    assert set(dense_air.combined["name"].split("+")) == {"air_density", "buckling"}
    assert "buckling + air_density close" in v.text and "of the flight gap" in v.text
    assert "- spin correction: " in markdown(dense_air)


@pytest.mark.slow  # 24 s: the command-line door of the record check that the fixtures above run in the diagnosis
def test_data_info_spin_check_runs_the_same_check(capsys):
    from ttsim_jax.cli import main

    assert main(["data", "info", str(BUCKLING), "--spin-check"]) == 0
    out = capsys.readouterr().out
    line = [x for x in out.splitlines() if x.startswith("spin check:")]
    assert len(line) == 1 and "opposite" in line[0] and line[0].endswith("consistent"), out


@pytest.mark.slow  # 15 s: a third diagnosis of the record
def test_without_the_correction_the_check_is_reported_and_nothing_is_explained_with_it(model):
    out = diagnose(with_spin(load(BUCKLING), 1.25), model,
                   Settings.quick(effects=CANDIDATES, spin_check=True, spin_correct=False))
    assert out.spin_correction is None and out.record["spin_check"]["findings"]
    v = out.verdict
    assert v.level != "explained" and "spin_record" not in v.effects and "correct the record's spin" in v.text
