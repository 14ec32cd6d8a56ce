"""The ``ttsim data ...`` commands (``import``, ``info``, ``upgrade``). Thin: parsing and printing
only; the work is in :mod:`ttsim_jax.data`."""

from __future__ import annotations

import argparse
import json
import warnings

from ttsim_jax.cli.options import (UsageError, existing_dir, existing_path, finite_float, model_name_or_file,
                                   positive_float, writable_dir)


def _dataset_to_rewrite(text: str):
    """A dataset directory that exists and can be replaced (its parent takes a temporary sibling)."""
    return writable_dir(str(existing_dir(text)))


def register(subparsers) -> argparse.ArgumentParser:
    """Adds ``data import``, ``data info`` and ``data upgrade`` to an argparse subparsers object.

    Arguments:
        subparsers: what ``ArgumentParser.add_subparsers()`` returned.

    Returns:
        The ``data`` parser.
    """
    from ttsim_jax.data.csvlog import LENGTH_UNITS, TIME_UNITS
    from ttsim_jax.data.importers import SOURCES

    data = subparsers.add_parser("data", help="measured data: import public datasets, inspect datasets", description="Measured-data commands.")
    sub = data.add_subparsers(dest="data_command", metavar="COMMAND")
    sub.required = True

    imp = sub.add_parser(
        "import",
        help="convert a public dataset (or a CSV log) into the canonical format",
        description="Read PATH, convert it to the canonical table frame, detect contacts, segment, validate and "
        "write a dataset directory (Parquet tables + metadata.json). Sessions are split where the tracker did not "
        "follow one ball (pauses longer than 0.25 s, missing frames or jumps that no flight bridges); the import "
        "prints what it found per session and warns about segments that no ballistic flight fits.",
    )
    imp.add_argument("path", metavar="PATH", type=existing_path, help="the source's folder (e.g. shared/data/real/spindoe) or one of its files")
    imp.add_argument("--source", required=True, choices=SOURCES, help="which importer reads PATH: spindoe, tt3d, mpi (flight recordings), tt_rackets (racket "
                     "bounces with measured states, one racket configuration per file) or csv (a tracker's log)")
    imp.add_argument("--out", required=True, metavar="DIR", type=writable_dir, help="dataset directory to write")
    imp.add_argument("--force", action="store_true", help="replace DIR if it holds a dataset (other files in it are kept)")
    imp.add_argument("--length-unit", choices=tuple(LENGTH_UNITS), default="m", help="with --source csv: unit of the positions (default m)")
    imp.add_argument("--time-unit", choices=tuple(TIME_UNITS), default="s", help="with --source csv: unit of the times (default s)")
    imp.add_argument("--filter", action="store_true", help="also drop short, low-spin-confidence and badly fitting segments (prints a report)")
    imp.add_argument("--min-spin-conf", type=finite_float, default=0.5, metavar="C", help="with --filter: least spin confidence, negative to keep all (default 0.5)")
    imp.add_argument("--max-rmse", type=positive_float, default=0.02, metavar="M", help="with --filter: largest flight-fit RMSE in metres (default 0.02)")
    imp.set_defaults(func=cmd_import)

    inf = sub.add_parser(
        "info",
        help="counts, ranges and validation summary of a dataset",
        description="Print counts of sessions, segments and events by kind, speed and spin ranges, whether the files "
        "carry page checksums (protected against silent damage), and the validation summary with its warnings.",
    )
    inf.add_argument("path", metavar="DIR", type=existing_dir, help="dataset directory")
    inf.add_argument("--json", action="store_true", help="print the summary as JSON")
    inf.add_argument("--spin-check", nargs="?", const="conti2026", default=None, metavar="MODEL",
                     type=model_name_or_file,
                     help="also check the measured spins against the spins the flights show, under MODEL (default "
                     "conti2026): the share bent opposite to their measured spin, an axis rotation and a scale, with "
                     "95 %% intervals, over the segments with a spin confidence >= 0.5 and at least 8 samples "
                     "(fits every such segment: seconds to minutes)")
    inf.set_defaults(func=cmd_info)

    upg = sub.add_parser(
        "upgrade",
        help="rewrite a dataset in the current schema version, with page checksums",
        description="Rewrite dataset DIR (in place, or as a copy with --out) in the current schema version: Parquet "
        "page checksums (so that a damaged file is refused on load) and a new dataset id in every file; every value "
        "and every other file is kept. Each file is read back and compared before the new directory replaces the old "
        "one in one step, so a failure leaves the original as it was.",
    )
    upg.add_argument("path", metavar="DIR", type=_dataset_to_rewrite, help="dataset directory")
    upg.add_argument("--out", metavar="OUT", type=writable_dir, help="write the upgraded copy here and leave DIR as it is")
    upg.add_argument("--force", action="store_true", help="with --out: replace a dataset already in OUT")
    upg.set_defaults(func=cmd_upgrade)
    return data


def cmd_import(args) -> int:
    """``data import``: import, optionally filter, save, and print a summary."""
    from ttsim_jax.data.errors import DataWarning
    from ttsim_jax.data.importers import import_source
    from ttsim_jax.data.io import parquet_files, save, unprotected_files
    from ttsim_jax.data.summary import format_info, info
    from ttsim_jax.data.tracks import tracking_report
    from ttsim_jax.fit.flightfit import ballistic_rmse_many
    from ttsim_jax.fit.segment_filter import filter_segments

    if args.out.exists() and not args.force and (not args.out.is_dir() or any(args.out.iterdir())):
        raise UsageError(f"--out {args.out}: exists and is not empty; pass --force to replace it")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataWarning)
        try:
            ds = import_source(args.path, args.source, length_unit=args.length_unit, time_unit=args.time_unit)
        except UnicodeDecodeError as e:
            raise UsageError(f"{args.path}: not a {args.source} recording (a file is not UTF-8 text: {e})") from None
    doubts = [w.message for w in caught if isinstance(w.message, DataWarning)]
    for w in caught:
        if not isinstance(w.message, DataWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    if len(ds.observations["t"]):  # a rig's contact states (tt_rackets) hold no flights to check
        print("fitting a flight to every segment to check it ...", flush=True)
        print(tracking_report(ds, rmse_many=ballistic_rmse_many))
    if args.filter:
        conf = None if args.min_spin_conf < 0 else args.min_spin_conf
        ds, report = filter_segments(ds, min_spin_conf=conf, max_rmse=args.max_rmse)
        print(report)
    if not len(ds.segments["segment_id"]) and not len(ds.events["kind"]):
        raise UsageError(f"{args.path}: nothing to write: no flight segment (a segment needs 5 samples or more of "
                         f"one tracked flight) and no contact among its {len(ds.observations['t'])} observations"
                         + (" after --filter" if args.filter else ""))
    save(ds, args.out, overwrite=args.force)
    print(f"wrote {args.out}")
    print(format_info(info(ds, warnings=doubts, unprotected=(unprotected_files(args.out), len(parquet_files(args.out))))))
    return 0


def cmd_info(args) -> int:
    """``data info``: load without stopping at problems, then summarise them."""
    from ttsim_jax.data.errors import DataWarning
    from ttsim_jax.data.io import METADATA_FILE, load, parquet_files, table_path, unprotected_files, verify_files
    from ttsim_jax.data.schema import TABLES
    from ttsim_jax.data.summary import format_info, info
    from ttsim_jax.data.validate import borderline, problems

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)  # reported below, with the rest
        ds = load(args.path, validate=False)
    verify_files(args.path)  # the files load leaves to their readers too (a generator's truth)
    files = {name: table_path(args.path, name) for name in TABLES}
    files["metadata"] = f"{args.path}/{METADATA_FILE}"
    found = problems(ds, files)
    doubts = [] if found else borderline(ds, files)
    d = info(ds, found, doubts, (unprotected_files(args.path), len(parquet_files(args.path))))
    if args.spin_check and not found:
        d["spin_check"] = _spin_check(ds, args.spin_check)
    text = format_info(d)
    if "spin_check" in d:
        sc = d["spin_check"]
        text += "\nspin check:    " + (sc["skipped"] if "skipped" in sc else sc["summary"])
    print(json.dumps(d, indent=2) if args.json else text)
    return 1 if found else 0


def _spin_check(ds, model_name: str) -> dict:
    """``--spin-check``: :func:`ttsim_jax.fit.spin_check.check_record_spin` over the segments with a
    confident measured spin."""
    import sys

    import numpy as np

    from ttsim_jax.fit.segment_batches import dataset_segments
    from ttsim_jax.fit.choices import LATENT_MIN_SAMPLES
    from ttsim_jax.fit.spin_check import check_record_spin
    from ttsim_jax.params import load_model

    ids, times, positions, spins, conf = dataset_segments(ds, LATENT_MIN_SAMPLES)
    rows = np.flatnonzero(conf >= 0.5)
    if len(rows) < 3:
        return dict(skipped=f"{len(rows)} segments with a measured spin (confidence >= 0.5) and at least "
                    f"{LATENT_MIN_SAMPLES} samples: nothing to check")
    print(f"spin check: fitting the latent spin of {len(rows)} segments under {model_name} (compiling ...)",
          file=sys.stderr)
    return check_record_spin(load_model(model_name), [times[i] for i in rows],
                             [positions[i] for i in rows], spins[rows])


def cmd_upgrade(args) -> int:
    """``data upgrade``: rewrite a dataset with page checksums in the current schema version."""
    from ttsim_jax.data.io import parquet_files, read_metadata, unprotected_files, unsummed_files, upgrade
    from ttsim_jax.data.schema import SCHEMA_VERSION

    before = read_metadata(args.path).schema_version
    bare = unprotected_files(args.path)
    n = len(parquet_files(args.path))
    unsummed = unsummed_files(args.path)
    if args.out is None and not bare and not unsummed and before == SCHEMA_VERSION:
        print(f"{args.path}: already schema {SCHEMA_VERSION} with page checksums in all {n} Parquet files and every "
              "file's SHA-256 recorded; nothing to do")
        return 0
    if args.out is not None and args.out.exists() and not args.force:
        raise UsageError(f"--out {args.out}: exists; add --force to replace the dataset there (other files in it are kept)")
    try:
        out = upgrade(args.path, args.out, overwrite=args.force)
    except (FileExistsError, NotADirectoryError) as e:
        if args.out is None:
            raise
        raise UsageError(f"--out: {e}") from None
    print(f"wrote {out}: schema {before} -> {SCHEMA_VERSION}, page checksums in all {n} Parquet files "
          f"({len(bare)} had none), every file's SHA-256 recorded ({len(unsummed)} were not), a new dataset id; "
          "every value kept (each file read back and compared)")
    return 0
