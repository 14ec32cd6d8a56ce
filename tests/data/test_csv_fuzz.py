"""Generated tracker logs, clean and broken, through ``read_csv``: each one imports or is refused
with a :class:`~ttsim_jax.errors.UserError` (whose message names the file), never anything else."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ttsim_jax.data import Dataset, read_csv
from ttsim_jax.data.csvlog import OBSERVATION_COLUMNS
from ttsim_jax.errors import UserError

#: Cells a broken log holds: extremes, non-numbers, overflowing integers, blanks.
ODD_CELLS = ["nan", "-nan", "inf", "-inf", "1e400", "-1e400", "1e308", "-1e308", "0", "-0", "", " ", "abc", "1,5",
             "0x10", str(2**70), str(-(2**70)), str(2**63), str(2**63 - 1), "1e-320", "3", "-7", "1_000", "NaN",
             "\u00e9", "\"", "1e5", "-1e5"]


def flight_rows(n: int, sessions: int, rate: float = 200.0) -> list[dict]:
    """``n`` samples of a ballistic flight across the table per session, as CSV cells."""
    rows = []
    for s in range(sessions):
        t = np.arange(n) / rate + 3.0 * s
        tau = t - 3.0 * s
        x, y, z = -1.2 + 6.0 * tau, 0.1 - 0.5 * tau, 0.3 + 1.5 * tau - 4.905 * tau**2
        for k in range(n):
            rows.append(dict(session_id=str(s), t=repr(float(t[k])), x=repr(float(x[k])), y=repr(float(y[k])),
                             z=repr(float(z[k])), spin_x="0.0", spin_y="150.0", spin_z="0.0", spin_conf="0.9"))
    return rows


@st.composite
def logs(draw):
    """A CSV log's text: columns dropped, added, reordered; cells replaced by odd values; rows
    duplicated, dropped and shuffled (each fault at its own rate, so that a good share of the
    logs stay importable)."""
    import random

    # hypothesis draws the seed; the faults' rates are the stream's (its own draws favour the ends
    # of every range, which would break nearly every log)
    rnd = random.Random(draw(st.integers(0, 2**32 - 1)))
    maybe = lambda p: rnd.random() < p  # noqa: E731
    columns = list(OBSERVATION_COLUMNS)
    spin = ["spin_x", "spin_y", "spin_z"]
    if maybe(0.25):  # no spin, or no confidence
        drop = spin if maybe(0.5) else ["spin_conf"]
        columns = [c for c in columns if c not in drop]
    if "spin_x" in columns and maybe(0.05):  # part of the spin
        columns.remove(rnd.choice(spin))
    if maybe(0.05):  # a required column missing
        columns.remove(rnd.choice(["session_id", "t", "x", "y", "z"]))
    if maybe(0.05):  # unknown or duplicated
        columns.append(rnd.choice(["speed", "session", "X", "t"]))
    rnd.shuffle(columns)
    rows = flight_rows(rnd.randint(0, 40) if maybe(0.1) else rnd.randint(20, 40), rnd.randint(1, 3))
    if rows and maybe(0.5):  # odd cells
        for _ in range(rnd.choice([1, 1, 2, 6])):
            r = rnd.randrange(len(rows))
            rows[r] = dict(rows[r], **{rnd.choice(columns): draw(st.sampled_from(ODD_CELLS))})
    if rows and maybe(0.2):  # duplicated rows
        for _ in range(rnd.choice([1, 3])):
            rows.insert(rnd.randrange(len(rows) + 1), rows[rnd.randrange(len(rows))])
    if rows and maybe(0.1):
        rnd.shuffle(rows)
    lines = [",".join(columns)] + [",".join(r.get(c, "1.0") for c in columns) for r in rows]
    if rows and maybe(0.05):  # a ragged line
        lines.insert(rnd.randint(1, len(lines)), ",".join(["1.0"] * rnd.randint(1, 12)))
    return "\n".join(lines) + "\n"


def import_or_refuse(text: str, folder) -> str:
    """Imports ``text`` as a log: "imported" or "refused" (a UserError naming the file); anything
    else raised fails the test."""
    path = folder / "observations.csv"
    path.write_text(text)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            ds = read_csv(path)
        except UserError as e:
            assert "observations.csv" in str(e), str(e)
            return "refused"
    assert isinstance(ds, Dataset)
    assert np.isfinite(ds.positions).all() and np.isfinite(ds.observations["t"]).all()
    return "imported"


def check(examples: int, tmp_path_factory) -> dict:
    """Runs the property over ``examples`` generated logs: {outcome: count}."""
    seen = {"imported": 0, "refused": 0}

    @settings(max_examples=examples, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(text=logs())
    def run(text):
        seen[import_or_refuse(text, tmp_path_factory.mktemp("log"))] += 1

    run()
    # both doors tested: a generator that broke every log would test the refusals only
    assert min(seen.values()) >= examples // 20, seen
    return seen


def test_a_generated_log_imports_or_is_refused_with_a_user_error(tmp_path_factory):
    check(200, tmp_path_factory)


@pytest.mark.slow
def test_a_generated_log_imports_or_is_refused_with_a_user_error_many(tmp_path_factory):
    check(2000, tmp_path_factory)


def test_the_fast_reader_reads_what_the_line_reader_reads(tmp_path_factory):
    """A plain log is parsed by Arrow, any other line by line: on 200 generated logs (clean and
    broken) the two give the same columns, or the same refusal at the same line and column."""
    from ttsim_jax.data import csvlog

    compared = {"same columns": 0, "same refusal": 0}

    def outcome(reader, text, file):
        try:
            return reader(text, file)
        except UserError as e:
            return (e.row, e.column, e.problem)

    @settings(max_examples=200, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(text=logs())
    def run(text):
        header = [h.strip() for h in text.split("\n", 1)[0].split(",")]
        if set(header) - set(OBSERVATION_COLUMNS) or len(set(header)) != len(header):
            return  # refused at the header, before either reader
        dtypes = {h: np.int64 if h == "session_id" else np.float64 for h in header}
        file = tmp_path_factory.getbasetemp() / "observations.csv"
        plain = outcome(lambda t, f: csvlog._read_plain(t, f, header, dtypes), text, file)
        if plain is None:
            return  # not a plain file: read line by line only
        lines = outcome(lambda t, f: csvlog._read_lines(t, f, header, dtypes, None), text, file)
        if isinstance(plain, tuple) and isinstance(plain[0], dict):
            assert isinstance(lines[0], dict), (lines, text[:500])
            np.testing.assert_array_equal(plain[1], lines[1])
            for h in header:
                np.testing.assert_array_equal(plain[0][h], lines[0][h], err_msg=h)
            compared["same columns"] += 1
        else:
            assert plain == lines, text[:500]
            compared["same refusal"] += 1

    run()
    assert min(compared.values()) >= 5, compared
