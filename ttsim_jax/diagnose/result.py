"""What :func:`~ttsim_jax.diagnose.diagnosis.diagnose` returns: :class:`Diagnosis`, with its
:class:`~ttsim_jax.diagnose.verdict.Verdict`.

The sections are JSON-ready values (dicts and lists of numbers and strings: the report's own
content, also read back from a stored ``diagnosis.json``); ``arrays`` and ``histories`` are the
arrays the figures draw. :meth:`Diagnosis.to_json` is the content of ``diagnosis.json``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from ttsim_jax.diagnose.verdict import Verdict
from ttsim_jax.results import jsonable

#: Sections present only where they apply, left out of the JSON where they do not.
OPTIONAL = ("spin_sources", "spin_correction", "combined", "landing")


@dataclasses.dataclass(frozen=True)
class Diagnosis:
    """The diagnosis of a model on a dataset.

    Attributes:
        verdict: the :class:`~ttsim_jax.diagnose.verdict.Verdict`.
        phases: the phases with data; counts: their items (flight segments, contacts);
            skipped: {phase or stage: why it was skipped}; left_out: {phase: {reason: count}} of
            items left out; no_data: {phase: reason} of the phases without items;
            spin_sources: how many flight segments flew which spin (None without flights).
        floor: per phase the noise floor and the removable gap, or why there is none
            (:func:`~ttsim_jax.diagnose.floor.floors`); where: per phase the regimes where the error
            lies; dependence: per phase the residuals' significant dependences; record: the
            record's own sizes and its spin check; spin_correction: the correction of the record's
            spin, where one was fitted (else None); bound: per phase how far a model-free
            correction gets.
        candidates: the candidate effects, ranked (fits, held-out scores, parameters);
            limits: the detection limits (:func:`~ttsim_jax.diagnose.limits.limits`);
            implausible: significant effects whose fit needs implausible parameters;
            indistinguishable: groups of effects the data cannot tell apart; reads_as: accepted
            effects that change the errors only as a simpler reading does; combined: the accepted
            effects fitted together (None where none is accepted); before_after: per phase the
            errors before and after them; landing: the landing's errors before and after (None
            without the landing stage or its cases).
        pooled_sessions: per-session effects fitted with one shared set; settings: the settings
            as run; seconds: the run's wall time; timings: {stage: seconds}.
        arrays: per-item errors before and after, for the figures; histories: {effect: loss
            history of its fit}.
    """

    verdict: Verdict
    phases: list
    counts: dict
    skipped: dict
    left_out: dict
    no_data: dict
    floor: dict
    where: dict
    dependence: dict
    record: dict
    bound: dict
    candidates: list
    limits: dict
    implausible: list
    indistinguishable: list
    reads_as: dict
    before_after: dict
    pooled_sessions: Any
    settings: dict
    seconds: float
    timings: dict
    arrays: dict
    histories: dict
    spin_sources: dict | None = None
    spin_correction: dict | None = None
    combined: dict | None = None
    landing: dict | None = None

    def to_json(self) -> dict:
        """The content of ``diagnosis.json``, JSON-ready (:func:`~ttsim_jax.results.jsonable`):
        every section but the arrays (the optional ones only where they apply), the verdict as a
        dict and each fit's loss history as a list."""
        body = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if f.name not in ("arrays", "histories") and not (f.name in OPTIONAL and getattr(self, f.name) is None)}
        body["verdict"] = self.verdict.to_json()
        body["loss_history"] = self.histories
        return jsonable(body)
