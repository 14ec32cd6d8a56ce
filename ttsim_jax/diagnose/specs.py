"""Candidate effects as the diagnosis fits them: the phases each effect can change (from its hooks),
its fitted parameters and their scales (:func:`spec`).

Its free parameters are written ``start + scale * u`` with ``u`` starting at 0 (the effect neutral,
or at the typical values of its fixed shape parameters, e.g. the bump centres of
``table_unevenness``), so a descent's step size means the same for every parameter. The effect
declares both with its parameters (:class:`~ttsim_jax.effects.base.Param`'s ``fit_scale`` and
``fit_start``); by default a parameter is fitted where its typical value differs from its neutral
one, at the scale of that difference, from neutral. What a second descent frees (the ``SCALES`` of
:mod:`~ttsim_jax.diagnose.gusts`, :mod:`~ttsim_jax.diagnose.bumps` and
:mod:`~ttsim_jax.diagnose.onsets`) is free from the first descent on at step 0 (held where it
starts), so both descents run one compiled program.

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
    free = {}
    for k, p in cls.PARAMS.items():
        if p.fit_scale is not None:
            free[k] = float(p.fit_scale)
            continue
        d = np.abs(np.broadcast_to(np.asarray(p.typical, np.float64) - np.asarray(p.neutral, np.float64), p.shape))
        if d.size and d.max() > 0:
            free[k] = float(d.max())
    start = {k: np.broadcast_to(np.asarray(p.typical if p.fit_start == "typical" else p.neutral, np.float64),
                                p.shape).copy() for k, p in cls.PARAMS.items()}
    scale = {k: np.float64(free.get(k, 0.0)) for k in cls.PARAMS}
    return Spec(name, cls, free_order(cls, free), cls.SCOPE == "session" and not pooled), dict(start=start, scale=scale)


def free_order(cls, names) -> tuple:
    """The parameter names ``names`` in the effect class's order: a spec is a static argument of the
    compiled fit, so two descents that free the same parameters must name them alike."""
    return tuple(k for k in cls.PARAMS if k in names)
