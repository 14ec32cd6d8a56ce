"""Importers of the three public datasets: every file read, bounces at the ball radius.

Needs the data in ../shared/data/real (or $TTSIM_REAL_DATA); skipped with a reason otherwise.
"""

from __future__ import annotations

import numpy as np
import pytest

from ttsim_jax.data import import_source, validate
from ttsim_jax.data.importers import mpi, spindoe, survey, tt3d

pytestmark = pytest.mark.realdata

RADIUS = 0.02
SOURCES = {
    # source: (folder, file pattern, module)
    "spindoe": ("spindoe", "[0-9]*.csv", spindoe),
    "tt3d": ("tt3d", "*.csv", tt3d),
    "mpi": ("mpi_ball_prediction", "*.hdf5", mpi),
}
_cache = {}


def imported(root, source):
    if source not in _cache:
        _cache[source] = import_source(root / SOURCES[source][0], source)
    return _cache[source]


def bounce_minima(t, z, window=3, min_speed=0.5):
    """Independent bounce finder: at each z minimum where the ball falls and rises faster than
    ``min_speed``, intersect the gravity parabolas through the samples on either side.

    Returns:
        list of (contact height, clean) where clean means no dropped frames next to it.
    """
    out = []
    dt_med = np.median(np.diff(t))
    for i in range(window, len(z) - window):
        if not (z[i] <= z[i - 1] and z[i] < z[i + 1]):
            continue
        if (z[i] - z[i - window]) / (t[i] - t[i - window]) > -min_speed:
            continue
        if (z[i + window] - z[i]) / (t[i + window] - t[i]) < min_speed:
            continue
        best = None
        for s in (i, i + 1):  # contact just before or just after sample i
            pre, post = slice(s - window, s), slice(s, s + window)
            zg = z + 4.905 * (t - t[i]) ** 2
            b1, a1 = np.polyfit(t[pre] - t[i], zg[pre], 1)
            b2, a2 = np.polyfit(t[post] - t[i], zg[post], 1)
            tc = (a2 - a1) / (b1 - b2)
            if t[s - 1] - t[i] - 1e-9 <= tc <= t[s] - t[i] + 1e-9:
                zc = a1 + b1 * tc - 4.905 * tc**2
                if best is None or zc < best:
                    best = zc
        if best is not None:
            clean = np.max(np.diff(t[i - 2 : i + 3])) <= 2.5 * dt_med
            out.append((best, clean))
    return out


@pytest.mark.parametrize("source", list(SOURCES))
def test_every_file_is_imported(real_root, source):
    folder, pattern, _ = SOURCES[source]
    files = sorted((real_root / folder).glob(pattern))
    assert files, f"no {pattern} in {real_root / folder}"
    ds = imported(real_root, source)
    validate(ds)
    names = set(ds.sessions["name"])
    if source == "mpi":
        import h5py

        expected = {f"mpi/{f.stem}/{k}" for f in files for k in h5py.File(f, "r")["originals"].keys()}
    else:
        expected = {f"{source}/{f.name}" for f in files}
    assert names == expected
    assert len(ds.events["event_id"]) > 0 and len(ds.segments["segment_id"]) > len(files) / 2


@pytest.mark.parametrize("source", list(SOURCES))
def test_bounces_sit_at_the_ball_radius(real_root, source):
    ds = imported(real_root, source)
    o = ds.observations
    heights, clean = [], []
    cuts = np.flatnonzero(np.diff(o["session_id"])) + 1
    for rows in np.split(np.arange(len(o["t"])), cuts):
        for zc, ok in bounce_minima(o["t"][rows], o["z"][rows]):
            if abs(zc - RADIUS) < 0.1:  # a table bounce, not a hit in the air
                heights.append(zc)
                clean.append(ok)
    heights = np.asarray(heights)[np.asarray(clean, bool)]
    assert len(heights) >= 50
    err = heights - RADIUS
    assert abs(np.median(err)) < 0.002, np.median(err)
    assert np.percentile(np.abs(err), 90) < 0.005, np.percentile(np.abs(err), 90)
    assert np.max(np.abs(err)) < 0.015, np.max(np.abs(err))
    # The detected table events agree.
    zt = ds.events["z"][ds.events["kind"] == "table"]
    assert abs(np.median(zt) - RADIUS) < 0.002


@pytest.mark.parametrize("source", list(SOURCES))
def test_frame_constants_match_the_data(real_root, source):
    folder, _, module = SOURCES[source]
    s = survey(module.read_raw(real_root / folder), module.AXES)
    fit = s["tilted"] if module.PLANE[0] or module.PLANE[1] else s["level"]
    assert abs(fit["c"] - module.PLANE[2]) < 0.001
    assert abs(fit["a"] - module.PLANE[0]) < 0.001 and abs(fit["b"] - module.PLANE[1]) < 0.001


def test_canonical_axes(real_root):
    for source in SOURCES:
        ds = imported(real_root, source)
        ev = ds.events
        table = ev["kind"] == "table"
        # Bounces lie on the table: x along its length, y across.
        assert np.all(np.abs(ev["x"][table]) < 1.37 + 0.05) and np.all(np.abs(ev["y"][table]) < 0.7625 + 0.05)
        assert np.ptp(ev["x"][table]) > np.ptp(ev["y"][table])
        if source in ("spindoe", "mpi"):
            # Launched balls travel towards +x.
            o = ds.observations
            first = np.r_[0, np.flatnonzero(np.diff(o["session_id"])) + 1]
            assert np.median(o["x"][first + 3] - o["x"][first]) > 0
    # SpinDOE: the ball only drops below the table surface beyond its edges.
    o = imported(real_root, "spindoe").observations
    below = o["z"] < -0.01
    assert below.any()
    assert np.all((np.abs(o["x"][below]) > 1.37) | (np.abs(o["y"][below]) > 0.7625))


def test_spindoe_spin_is_on_the_first_segment_and_rotated(real_root):
    ds = imported(real_root, "spindoe")
    index = spindoe.read_index(real_root / "spindoe" / "index.csv")
    seg = ds.segments
    first = np.r_[True, seg["session_id"][1:] != seg["session_id"][:-1]]
    assert np.all(seg["spin_conf"][first] == 1.0) and np.all(seg["spin_conf"][~first] == 0.0)
    name = ds.sessions["name"][0]
    raw_spin = index[int(name.split("/")[1][:3])]
    k = np.flatnonzero(first)[0]
    got = [seg["spin_x"][k], seg["spin_y"][k], seg["spin_z"][k]]
    np.testing.assert_allclose(got, [-raw_spin[1], raw_spin[0], raw_spin[2]], rtol=0, atol=0.05 * np.linalg.norm(raw_spin))
    assert np.linalg.norm(got) == pytest.approx(np.linalg.norm(raw_spin))


def test_mpi_table_centre_is_the_middle_of_what_the_data_allow(real_root):
    lo, hi = mpi.centre_bounds(mpi.read_raw(real_root / "mpi_ball_prediction"))
    assert 1.0 < lo < hi < 1.9
    assert abs(-mpi.SHIFT_XY[0] - (lo + hi) / 2) < 0.01
