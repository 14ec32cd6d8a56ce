"""Counts and ranges of a dataset, for ``ttsim data info``."""

from __future__ import annotations

import numpy as np

from . import racket_configs, schema
from .dataset import Dataset
from .speeds import step_speeds


def _speeds(ds: Dataset) -> np.ndarray:
    """Speeds between consecutive samples of the same segment [m/s]
    (:func:`~ttsim_jax.data.speeds.step_speeds`)."""
    rows, speed = step_speeds(ds)
    seg = np.asarray(ds.observations["segment_id"])
    return speed[(seg[rows + 1] == seg[rows]) & (seg[rows] >= 0)]


def info(ds: Dataset, problems=None, warnings=None, unprotected=None) -> dict:
    """Summary of ``ds``.

    Arguments:
        ds: the dataset.
        problems: optional list of validation problems to report.
        warnings: optional list of borderline values to report
            (:func:`ttsim_jax.data.validate.borderline`).
        unprotected: optional (files without page checksums, Parquet files in all) of the
            dataset's directory (:func:`ttsim_jax.data.io.unprotected_files`); None: not known.

    Returns:
        dict with counts (sessions, observations, segments, events by kind, racket states),
        speed percentiles [m/s], spin magnitude range over segments with spin [rad/s], time span,
        whether the files are protected by checksums, and the validation summary.
    """
    seg = ds.segments
    kinds = {k: int(np.sum(ds.events["kind"] == k)) for k in schema.EVENT_KINDS}
    speeds = _speeds(ds)
    spin = np.stack([seg["spin_x"], seg["spin_y"], seg["spin_z"]], -1)
    has_spin = seg["spin_conf"] > 0
    mags = np.linalg.norm(spin[has_spin], axis=-1)
    pct = lambda a, q: [float(v) for v in np.percentile(a, q)] if len(a) else []  # noqa: E731
    return {
        "source": ds.metadata.source,
        "schema_version": ds.metadata.schema_version,
        "frame": ds.metadata.frame,
        "sessions": len(ds.sessions["session_id"]),
        "observations": len(ds.observations["t"]),
        "segments": len(seg["segment_id"]),
        "segments_with_spin": int(has_spin.sum()),
        "events": kinds,
        "racket_states": len(ds.rackets["event_id"]),
        "contact_states": len(ds.contact_states["event_id"]),
        "racket_configs": racket_configs.summary(ds),
        "speed_p1_p50_p99": pct(speeds, [1, 50, 99]),
        "spin_min_median_max": [float(mags.min()), float(np.median(mags)), float(mags.max())] if len(mags) else [],
        "checksums": None if unprotected is None else {"protected": not unprotected[0],
                                                        "unprotected_files": [str(f) for f in unprotected[0]],
                                                        "parquet_files": int(unprotected[1])},
        "left_out": dict(ds.metadata.left_out),
        "problems": [str(p) for p in (problems or [])],
        "warnings": [str(w) for w in (warnings or [])],
    }


def format_info(d: dict) -> str:
    """Human-readable text of :func:`info`'s dict."""
    ev = ", ".join(f"{k} {n}" for k, n in d["events"].items())
    lines = [
        f"source:        {d['source']}",
        f"schema:        {d['schema_version']}, frame {d['frame']}",
        f"sessions:      {d['sessions']}",
        f"observations:  {d['observations']}",
        f"segments:      {d['segments']} ({d['segments_with_spin']} with spin)",
        f"events:        {ev}",
        f"racket states: {d['racket_states']}",
    ]
    if d.get("contact_states"):
        lines.append(f"contact states: {d['contact_states']} measured directly (not estimated from observations)")
    for name, c in d.get("racket_configs", {}).items():
        tilts = ", ".join(f"{t} deg {n}" for t, n in c["tilts_deg"].items())
        what = ", ".join(str(c[k]) + (" mm" if k == "sponge_mm" else "") for k in ("blade", "sponge_mm", "rubber", "rubber_type")
                         if k in c)
        lines.append(f"  racket {name}: {c['n']} contacts" + (f" (tilt {tilts})" if tilts else "") + (f"; {what}" if what else ""))
    if d["speed_p1_p50_p99"]:
        lo, mid, hi = d["speed_p1_p50_p99"]
        lines.append(f"speed [m/s]:   {lo:.2f} .. {hi:.2f} (1st..99th percentile), median {mid:.2f}")
    if d["spin_min_median_max"]:
        lo, mid, hi = d["spin_min_median_max"]
        lines.append(f"spin [rad/s]:  {lo:.0f} .. {hi:.0f}, median {mid:.0f}")
    c = d.get("checksums")
    if c is not None:
        n_bare = len(c["unprotected_files"])
        lines.append("checksums:     " + (f"every page of the {c['parquet_files']} Parquet files (protected: a damaged file is "
                                          "refused on load)" if c["protected"] else
                                          f"none in {n_bare} of {c['parquet_files']} Parquet files (not protected: damage "
                                          "loads unnoticed; add them with 'ttsim data upgrade DIR')"))
    if d.get("left_out"):
        lines.append("left out:      " + "; ".join(f"{n} {what}" for what, n in d["left_out"].items()) + " (at import)")
    lines.append("validation:    " + ("ok" if not d["problems"] else f"{len(d['problems'])} problem(s)")
                 + (f", {len(d['warnings'])} warning(s)" if d.get("warnings") else ""))
    lines += [f"  - {p}" for p in d["problems"]]
    lines += [f"  - warning: {w}" for w in d.get("warnings", [])]
    return "\n".join(lines)
