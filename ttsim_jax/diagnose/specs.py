"""Candidate effects as the diagnosis fits them: the phases each effect can change (from its hooks),
its fitted parameters and their scales (:func:`spec`).

Its free parameters are written ``start + scale * u`` with ``u`` starting at 0 (the effect neutral,
or at the typical values of its fixed shape parameters, e.g. the bump centres of
``table_unevenness``), so a descent's step size means the same for every parameter. Which parameters
are fitted is inferred (those whose typical value differs from the neutral one, at the scale of
that difference) unless :data:`FREE` says otherwise.

The fit itself, its scores and the ranking are :mod:`ttsim_jax.diagnose.candidates`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ttsim_jax import effects as fx

#: Phases whose errors the candidates are fitted and scored on.
PHASES = ("flight", "table", "racket")
#: Hooks -> phases they act in.
HOOK_PHASES = {
    "ball_properties": ("flight", "table", "racket"),
    "air_properties": ("flight",),
    "air_velocity": ("flight",),
    "spin_derivative": ("flight", "table", "racket"),
    "table_surface": ("table",),
    "table_restitution": ("table",),
    "table_friction": ("table",),
    "racket_coefficients": ("racket",),
}
#: Fitted parameters and their scales where the default rule (typical != neutral) is not right:
#: the gusts' frequencies are not found by descent, so the first descent fits the steady wind
#: and the gusts follow in a second (:data:`~ttsim_jax.diagnose.candidates.REFINE`); the onsets of
#: buckling are fitted too; the bumps keep their typical centres and widths; the air density at
#: twice its typical step, so that a descent reaches a hall at altitude (-0.25 at 2,500 m). What a
#: second descent frees (the ``SCALES`` of :mod:`~ttsim_jax.diagnose.gusts`,
#: :mod:`~ttsim_jax.diagnose.bumps` and :mod:`~ttsim_jax.diagnose.onsets`) is free from the first
#: descent on at step 0 (held where it starts), so both descents run one compiled program.
FREE = {
    "air_density": {"d_rho": 0.1},
    "air_flow": {"wind": 0.2, "gust_amp": 0.0, "gust_phase": 0.0, "gust_freq": 0.0},
    "buckling": {"table_depth": 0.06, "racket_depth": 0.1, "table_onset": 1.0, "racket_onset": 3.0,
                 "table_width": 0.0, "racket_width": 0.0},
    "table_unevenness": {"amplitude": 0.0015, "center": 0.3, "width": 0.0},
}
#: Parameters that start at their typical value (the others at neutral).
START_TYPICAL = {"table_unevenness": ("center", "width")}


@dataclasses.dataclass(frozen=True)
class Spec:
    """A candidate effect as the fit sees it (hashable: a static argument of the jitted fit).

    Attributes:
        name: catalogue name; cls: effect class; free: fitted parameter names;
        per_session: one parameter set per session.
    """

    name: str
    cls: type
    free: tuple
    per_session: bool

    @property
    def phases(self) -> tuple:
        return phases_of(self.cls)


def phases_of(cls) -> tuple:
    """Phases (of :data:`PHASES`) an effect class can change, from its hooks."""
    out = set()
    for h in cls.hooks():
        out.update(HOOK_PHASES.get(h, ()))
    return tuple(p for p in PHASES if p in out)


def spec(name: str, pooled: bool = False) -> tuple[Spec, dict]:
    """(:class:`Spec`, numpy constants {"start": {param: value}, "scale": {param: value}}) of a
    catalogue effect; ``pooled``: one parameter set for all sessions even for a per-session effect."""
    cls = fx.effect_class(name)
    if cls.WHERE != "simulator":
        raise fx.EffectError(f"effect {name!r} acts on the record, not in the simulator: it is not fitted as physics")
    free = FREE.get(name)
    if free is None:
        free = {}
        for k, p in cls.PARAMS.items():
            d = np.abs(np.broadcast_to(np.asarray(p.typical, np.float64) - np.asarray(p.neutral, np.float64), p.shape))
            if d.size and d.max() > 0:
                free[k] = float(d.max())
    typical = START_TYPICAL.get(name, ())
    start = {k: np.broadcast_to(np.asarray(p.typical if k in typical else p.neutral, np.float64), p.shape).copy()
             for k, p in cls.PARAMS.items()}
    scale = {k: np.float64(free.get(k, 0.0)) for k in cls.PARAMS}
    return Spec(name, cls, free_order(cls, free), cls.SCOPE == "session" and not pooled), dict(start=start, scale=scale)


def free_order(cls, names) -> tuple:
    """The parameter names ``names`` in the effect class's order: a spec is a static argument of the
    compiled fit, so two descents that free the same parameters must name them alike."""
    return tuple(k for k in cls.PARAMS if k in names)
