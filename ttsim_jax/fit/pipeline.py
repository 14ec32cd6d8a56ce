"""System identification of one or several datasets, stage by stage (what ``ttsim fit`` runs).

::

    from ttsim_jax.fit.pipeline import FitSettings, fit_dataset, write_fit

    result = fit_dataset(["data/spindoe", "data/tt3d", "data/mpi"], settings=FitSettings(test_fraction=0.3))
    print(result.summary())
    write_fit(result, "runs/public.toml")          # runs/public.toml + runs/public.fit.json

Stages (:data:`STAGES`; :mod:`ttsim_jax.fit.identify`, :mod:`~ttsim_jax.fit.table`,
:mod:`~ttsim_jax.fit.racket`, :mod:`~ttsim_jax.fit.network_training` do the work):

- ``aero``: C_D and C_M of each flight segment, regressed into the base model's forms
  (``settings.forms``): C_D from the segments with a measured spin and, at their latent spin,
  from those without; C_M from the measured spins only.
- ``table``: e0, e1 (held within the physical range, see :func:`ttsim_jax.fit.table.fit_table`)
  and the residual matrices, from bounces with a measured spin on both sides.
- ``racket``: the updated racket base model, from racket contacts with a racket state.
- ``residual``: the racket residual network on what the fitted racket model leaves.

Which stages run: with ``stages=None`` the defaults (:data:`DEFAULT_STAGES`) that the data can
support; a stage it cannot is skipped with the reason (:func:`stage_problems` finds the reasons
that need no work; a stage that finds too few usable items after its work is skipped too). A
stage named in ``stages`` that the data cannot support is refused before any work
(:class:`FitError`). A stage that raises stops the fit with :class:`StageFailed`, whose
``partial`` holds what the stages before it fitted, ready for :func:`write_fit`.

Several datasets are merged (:func:`ttsim_jax.data.merge.merge_datasets`); the held-out sessions
(``settings.test_fraction``) are drawn per dataset with the same seed, so they are the sessions
``ttsim evaluate --split test --test-fraction F --seed S`` takes on each dataset alone.

Each fitted stage is compared with the base model on the held-out sessions (on the training
data where none are held out): flight RMSE (median, 75th percentile), table and racket contact
errors by component; the components where the fitted model is worse are listed
(``FitResult.worse``). With several datasets the flight comparison is made on each dataset too
(``comparison["aero on LABEL"]``): a fit pooled over labs can serve one at another's cost, as
SpinDOE's C_D table does the MPI launcher's balls (``docs/measurements/fitting.md``).

:func:`write_fit` writes the model config and the JSON summary as one unit: the summary holds the
config's text (``model_toml``) and is written first, the config last, each atomically.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ttsim_jax.fit.choices import (DEFAULT_FORMS, DEFAULT_STAGES, FORMS, LATENT_MIN_SAMPLES, SPIN_SOURCES,  # noqa: F401
                                   STAGES)  # (re-exported)
from ttsim_jax.errors import UserError
from ttsim_jax.fit.comparison import comparison, comparison_text, flight_comparisons
from ttsim_jax.files.toml import signed

_TABLE_COMPONENTS = {"v_x": "m/s", "v_y": "m/s", "v_z": "m/s", "w_x": "rad/s", "w_y": "rad/s", "w_z": "rad/s"}


def bundled_config(model: str) -> Path:
    """The bundled residual network config of a model family (``configs/residual/MODEL.toml``)."""
    from ttsim_jax.bundled import config_dir

    return config_dir() / "residual" / f"{model}.toml"


class FitError(UserError, ValueError):
    """The data cannot support what was asked (a requested stage, or any stage at all).

    Attributes:
        problems: stage -> reason, for requested stages the data cannot support (empty otherwise).
    """

    def __init__(self, message: str, problems: dict | None = None):
        super().__init__(message)
        self.problems = dict(problems or {})


class StageFailed(RuntimeError):
    """A stage raised. ``stage`` names it, ``cause`` is what it raised, ``partial`` the
    :class:`FitResult` of the stages fitted before it (``partial.fitted`` may be empty)."""

    def __init__(self, stage: str, cause: BaseException, partial: "FitResult"):
        super().__init__(f"stage {stage} failed: {cause}")
        self.stage, self.cause, self.partial = stage, cause, partial


class _Skip(Exception):
    """Raised inside a stage whose data turns out too thin after its work."""


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """How the stages select, fit and hold out data.

    Attributes:
        association: aero: ``"averaged"`` or ``"v_eff"`` (:mod:`ttsim_jax.fit.aero_forms`).
        forms: aero: the forms fitted (of ``"drag"``, ``"magnus"``); the other keeps the base's.
        min_spin_conf: least spin confidence of a segment (aero) or of both sides of a contact.
        max_rmse: aero: segments whose constant-coefficient fit has a larger RMSE are dropped [m].
        folds, lambda_rule: table: K of the cross-validation and the penalty rule (``1se``, ``min``).
        epochs: residual: most epochs (None: the bundled config's).
        test_fraction: fraction of each dataset's sessions held out of every stage.
        seed: seed of the held-out draw and of the cross-validation folds.
        spin: the spin of the flight segments the fitted and the base model are compared on
            (:func:`ttsim_jax.fit.flight.segment_rmse`'s ``spin``; default ``"auto"``: the measured
            spin where there is one, each model's latent spin elsewhere). The aero stage's C_D
            takes the latent spin of the segments without a measured one too with ``"auto"`` and
            ``"latent"`` (:func:`ttsim_jax.fit.identify.identify_aero`'s ``spin="auto"``), and
            leaves them out with ``"measured"`` and ``"zero"``; its C_M comes from measured spins
            only, whatever this says.
    """

    association: str = "averaged"
    forms: tuple = DEFAULT_FORMS
    min_spin_conf: float = 0.5
    max_rmse: float = 0.02
    folds: int = 5
    lambda_rule: str = "1se"
    epochs: int | None = None
    test_fraction: float = 0.0
    seed: int = 0
    spin: str = "auto"

    def __post_init__(self):
        if self.spin not in SPIN_SOURCES:
            raise ValueError(f"FitSettings.spin = {self.spin!r}: expected one of {SPIN_SOURCES}")
        bad = [f for f in self.forms if f not in FORMS]
        if bad or not self.forms:
            raise ValueError(f"FitSettings.forms = {self.forms!r}: expected some of {FORMS}")
        if not 0.0 <= self.test_fraction < 1.0:
            raise ValueError(f"FitSettings.test_fraction = {self.test_fraction!r}: expected a fraction in [0, 1)")


@dataclasses.dataclass
class FitResult:
    """What :func:`fit_dataset` identified.

    Attributes:
        model: the base model with every fitted stage's parameters (a :class:`~ttsim_jax.params.Model`).
        toml: the model config's text (what :func:`write_fit` writes).
        report: the JSON summary: settings, per stage counts, fitted values and standard errors,
            the comparison with the base model, wall and CPU time; ``fitted``, ``skipped``
            (stage -> reason), ``failed`` (stage and error, or None) and ``partial`` (a stage failed).
        network: the trained residual network (``residual`` stage) or None; network_info: its
            training summary.
    """

    model: object
    toml: str
    report: dict
    network: object = None
    network_info: dict | None = None

    @property
    def fitted(self) -> list:
        return list(self.report["fitted"])

    @property
    def skipped(self) -> dict:
        return dict(self.report["skipped"])

    @property
    def worse(self) -> dict:
        """stage -> components where the fitted model is worse than the base (only such stages)."""
        return {s: c["worse"] for s, c in self.report["comparison"].items() if c.get("worse")}

    def summary(self) -> str:
        """A few lines: what was fitted, skipped, failed, and where the fit is worse than the base."""
        r = self.report
        lines = [f"fitted: {', '.join(r['fitted']) or 'nothing'}"]
        lines += [f"skipped {s}: {why}" for s, why in r["skipped"].items()]
        if r["failed"]:
            lines.append(f"failed {r['failed']['stage']}: {r['failed']['error']}")
        lines += [comparison_text(s, c) for s, c in r["comparison"].items()]
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------- data
def load_datasets(data) -> tuple[list, list[str]]:
    """(datasets, labels) from a :class:`~ttsim_jax.data.Dataset`, a directory, or a list of them.

    A directory is loaded (and validated) and labelled with its path; a Dataset is labelled with
    its position in the list."""
    from ttsim_jax.data import Dataset, load

    items = [data] if isinstance(data, (Dataset, str, os.PathLike)) else list(data)
    if not items:
        raise FitError("no dataset given")
    datasets, labels = [], []
    for k, item in enumerate(items):
        datasets.append(item if isinstance(item, Dataset) else load(item))
        labels.append(str(k) if isinstance(item, Dataset) else os.fspath(item))
    return datasets, labels


def held_out_parts(datasets: Sequence, test_fraction: float, seed: int) -> list:
    """Per dataset, its held-out sessions (a ``test_fraction`` of its sessions with flight segments,
    drawn with ``seed`` as :func:`ttsim_jax.fit.identify.split_sessions` draws them on that dataset
    alone), or all its sessions where ``test_fraction`` is 0, in the ids of
    :func:`ttsim_jax.data.merge.merge_datasets`."""
    from ttsim_jax.data.merge import id_offsets
    from ttsim_jax.fit.identify import split_sessions

    return [(split_sessions(ds.segments["session_id"], test_fraction, seed) if test_fraction > 0 else
             np.unique(np.asarray(ds.segments["session_id"]))).astype(np.int64) + off["session_id"]
            for ds, off in zip(datasets, id_offsets(datasets))]


def held_out_sessions(datasets: Sequence, test_fraction: float, seed: int) -> np.ndarray:
    """The held-out sessions of the merged datasets (:func:`held_out_parts`, together)."""
    if test_fraction <= 0:
        return np.zeros(0, np.int64)
    parts = held_out_parts(datasets, test_fraction, seed)
    return np.sort(np.concatenate(parts)).astype(np.int64) if parts else np.zeros(0, np.int64)


def stage_problems(ds, stages: Sequence[str], min_spin_conf: float = 0.5, min_samples: int = 5,
                   spin: str = "auto") -> dict:
    """Why ``ds`` cannot support some of ``stages``, found without fitting anything. ``spin``:
    :attr:`FitSettings.spin` (with ``"auto"`` or ``"latent"`` the aero stage fits C_D from
    segments without a measured spin too, at their latent spin; C_M then stays the base's).

    Returns:
        stage -> reason (one line), for the stages the data cannot support.
    """
    out = {}
    seg, ev = ds.segments, ds.events
    if "aero" in stages:
        counts = dict(zip(*np.unique(ds.observations["segment_id"], return_counts=True)))
        latent = spin in ("auto", "latent")
        need = LATENT_MIN_SAMPLES if latent else min_samples
        long = np.array([counts.get(int(s), 0) >= need for s in seg["segment_id"]], bool)
        if latent and not long.any():
            out["aero"] = (f"no flight segment with at least {need} observations, which a latent spin needs "
                           f"({len(long)} segments)")
        elif not latent and not np.any(long & (np.asarray(seg["spin_conf"]) >= min_spin_conf)):
            out["aero"] = (f"no flight segment with a measured spin (confidence >= {min_spin_conf:g}) and at least "
                           f"{min_samples} observations ({len(long)} segments); --spin auto fits C_D at the "
                           "segments' latent spins")
    if "table" in stages:
        table = np.asarray(ev["event_id"])[np.asarray(ev["kind"]).astype(str) == "table"]
        spun = np.asarray(seg["spin_conf"]) >= min_spin_conf
        ends = set(np.asarray(seg["end_event_id"])[spun].tolist())
        starts = set(np.asarray(seg["start_event_id"])[spun].tolist())
        if len(table) == 0:
            out["table"] = "no table bounces (no event of kind 'table')"
        elif not any(int(e) in ends and int(e) in starts for e in table):
            out["table"] = (f"none of its {len(table)} table bounces has a measured spin (confidence >= "
                            f"{min_spin_conf:g}) both before and after it, which the table fit needs")
    for stage in ("racket", "residual"):
        if stage in stages and len(ds.rackets["event_id"]) == 0:
            out[stage] = "no racket contacts with a racket state (the rackets table is empty)"
    return out


# ---------------------------------------------------------------------------------------------- stages
def _counts(total: int, used: int, skipped: dict, held_out: int) -> dict:
    return dict(total=total, used=used, held_out=held_out, skipped={k: len(v) for k, v in skipped.items() if v})


class _Run:
    """The state the stages pass on: the model so far, the config sections, the report."""

    def __init__(self, ds, base_path, settings, test_sessions, progress, log, parts=None):
        from ttsim_jax.params import load_model

        self.ds, self.base_path, self.settings, self.test = ds, base_path, settings, test_sessions
        self.parts = parts or {}
        self.base = load_model(base_path)
        self.model = self.base
        self.sections: dict = {}
        self.progress, self.log = progress, log
        self.report: dict = {}
        self.comparison: dict = {}
        self.network = self.network_info = None

    def tick(self, stage):
        return None if self.progress is None else (lambda done, total: self.progress(stage, done, total))

    def model_text(self, name: str, source: str) -> str:
        from ttsim_jax.fit.aero_forms import config_text

        return config_text(self.base_path, self.sections, name=name, source=source)

    def aero(self):
        from ttsim_jax.fit.aero_forms import aero_sections
        from ttsim_jax.fit.identify import identify_aero

        s = self.settings
        result = identify_aero(self.ds, self.base_path, association=s.association, min_spin_conf=s.min_spin_conf,
                               max_rmse=s.max_rmse, test_fraction=s.test_fraction, seed=s.seed, forms=tuple(s.forms),
                               spin="auto" if s.spin in ("auto", "latent") else "measured",
                               progress=self.tick("aero"), test_sessions=self.test)
        self.log(result.summary())
        if result.drag is None:
            spun = "" if s.spin in ("auto", "latent") else f" with a measured spin (confidence >= {s.min_spin_conf:g})"
            raise _Skip(f"no segment{spun} fits within {1e3 * s.max_rmse:g} mm ({result.counts['fitted']} fitted, "
                        f"{result.counts['held_out']} held out)")
        self.sections.update(aero_sections(self.base_path, result.drag.values["cd"], result.magnus.values))
        self.report["aero"] = result.to_dict()
        self.model = self.model.replace(aero=_model_of(self.model_text("fitting", "")).aero)
        held = len(self.test) > 0
        self.comparison.update(flight_comparisons(self.ds, self.base, self.model, self.test if held else None, held,
                                                   s, self.parts))

    def table(self):
        from ttsim_jax.fit import table as table_fit
        from ttsim_jax.data.contact_states import ContactFit
        from ttsim_jax.kernel.ball_step import ball_properties

        s, ds = self.settings, self.ds
        bounces = table_fit.table_bounces(ds, self.model, fit=ContactFit(min_spin_conf=s.min_spin_conf),
                                          validate=False, progress=self.tick("table"))
        session = dict(zip(np.asarray(ds.events["event_id"]).tolist(), np.asarray(ds.events["session_id"]).tolist()))
        kept = ~np.isin([session[int(e)] for e in bounces.event_id], self.test)
        counts = _counts(bounces.n_bounces, int(kept.sum()), bounces.skipped, int((~kept).sum()))
        if kept.sum() < 2 * s.folds:
            raise _Skip(f"{int(kept.sum())} usable table bounces ({bounces.n_bounces} table events; skipped: "
                        f"{counts['skipped'] or 'none'}; {counts['held_out']} held out); at least {2 * s.folds} are "
                        f"needed for {s.folds}-fold cross-validation")
        fit = table_fit.fit_table(bounces.vel_in[kept], bounces.spin_in[kept], bounces.vel_out[kept],
                                  bounces.spin_out[kept], self.model,
                                  table_fit.LassoSettings(folds=s.folds, rule=s.lambda_rule, seed=s.seed))
        counts["bounded"] = fit.n_bounded
        self.log(f"table: {counts['used']} of {counts['total']} bounces used; skipped {counts['skipped']}, "
                 f"{counts['held_out']} held out\n" + fit.summary())
        self.sections.update(table_fit.table_sections(self.model.table, fit))
        self.report["table"] = dict(counts=counts, fit=fit.to_dict())
        fitted = fit.params(self.model.table)
        if (~kept).any():
            radius = ball_properties(self.model)[0]
            rows = [a[~kept] for a in (bounces.vel_in, bounces.spin_in, bounces.vel_out, bounces.spin_out)]
            self.comparison["table"] = comparison("held_out", (~kept).sum(),
                                                   table_fit.bounce_errors(self.base.table, radius, *rows),
                                                   table_fit.bounce_errors(fitted, radius, *rows), _TABLE_COMPONENTS)
        else:
            self.comparison["table"] = comparison("training", fit.n_used, fit.errors["base"], fit.errors["fitted"],
                                                   _TABLE_COMPONENTS)
        self.model = self.model.replace(table=fitted)

    def _contacts(self):
        from ttsim_jax.data.contact_states import ContactFit
        from ttsim_jax.fit.racket_arrays import contact_arrays

        arrays = contact_arrays(self.ds, self.model, n_inputs=8, fit=ContactFit(min_spin_conf=self.settings.min_spin_conf),
                                validate=False)
        return arrays, ~np.isin(arrays.session_id, self.test)

    def racket(self):
        from ttsim_jax.fit import racket as racket_fit
        from ttsim_jax.kernel.ball_step import ball_properties

        arrays, kept = self._contacts()
        counts = _counts(arrays.n_contacts, int(kept.sum()), arrays.skipped, int((~kept).sum()))
        if kept.sum() < 2 * len(racket_fit.PARAMETERS):
            raise _Skip(f"{int(kept.sum())} usable racket contacts ({arrays.n_contacts} racket events; skipped: "
                        f"{counts['skipped'] or 'none'}; {counts['held_out']} held out); at least "
                        f"{2 * len(racket_fit.PARAMETERS)} are needed")
        fit = racket_fit.fit_racket(arrays.x[kept], arrays.y_obs[kept], self.model)
        tick = self.tick("racket")
        if tick is not None:
            tick(1, 1)
        self.log(f"racket: {counts['used']} of {counts['total']} contacts used; skipped {counts['skipped']}, "
                 f"{counts['held_out']} held out\n" + fit.summary())
        self.sections.update(racket_fit.racket_section(self.model.racket, fit))
        self.report["racket"] = dict(counts=counts, fit=fit.to_dict())
        fitted = fit.params(self.model.racket)
        units = dict(velocity="m/s", spin="rad/s")
        if (~kept).any():
            radius, mass = ball_properties(self.model)
            x, y = arrays.x[~kept], arrays.y_obs[~kept]
            self.comparison["racket"] = comparison("held_out", len(x),
                                                    racket_fit.racket_errors(self.base.racket, x, y, radius, mass),
                                                    racket_fit.racket_errors(fitted, x, y, radius, mass), units)
        else:
            self.comparison["racket"] = comparison("training", fit.n_used, fit.errors["base"], fit.errors["fitted"],
                                                    units)
        self.model = self.model.replace(racket=fitted)

    def residual(self):
        from ttsim_jax.fit.network_config import load_train_config
        from ttsim_jax.fit.network_training import split_by_contact, train_residual

        arrays, rows = self._contacts()  # y_base of the fitted racket parameters
        config, tcfg = load_train_config(bundled_config("conti2026"))
        if self.settings.epochs is not None:
            tcfg = dataclasses.replace(tcfg, max_epochs=self.settings.epochs)
        x, yb, yo = arrays.x[rows], arrays.y_base[rows], arrays.y_obs[rows]
        if len(x) < 3:
            raise _Skip(f"{len(x)} usable racket contacts; at least 3 are needed (train / validation / test)")
        n_train = len(split_by_contact(len(x), tcfg.split, tcfg.seed)[0])
        config = dataclasses.replace(config, n_clusters=min(config.n_clusters, n_train))
        net, report = train_residual(x, yb, yo, config, tcfg, progress=self.progress is not None)
        info = {k: v for k, v in report.items() if k != "history"}
        info.update(train_config=tcfg.to_dict(),
                    contacts=dict(used=len(x), total=arrays.n_contacts, skipped=arrays.counts()))
        self.log(f"residual: trained {report['epochs']} epochs on {len(x)} contacts (best validation loss "
                 f"{report['best_val_loss']:.4g})")
        self.network, self.network_info = net, info
        self.report["residual"] = dict(epochs=report["epochs"], best_val_loss=report["best_val_loss"],
                                       contacts=info["contacts"])


def _model_of(text: str):
    """The model a config text describes (read from a temporary file, as :func:`load_model` reads)."""
    from ttsim_jax.params import load_model

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fitted.toml"
        path.write_text(text, encoding="utf-8")
        return load_model(path)


def fit_dataset(data, base="conti2026", *, stages: Sequence[str] | None = None, settings: FitSettings = FitSettings(),
                labels: Sequence[str] | None = None, name: str = "fitted", progress: Callable | None = None,
                log: Callable | None = None) -> FitResult:
    """Identifies a model from one or several datasets (see the module docstring).

    Arguments:
        data: a :class:`~ttsim_jax.data.Dataset`, a dataset directory, or a list of them (merged).
        base: base model (bundled name or TOML path): ball, air, the forms' breakpoints, the values
            where data is missing and every parameter no stage fits.
        stages: the stages to run, of :data:`STAGES` (run in that order); None: those of
            :data:`DEFAULT_STAGES` that the data supports, the others skipped with the reason.
        settings: :class:`FitSettings`.
        labels: a name per dataset, for the report and the merged session names (default: the
            directories' paths, the Datasets' positions).
        name: the fitted model's name (its config's ``name``).
        progress: optional ``progress(stage, done, total)``.
        log: optional ``log(text)`` for each stage's summary lines (default: nothing).

    Returns:
        :class:`FitResult`.

    Raises:
        FitError: a stage in ``stages`` the data cannot support, or no stage the data can.
        StageFailed: a stage raised; its ``partial`` holds the stages fitted before it.
    """
    from ttsim_jax.data.merge import merge_datasets
    from ttsim_jax.params import resolve_model_path

    log = log or (lambda text: None)
    explicit = stages is not None
    requested = tuple(s for s in STAGES if s in (stages if explicit else DEFAULT_STAGES))
    unknown = sorted(set(stages or ()) - set(STAGES))
    if unknown or not requested:
        raise FitError(f"stages: expected some of {', '.join(STAGES)}; got {list(stages or ())}")
    datasets, default_labels = load_datasets(data)
    labels = list(default_labels if labels is None else labels)
    ds = merge_datasets(datasets, labels)
    test = held_out_sessions(datasets, settings.test_fraction, settings.seed)
    base_path = resolve_model_path(base)
    problems = stage_problems(ds, requested, settings.min_spin_conf, spin=settings.spin)
    if explicit and problems:
        raise FitError("; ".join(f"stage {s} cannot run on {', '.join(labels)}: {why}" for s, why in problems.items())
                       + "; leave " + ", ".join(problems) + " out of the stages (without stages, those the data "
                       "cannot fit are skipped)", problems)
    run = _Run(ds, base_path, settings, test, progress, log,
               parts=dict(zip(labels, held_out_parts(datasets, settings.test_fraction, settings.seed))))
    skipped = dict(problems)
    for stage, why in problems.items():
        log(f"{stage}: skipped: {why}")
    seconds, fitted, failed = {}, [], None
    for stage in requested:
        if stage in skipped:
            continue
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            getattr(run, stage)()
            fitted.append(stage)
        except _Skip as e:
            skipped[stage] = str(e)
            log(f"{stage}: skipped: {e}")
        except Exception as e:
            failed = dict(stage=stage, error=f"{type(e).__name__}: {e}")
            cause = e
            break
        finally:
            seconds[stage] = dict(wall=time.perf_counter() - wall, cpu=time.process_time() - cpu)
        if stage in run.comparison:
            log(comparison_text(stage, run.comparison[stage]))
    report = dict(data=labels, base=str(base_path), stages=list(requested), fitted=fitted, skipped=skipped,
                  failed=failed, partial=failed is not None,
                  settings=dict(dataclasses.asdict(settings), forms=list(settings.forms)),
                  test_sessions=[int(x) for x in test], seconds=seconds, comparison=run.comparison, **run.report)
    source = (f"fitted by ttsim fit on {', '.join(labels)} (stages {','.join(fitted) or 'none'}) over "
              f"{base_path.name}")
    text = run.model_text(name, source)
    result = FitResult(model=run.model.replace(name=name), toml=text, report=report, network=run.network,
                       network_info=run.network_info)
    if failed is not None:
        raise StageFailed(failed["stage"], cause, result) from cause
    if not fitted:
        raise FitError("nothing to fit: " + "; ".join(f"{s}: {why}" for s, why in skipped.items()))
    return result


# ---------------------------------------------------------------------------------------------- output
def output_paths(out) -> dict:
    """The files :func:`write_fit` writes for ``out``: ``toml`` (``.toml`` added if missing),
    ``json`` (``.fit.json``) and ``network`` (``.ttres``, with a residual network)."""
    out = Path(out)
    if out.suffix != ".toml":
        out = out.with_name(out.name + ".toml")
    return dict(toml=out, json=out.with_suffix(".fit.json"), network=out.with_suffix(".ttres"))


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def write_fit(result: FitResult, out, *, force: bool = False) -> dict:
    """Writes a fit: the model config, its JSON summary (holding the config's text) and, with a
    trained residual network, its checkpoint.

    The network goes first, then the summary, then the config, each atomically: a config on disk
    always has its summary beside it, and the summary's ``model_toml`` is the config it describes
    (compare them to tell a config left from an earlier fit).

    Arguments:
        result: what :func:`fit_dataset` returned (or a :class:`StageFailed`'s ``partial``).
        out: the model config to write (``.toml`` added if missing); the model's name is the one
            given to :func:`fit_dataset`.
        force: overwrite existing files.

    Returns:
        :func:`output_paths` of the written files (``network`` only with a network).
    """
    from ttsim_jax.files.atomic import atomic_write
    from ttsim_jax.params import load_model

    paths = output_paths(out)
    if result.network is None:
        del paths["network"]
    existing = [str(p) for p in paths.values() if p.exists()]
    if existing and not force:
        raise FileExistsError(f"the output already exists ({', '.join(existing)}); pass force=True to overwrite it")
    text = signed(result.toml)  # a damaged copy is refused on loading
    _model_of(text)  # refuses a config that does not load before anything is written
    report = dict(result.report, model=str(paths["toml"]), model_toml=text)
    if result.network is not None:
        from ttsim_jax.physics.network_checkpoint import save_residual

        info = dict(result.network_info, model=str(paths["toml"]), data=result.report["data"])
        save_residual(paths["network"], result.network, metadata=info)
        report["residual"] = dict(report.get("residual", {}), checkpoint=str(paths["network"]))
    atomic_write(paths["json"], (json.dumps(report, indent=1, default=_json_default) + "\n").encode("utf-8"))
    atomic_write(paths["toml"], text.encode("utf-8"))
    load_model(paths["toml"])
    return paths
