"""`ttsim fit` on several datasets, on data that cannot support every stage, and when a stage fails
(:mod:`ttsim_jax.fit.pipeline`, through the command line in-process), on parts of the bundled
sample (3 sessions, 238 segments, 115 table bounces, 51 racket contacts)."""

import json
from pathlib import Path

import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.cli import main
from ttsim_jax.data import load, save, validate
from ttsim_jax.data.dataset import select_rows
from ttsim_jax.data.merge import id_offsets, merge_datasets

SAMPLE = Path(__file__).resolve().parents[2] / "ttsim_jax" / "data" / "sample" / "games"


@pytest.fixture(scope="module")
def sample():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the sample predates page checksums
        return load(SAMPLE)


def sessions_of(ds, keep):
    """The rows of ``ds`` in sessions ``keep`` (ids unchanged)."""
    tables = {}
    for name in ("sessions", "observations", "events", "segments"):
        t = ds.table(name)
        tables[name] = select_rows(t, np.isin(t["session_id"], keep))
    tables["rackets"] = select_rows(ds.rackets, np.isin(ds.rackets["event_id"], tables["events"]["event_id"]))
    return ds.replace(**tables)


def test_merged_datasets_keep_their_references(sample):
    a, b = sessions_of(sample, [0]), sessions_of(sample, [1, 2])
    merged = merge_datasets([a, b], ["first", "second"])
    validate(merged)
    for name in ("sessions", "observations", "events", "rackets", "segments"):
        assert merged.n_rows(merged.table(name)) == sample.n_rows(sample.table(name))
    off = id_offsets([a, b])[1]
    assert off["session_id"] == 1 and off["event_id"] > int(a.events["event_id"].max())
    # b's rows point at b's rows: the same observations per segment, the same events around them
    seg = merged.segments
    second = seg["session_id"] >= off["session_id"]
    np.testing.assert_array_equal(seg["segment_id"][second] - off["segment_id"], b.segments["segment_id"])
    ends = seg["end_event_id"][second]
    np.testing.assert_array_equal(np.where(ends >= 0, ends - off["event_id"], -1), b.segments["end_event_id"])
    counts = lambda d: np.unique(d.observations["segment_id"][d.observations["segment_id"] >= 0], return_counts=True)[1]  # noqa: E731
    np.testing.assert_array_equal(counts(merged), np.concatenate([counts(a), counts(b)]))
    assert [str(n).split("/")[0] for n in merged.sessions["name"]] == ["first", "second", "second"]
    assert len(np.unique(merged.events["event_id"])) == len(merged.events["event_id"])


def test_fit_of_two_datasets_is_the_fit_of_their_union(sample, tmp_path, capsys):
    save(sessions_of(sample, [0]), tmp_path / "a")
    save(sessions_of(sample, [1, 2]), tmp_path / "b")
    both, whole = tmp_path / "both", tmp_path / "whole"
    assert main(["fit", "--data", str(tmp_path / "a"), "--data", str(tmp_path / "b"), "--out", str(both),
                 "--stages", "aero", "--spin", "measured", "--quiet"]) == 0  # the union, not the latent spins, on test
    assert main(["fit", "--data", str(SAMPLE), "--out", str(whole), "--stages", "aero", "--spin", "measured",
                 "--quiet"]) == 0
    info = json.loads(both.with_suffix(".fit.json").read_text())
    assert info["data"] == [str(tmp_path / "a"), str(tmp_path / "b")]
    assert info["aero"]["counts"]["segments"] == 238
    assert info["aero"]["counts"]["used"] == json.loads(whole.with_suffix(".fit.json").read_text())["aero"]["counts"]["used"]
    np.testing.assert_allclose(np.asarray(load_model(both.with_suffix(".toml")).aero.drag.cd),
                               np.asarray(load_model(whole.with_suffix(".toml")).aero.drag.cd), rtol=1e-4)
    # the JSON holds the config it was written with
    assert info["model_toml"] == both.with_suffix(".toml").read_text()
    # the fitted model is compared with the base on each dataset too, and on all of them together
    each = {f"aero on {tmp_path / x}": info["comparison"][f"aero on {tmp_path / x}"] for x in "ab"}
    assert sum(c["n"] for c in each.values()) == info["comparison"]["aero"]["n"]
    assert all(c["on"] == "training" and c["worse"] == [k for k in c["base"] if c["fitted"][k] > c["base"][k]]
               for c in each.values())


def test_default_stages_skip_what_the_data_cannot_fit(sample, tmp_path, capsys):
    data = tmp_path / "no_rackets"  # as the public datasets: racket hits seen as 'other' events, no racket states
    events = dict(sample.events, kind=np.where(sample.events["kind"] == "racket", "other", sample.events["kind"]))
    save(sample.replace(events=events, rackets=select_rows(sample.rackets, np.zeros(len(sample.rackets["event_id"]),
                                                                                   bool))), data)
    out = tmp_path / "fitted"
    assert main(["fit", "--data", str(data), "--out", str(out), "--test-fraction", "0.3", "--spin", "measured",
                 "--quiet"]) == 0  # the stages, not the latent spins (test_fit_command's default fit), on test
    text = capsys.readouterr().out
    assert "racket: skipped: no racket contacts with a racket state" in text
    info = json.loads(out.with_suffix(".fit.json").read_text())
    assert info["fitted"] == ["aero", "table"] and list(info["skipped"]) == ["racket"]
    assert load_model(out.with_suffix(".toml")).racket.kind == load_model("conti2026").racket.kind
    # fitted against the base on the held-out sessions, and what is worse is said
    for stage in ("aero", "table"):
        c = info["comparison"][stage]
        assert c["on"] == "held_out" and c["n"] > 0
        assert c["worse"] == [k for k in c["base"] if c["fitted"][k] > c["base"][k]]
        assert (f"warning: {stage}: the fitted model is worse" in text) == bool(c["worse"])
    # asked for by name, a stage the data cannot support is refused before any work
    assert main(["fit", "--data", str(data), "--out", str(tmp_path / "x"), "--stages", "aero,racket", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--stages racket" in err and str(data) in err and "no racket contacts" in err
    assert not (tmp_path / "x.toml").exists() and not (tmp_path / "x.fit.json").exists()


def test_what_was_fitted_is_written_when_a_later_stage_fails(tmp_path, monkeypatch, capsys):
    from ttsim_jax.fit import table

    def broken(*args, **kwargs):
        raise RuntimeError("the table solver broke")

    monkeypatch.setattr(table, "fit_table", broken)
    out = tmp_path / "partial"
    with pytest.raises(RuntimeError, match="the table solver broke"):
        main(["fit", "--data", str(SAMPLE), "--out", str(out), "--stages", "aero,table", "--spin", "measured", "--quiet"])
    assert "stage table failed" in capsys.readouterr().err
    model, base = load_model(out.with_suffix(".toml")), load_model("conti2026")
    assert not np.allclose(np.asarray(model.aero.drag.cd), np.asarray(base.aero.drag.cd))
    assert float(model.table.e0) == float(base.table.e0)
    info = json.loads(out.with_suffix(".fit.json").read_text())
    assert info["fitted"] == ["aero"] and info["partial"]
    assert info["failed"]["stage"] == "table" and "the table solver broke" in info["failed"]["error"]
    assert info["model_toml"] == out.with_suffix(".toml").read_text()


def test_too_few_racket_contacts_skip_the_racket_stage_with_the_count(sample, tmp_path, capsys):
    keep = np.zeros(len(sample.rackets["event_id"]), bool)
    keep[:5] = True  # five racket states: fewer than the stage needs for its parameters
    kept = set(np.asarray(sample.rackets["event_id"])[keep].tolist())
    is_other = (sample.events["kind"] == "racket") & ~np.isin(sample.events["event_id"], list(kept))
    data = tmp_path / "five_rackets"
    save(sample.replace(events=dict(sample.events, kind=np.where(is_other, "other", sample.events["kind"])),
                        rackets=select_rows(sample.rackets, keep)), data)
    out = tmp_path / "fitted"
    assert main(["fit", "--data", str(data), "--out", str(out), "--stages", "racket", "--quiet"]) == 2
    captured = capsys.readouterr()
    assert "racket: skipped: 3 usable racket contacts (5 racket events" in captured.out
    assert "nothing to fit" in captured.err and "at least 10 are needed" in captured.err
    assert not out.with_suffix(".toml").exists()


def test_segments_without_a_measured_spin_place_the_drag_at_their_latent_spin_and_leave_magnus_alone(sample):
    """The aero stage with the sample's spins withheld from every odd session: those segments enter
    the C_D regression at their latent spin (a C_D their deceleration shows whatever the spin, and
    placed along the spin ratio by the latent spin's size), and the C_M form is the one the
    measured spins alone give (a latent spin is the spin the base's C_M needs)."""
    from ttsim_jax.fit.identify import identify_aero

    seg = sample.segments
    blind = sample.replace(segments=dict(seg, spin_conf=np.where(np.asarray(seg["session_id"]) % 2 == 1, 0.0,
                                                                 seg["spin_conf"])))
    auto = identify_aero(blind, "conti2026", forms=("drag", "magnus"))
    measured = identify_aero(blind, "conti2026", forms=("drag", "magnus"), spin="measured")
    seen = identify_aero(sample, "conti2026", forms=("drag",), spin="measured")
    c = auto.counts
    assert c["segments"] == c["too_short"] + c["held_out"] + c["low_spin_conf"] + c["fitted"]
    assert c["latent"] >= 40 and c["fitted"] == measured.counts["fitted"] + c["latent"]
    assert c["used_measured"] == measured.counts["used"] and c["used"] > measured.counts["used"]
    for k, v in auto.magnus.values.items():
        np.testing.assert_allclose(v, measured.magnus.values[k], rtol=1e-12, err_msg=k)
    assert auto.drag.support.sum() == pytest.approx(c["used"]) and not np.allclose(auto.drag.values["cd"],
                                                                                 measured.drag.values["cd"])
    # each blinded segment: the C_D of its flight as with its measured spin, at a spin of about its size
    row = {int(i): k for k, i in enumerate(seen.segment_ids)}  # the segments with a measured spin
    latent = (auto.spin_source == "latent") & np.isin(auto.segment_ids, seen.segment_ids)
    assert latent.sum() >= 40
    rows = [row[int(i)] for i in auto.segment_ids[latent]]
    assert np.median(np.abs(auto.fits.cd[latent] - seen.fits.cd[rows])) < 0.1 * np.median(seen.fits.stderr[rows, 6])
    size = np.linalg.norm(auto.fits.spin[latent], axis=1) / np.linalg.norm(seen.fits.spin[rows], axis=1)
    assert abs(np.median(size) - 1.0) < 0.2, np.median(size)
    assert "at their latent spin" in auto.summary()


def test_a_record_without_any_measured_spin_fits_its_drag_at_the_latent_spin_only_when_asked(sample):
    from ttsim_jax.fit.pipeline import stage_problems

    blind = sample.replace(segments=dict(sample.segments, spin_conf=np.zeros(len(sample.segments["spin_conf"]))))
    assert "aero" not in stage_problems(blind, ("aero",))  # --spin auto, the default
    assert "aero" not in stage_problems(blind, ("aero",), spin="latent")
    for spin in ("measured", "zero"):
        why = stage_problems(blind, ("aero",), spin=spin)["aero"]
        assert "no flight segment with a measured spin" in why and "--spin auto" in why
