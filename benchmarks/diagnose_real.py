"""``ttsim diagnose`` on the public measured data: SpinDOE, TT3D and the MPI launcher recordings.

For each source in ``--real`` (read at run time; see their SOURCES.md and cite them): imports it
(``ttsim data import --source spindoe|tt3d|mpi``, in memory), diagnoses it with each of
``--models`` (default conti2026; ``--baselines`` adds the paper's baselines nakashima2011 and
durr2026) with the default settings of ``ttsim diagnose`` (``--quick`` for its quick ones), and
writes each report (``report.md``, ``diagnosis.json``, figures) to ``REPORTS/SOURCE/MODEL``
(``--reports``, default ``runs/diagnose_real``), the first model's gap-by-regime figure on the first
source to ``OUT/NAME_SOURCE.png`` and a summary of all of them to ``OUT/NAME.json`` (``--name``,
default ``diagnose_real``): per run the items per phase, the
phases without data, the mean error per phase with its 95 % interval, the flagged regimes, the
significant dependences, the ranked candidates (held-out reduction, interval, significance), the
record's sizes, the verdict, and the wall and CPU time.

    python benchmarks/diagnose_real.py --out benchmarks/results            # conti2026, about 10 min
    python benchmarks/diagnose_real.py --out runs --baselines --quick --name quick   # three models
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):  # run as a script: make ``benchmarks`` importable
    sys.path.insert(0, str(REPO))

from benchmarks.real_flight_rmse import real_root  # noqa: E402

#: Source folder (under --real) and importer name of each public dataset.
SOURCES = {"spindoe": "spindoe", "tt3d": "tt3d", "mpi": "mpi_ball_prediction"}
BASELINES = ("nakashima2011", "durr2026")


def summary(out, counts: dict, wall: float, cpu: float) -> dict:
    """The numbers of one diagnosis that the summary keeps (JSON-able)."""
    where = {p: dict(n=w["n"], groups=w["groups"], mean=w["mean"], ci95=w["ci95"], flagged=w["flagged"])
             for p, w in out.where.items()}
    cands = [dict(name=c["name"], significant=c["significant"],
                  heldout={p: dict(pct=h["pct"], ci95=h["ci95"], before_rms=h["before_rms"], after_rms=h["after_rms"],
                                   n=h["n"]) for p, h in c["heldout"].items()},
                  **({"adds": c["adds"]} if "adds" in c else {})) for c in out.candidates]
    return dict(dataset=counts, items=out.counts, no_data=out.no_data, pooled_sessions=out.pooled_sessions,
                where=where, dependence={p: d[:4] for p, d in out.dependence.items()}, candidates=cands,
                record={k: v for k, v in out.record.items()
                        if k in ("position_noise", "missing_frames", "spin_noise", "spin_check")},
                spin_sources=out.spin_sources or {},
                verdict=out.verdict.text, seconds=wall, cpu_seconds=cpu)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--real", type=Path, default=real_root(), help="folder of the public data (default: %(default)s)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results"), help="output folder (default: %(default)s)")
    p.add_argument("--sources", default=",".join(SOURCES), help="comma-separated (default: %(default)s)")
    p.add_argument("--models", default="conti2026", help="comma-separated bundled models (default: %(default)s)")
    p.add_argument("--baselines", action="store_true", help=f"also diagnose {' and '.join(BASELINES)}")
    p.add_argument("--quick", action="store_true", help="ttsim diagnose --quick's settings")
    p.add_argument("--reports", type=Path, default=Path("runs/diagnose_real"),
                   help="folder of the full reports (default: %(default)s)")
    p.add_argument("--name", default="diagnose_real", help="name of the summary JSON and the figure "
                   "(default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)

    import jax.numpy as jnp
    from tqdm import tqdm

    from ttsim_jax import load_model
    from ttsim_jax.data.importers import import_source
    from ttsim_jax.diagnose.diagnosis import Settings, diagnose, work_units
    from ttsim_jax.results import jsonable
    from ttsim_jax.diagnose.report import FIGURES, write_report

    sources = [s.strip() for s in args.sources.split(",") if s.strip()]
    unknown = [s for s in sources if s not in SOURCES]
    if unknown:
        p.error(f"--sources: unknown {unknown}; choose among {list(SOURCES)}")
    missing = [str(args.real / SOURCES[s]) for s in sources if not (args.real / SOURCES[s]).is_dir()]
    if missing:
        p.error(f"--real: missing {', '.join(missing)}")
    models = [m.strip() for m in args.models.split(",") if m.strip()] + (list(BASELINES) if args.baselines else [])
    settings = Settings.quick() if args.quick else Settings()
    reports = args.reports
    result = dict(settings=jsonable(dict(quick=args.quick, steps=settings.steps, max_segments=settings.max_segments,
                                         test_fraction=settings.test_fraction, seed=settings.seed)), runs={})
    args.out.mkdir(parents=True, exist_ok=True)
    t_start, c_start = time.perf_counter(), time.process_time()
    with tqdm(total=len(sources) * len(models) * work_units(settings), unit="step", disable=args.quiet) as bar:
        for source in sources:
            bar.set_description(f"import {source}")
            ds = import_source(args.real / SOURCES[source], source)
            counts = dict(sessions=len(ds.sessions["session_id"]), segments=len(ds.segments["segment_id"]),
                          table_bounces=int(sum(k == "table" for k in ds.events["kind"])),
                          racket_states=len(ds.rackets["event_id"]))
            for name in models:
                bar.set_description(f"{source}, {name}")

                def tick(what, n=1):
                    bar.set_postfix_str(what)
                    bar.update(n)

                t0, c0 = time.perf_counter(), time.process_time()
                out = diagnose(ds, load_model(name, dtype=jnp.float32), settings, progress=tick)
                wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                folder = reports / source / name
                if folder.exists():
                    shutil.rmtree(folder)
                write_report(out, folder, data=f"{source} ({args.real / SOURCES[source]})", model=name)
                result["runs"].setdefault(source, {})[name] = summary(out, counts, wall, cpu)
    result.update(seconds=time.perf_counter() - t_start, cpu_seconds=time.process_time() - c_start)
    path = args.out / f"{args.name}.json"
    path.write_text(json.dumps(jsonable(result), indent=1))
    shutil.copy(reports / sources[0] / models[0] / FIGURES["where"], args.out / f"{args.name}_{sources[0]}.png")
    for source, runs in result["runs"].items():
        for name, r in runs.items():
            print(f"{source}, {name}: {r['verdict']} ({r['seconds']:.0f} s wall, {r['cpu_seconds']:.0f} s CPU)")
    print(f"written: {path} and the reports under {reports}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
