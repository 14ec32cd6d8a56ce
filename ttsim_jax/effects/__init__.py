"""The effect catalogue: small augmentations of the physics shared by the reality generator and the
sim-to-real gap diagnosis.

Every effect is a ``flax.struct`` dataclass registered in :data:`CATALOGUE` (name -> class). Each
class carries its description, scope (drawn once per dataset or per session), its parameters with
units, neutral and typical values (``PARAMS``), and the constructors ``neutral()``, ``default()``,
``sample(rng)`` and ``from_dict(d)``. Effects acting in the simulator define methods named after
the hook points of ``ttsim_jax/physics/hooks.py``; attach them with
``model.replace(effects=(...))``::

    from ttsim_jax import load_model
    from ttsim_jax.effects import CATALOGUE, make
    model = load_model("conti2026")
    truth = model.replace(effects=(make("air_flow", wind=[0.3, 0, 0]), make("racket_logo")))

Effects acting outside the simulator (``WHERE == "record"``: racket-state error and sensor effects)
are applied by the reality generator to what the dataset records.

Catalogue (``python -m ttsim_jax.effects`` prints it with every parameter):

=====================  ==========  =======  ====================================================
name                   where       scope    what
=====================  ==========  =======  ====================================================
spin_decay             simulator   dataset  spin decays in flight
air_flow               simulator   session  steady wind plus gusts (time-varying)
table_tilt             simulator   dataset  tilted table plane (height and normal)
table_unevenness       simulator   dataset  mm bumps and dips of the surface
ball_variation         simulator   session  ball radius and mass
worn_ball              simulator   session  lower restitution of a worn ball (table, racket)
buckling               simulator   dataset  restitution drops at high impact speed
racket_logo            simulator   dataset  logo 5-8 cm towards the handle: less grip
racket_edge            simulator   dataset  rim beyond 8 cm: deader bounce
rubber_anisotropy      simulator   dataset  grip along racket y vs z differs
racket_state_error     record      dataset  recorded racket: bias, vibration, timing
position_noise         record      dataset  noisy ball positions
spin_noise             record      dataset  noisy spin estimates, outliers, confidences
missing_frames         record      dataset  dropped frames and occlusion bursts
air_density            simulator   session  air density: drag, Magnus, buoyancy scale
table_friction         simulator   dataset  table friction coefficient scales
clock_rate             record      dataset  tracker clock: rate error and latency
camera_scale           record      dataset  positions scaled about the table centre
spin_calibration       record      dataset  spin estimates scaled, turned, some signs flipped (*)
spin_unmeasured        record      dataset  a tracker without spin: spin 0, confidence 0 (*)
=====================  ==========  =======  ====================================================

(*) not in ``"all"`` (the generator's default): asked for by name (``Effect.IN_ALL``).
"""

from __future__ import annotations

from typing import Iterable

import jax.numpy as jnp

from . import physical, record  # noqa: F401  (importing registers the effects, in catalogue order)
from . import lab  # noqa: F401  (registered last: see its docstring)
from .base import BAND_SOFTNESS, CATALOGUE, RECORD_POINTS, SCOPES, Effect, EffectError, Param, register, smoothstep
from .lab import AirDensity, CameraScale, ClockRate, SpinCalibration, SpinUnmeasured, TableFriction
from .physical import (
    AirFlow,
    BallVariation,
    Buckling,
    RacketEdge,
    RacketLogo,
    RubberAnisotropy,
    SpinDecay,
    TableTilt,
    TableUnevenness,
    WornBall,
)
from .record import MissingFrames, PositionNoise, RacketStateError, SpinNoise, rotation_matrix

__all__ = [
    "AirDensity", "AirFlow", "BAND_SOFTNESS", "BallVariation", "Buckling", "CATALOGUE", "CameraScale", "ClockRate",
    "Effect", "EffectError", "MissingFrames", "Param", "PositionNoise", "RECORD_POINTS", "RacketEdge", "RacketLogo",
    "RacketStateError", "RubberAnisotropy", "SCOPES", "SpinCalibration", "SpinDecay", "SpinNoise", "SpinUnmeasured",
    "TableFriction", "TableTilt",
    "TableUnevenness", "WornBall", "describe", "effect_class",
    "make", "names", "parse_names", "record_effects", "register", "rotation_matrix", "simulator_effects", "smoothstep",
]


def names(where: str | None = None) -> list[str]:
    """Catalogue names in application order, optionally only those acting ``where``
    (``"simulator"`` or ``"record"``)."""
    return [n for n, c in CATALOGUE.items() if where is None or c.WHERE == where]


def effect_class(name: str) -> type:
    """The class registered as ``name``; :class:`EffectError` listing the known names otherwise."""
    try:
        return CATALOGUE[name]
    except KeyError:
        raise EffectError(f"unknown effect {name!r}; known effects: {', '.join(CATALOGUE)}") from None


def make(name: str, dtype=None, **params) -> Effect:
    """The effect ``name`` at its typical values, with ``params`` overriding some of them."""
    return effect_class(name).from_dict(params, dtype=dtype)


def parse_names(spec: str | Iterable[str] | None) -> list[str]:
    """Effect names from ``"all"``, ``"none"``, ``"a,b"`` or a list; checked, in catalogue order."""
    if spec is None:
        return []
    if isinstance(spec, str):
        s = spec.strip()
        if s in ("all", "*"):
            return [n for n in names() if CATALOGUE[n].IN_ALL]
        if s in ("none", ""):
            return []
        spec = [p.strip() for p in s.split(",") if p.strip()]
    chosen = list(spec)
    for n in chosen:
        effect_class(n)
    return [n for n in CATALOGUE if n in chosen]


def simulator_effects(effects: Iterable[Effect]) -> tuple:
    """The effects of ``effects`` that act inside the simulator (what a model's ``effects`` holds)."""
    return tuple(e for e in effects if e.WHERE == "simulator")


def record_effects(effects: Iterable[Effect]) -> dict:
    """name -> effect for the effects applied to the recorded data."""
    return {e.NAME: e for e in effects if e.WHERE == "record"}


def cast(effect: Effect, dtype) -> Effect:
    """``effect`` with every parameter converted to ``dtype`` (effects must match the model's dtype)."""
    return type(effect)(**{k: jnp.asarray(getattr(effect, k), dtype) for k in effect.PARAMS})


def describe(which: Iterable[str] | None = None) -> str:
    """Human-readable description of the catalogue (or of the named effects)."""
    return "\n\n".join(effect_class(n).describe() for n in (which or names()))
