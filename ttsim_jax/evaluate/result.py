"""What :func:`~ttsim_jax.evaluate.stages.evaluate_models` returns: an :class:`Evaluation` of
typed stages.

Each stage that ran is its per-item result (:class:`~ttsim_jax.fit.flight.FlightStage`,
:class:`TableStage`, :class:`RacketStage`, :class:`LandingStage`), a stage that could not run is a
:class:`~ttsim_jax.results.Skipped` with the reason, and a stage not asked for is None. Every one
has ``to_json()``: its fields, JSON-ready. The report's numbers (``metrics.json``) are
:func:`ttsim_jax.evaluate.report.summarise` of the evaluation.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ttsim_jax.fit.flight import FlightStage
from ttsim_jax.results import ItemArrays, Skipped, jsonable

STAGES = ("flight", "table", "racket", "landing")


@dataclasses.dataclass(frozen=True)
class TableStage(ItemArrays):
    """Table-contact errors per model (:func:`~ttsim_jax.evaluate.stages.table_stage`).

    Attributes:
        event_id: (N,) the bounces used.
        spin_known: (N, 2) bool: whether the spin before and after is measured.
        pre, post: (N, 6) the estimated world-frame (v, w) before and after [m/s, rad/s] (the
            pre-bounce spin 0 where it is not measured).
        spin_in: {model name: (N, 3) the pre-bounce spin it was given [rad/s]}.
        spin_source: (N,) where that spin came from
            (:func:`~ttsim_jax.evaluate.spins.incoming_spins`).
        error: {model name: (N, 6) predicted minus measured}, NaN spin components unless both
            spins are measured.
        skip_counts: {reason: number of bounces left out for it}.
        n_bounces: the table bounces of the sessions evaluated, used or not.
    """

    event_id: np.ndarray
    spin_known: np.ndarray
    pre: np.ndarray
    post: np.ndarray
    spin_in: dict
    spin_source: np.ndarray
    error: dict
    skip_counts: dict
    n_bounces: int


@dataclasses.dataclass(frozen=True)
class RacketStage(ItemArrays):
    """Racket-contact errors per model in the racket frame, on the contacts usable for every
    model (:func:`~ttsim_jax.evaluate.stages.racket_stage`).

    Attributes:
        event_id: (N,) the contacts used.
        distance: (N,) contact distance from the face centre [m].
        x: (N, 8) the pre-contact racket-frame state (v~, w~, d) of the first model's frame.
        error: {model name: (N, 8) signed errors
            (:data:`~ttsim_jax.fit.network_evaluation.ERROR_NAMES`)}.
        predicted: {model name: (N, 6) the predicted (v~+, w~+)}; y_obs: (N, 6) the measured.
        config, rubber_type: (N,) str, tilt: (N,) [deg]: the racket configuration of each contact
            (:func:`ttsim_jax.data.racket_configs.of_events`; "" where the data names none).
        skip_counts: {reason: number of contacts left out for it} (of the first model's conversion).
        n_contacts: the racket contacts, used or not.
    """

    event_id: np.ndarray
    distance: np.ndarray
    x: np.ndarray
    error: dict
    predicted: dict
    y_obs: np.ndarray
    config: np.ndarray
    rubber_type: np.ndarray
    tilt: np.ndarray
    skip_counts: dict
    n_contacts: int


@dataclasses.dataclass(frozen=True)
class LandingStage(ItemArrays):
    """Landing-position errors per model (:func:`~ttsim_jax.evaluate.stages.landing_stage`).

    Attributes:
        event_id: (N,) the racket contacts whose landing is compared.
        measured: (N, 2) the measured landing point [m]; landing: {model name: (N, 2)}.
        error: {model name: (N,) distance [m]}, NaN where the simulated ball was not hit or did not
            land; hit: {model name: (N,) bool}.
        spin_source: (N,) where each incoming spin came from; through_bounce: (N,) whether a latent
            one was fitted across the bounce before
            (:func:`~ttsim_jax.evaluate.spins.incoming_spins`).
        skip_counts: {reason: number of contacts left out for it}; n_contacts: the racket
            contacts, used or not.
    """

    event_id: np.ndarray
    measured: np.ndarray
    landing: dict
    error: dict
    hit: dict
    spin_source: np.ndarray
    through_bounce: np.ndarray
    skip_counts: dict
    n_contacts: int


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """Every stage of an evaluation for every model.

    Attributes:
        models: the models' names, in order; reference: the one reductions are relative to.
        settings: the :class:`~ttsim_jax.evaluate.stages.EvaluateSettings` as a dict.
        flight, table, racket, landing: each stage's result, :class:`~ttsim_jax.results.Skipped`
            with the reason it could not run, or None where it was not asked for.
    """

    models: list
    reference: str
    settings: dict
    flight: FlightStage | Skipped | None = None
    table: TableStage | Skipped | None = None
    racket: RacketStage | Skipped | None = None
    landing: LandingStage | Skipped | None = None

    def stages(self) -> dict:
        """{stage name: result} of the stages asked for (run or skipped), in :data:`STAGES` order."""
        return {s: getattr(self, s) for s in STAGES if getattr(self, s) is not None}

    def ran(self) -> dict:
        """{stage name: result} of the stages that ran (neither skipped nor left out)."""
        return {s: r for s, r in self.stages().items() if not isinstance(r, Skipped)}

    def to_json(self) -> dict:
        """The models, reference, settings and each stage's ``to_json()``, JSON-ready."""
        return dict(models=list(self.models), reference=self.reference, settings=jsonable(self.settings, finite=True),
                    **{s: r.to_json() for s, r in self.stages().items()})
