"""The effect base class, parameter descriptions and the one catalogue every effect registers in.

An effect is a ``flax.struct`` dataclass whose fields are its parameters (pytree leaves, so
``jax.grad`` reaches them) and whose methods are named after where it acts:

* in the simulator, at the hook points of ``ttsim_jax/physics/hooks.py`` (``ball_properties``,
  ``air_properties``, ``air_velocity``, ``spin_derivative``, ``table_surface``,
  ``table_restitution``, ``table_friction``, ``racket_coefficients``): attach them with
  ``model.replace(effects=(...))``;
* outside it, applied by the reality generator to what the dataset records
  (:data:`RECORD_POINTS`: ``record_racket``, ``observe_positions``, ``measure_spin``,
  ``drop_frames``, ``record_times``); they never change the simulated truth.

Every parameter has a *neutral* value at which the effect changes nothing (exactly: the hooks then
return their input bit for bit), a *typical* magnitude (:meth:`Effect.default`), a unit and a
*plausible* range: what a lab can meet (an indoor updraft of a few cm/s, a ball within the ITTF
tolerances, a table level to within a fraction of a degree). A fit beyond it is no explanation of a
sim-to-real gap, however well it fits (:meth:`Effect.implausible`).
:meth:`Effect.sample` draws a random instance of realistic magnitude for the generator.

A new effect is one class in this package, decorated with :func:`register`: the catalogue
(:data:`CATALOGUE`), the generator's ``--effects`` option, its TOML configuration and the truth
files all pick it up from there.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import jax.numpy as jnp
import numpy as np

from ttsim_jax.errors import UserError
from ttsim_jax.physics.hooks import HOOK_POINTS

#: Where effects that act outside the simulator are applied by the generator.
RECORD_POINTS = ("record_racket", "observe_positions", "measure_spin", "drop_frames", "record_times")

#: Effect scopes: one draw for the whole dataset, or a fresh draw for every session (game).
SCOPES = ("dataset", "session")

#: name -> effect class, in the order effects are applied when several act at one hook.
CATALOGUE: dict[str, type] = {}

#: Width [m] of the smooth band edges of position-dependent effects: a C1 cubic step over 2 mm
#: keeps the band radii differentiable while contacts outside the band are untouched exactly.
BAND_SOFTNESS = 0.002


#: A value this share of its parameter's typical magnitude beyond a plausible bound is still at it.
AT_BOUND = 0.01


@dataclasses.dataclass(frozen=True)
class Param:
    """Description of one effect parameter.

    Attributes:
        unit: SI unit ("1" when dimensionless).
        neutral: value (broadcast to ``shape``) at which the effect does nothing.
        typical: typical magnitude (broadcast to ``shape``), used by :meth:`Effect.default`.
        doc: one-line meaning.
        shape: array shape of the parameter (``()`` for a scalar).
        plausible: (low, high) bounds (each broadcast to ``shape``; +-inf for none) of the values a
            lab can meet; required (:func:`register` refuses a parameter without one).
        fit_scale: the step of the diagnosis's descent in this parameter (it fits ``start +
            fit_scale * u``; :mod:`ttsim_jax.diagnose.specs`); None (default): the largest
            |typical - neutral|, and a parameter whose typical value is its neutral one is not
            fitted; 0: among the fitted ones at step 0, held where it starts, for a later descent
            to free without compiling its fit again.
        fit_start: where that descent starts: ``"neutral"`` (default) or ``"typical"``.
    """

    unit: str
    neutral: Any
    typical: Any
    doc: str
    shape: tuple = ()
    plausible: Any = None
    fit_scale: float | None = None
    fit_start: str = "neutral"

    def __post_init__(self):
        if self.fit_start not in ("neutral", "typical"):
            raise ValueError(f"Param(fit_start=...) must be 'neutral' or 'typical', got {self.fit_start!r}")


class EffectError(UserError, ValueError):
    """A bad effect name or parameter; the message names the effect, the key and the value."""


class Effect:
    """Mixin of every effect: construction from neutral / typical / random / dict values.

    Subclasses are ``flax.struct`` dataclasses with one field per entry of ``PARAMS`` and set the
    class attributes below; :func:`register` adds them to :data:`CATALOGUE`.
    """

    NAME: ClassVar[str] = ""
    DESCRIPTION: ClassVar[str] = ""
    #: "simulator" (acts at hook points) or "record" (applied by the generator to the dataset).
    WHERE: ClassVar[str] = "simulator"
    SCOPE: ClassVar[str] = "dataset"
    PARAMS: ClassVar[dict] = {}
    #: Whether ``"all"`` (the generator's default) turns it on. False for an effect on the record that
    #: takes away or falsifies what a record's other effects leave (a tracker without spin, a
    #: miscalibrated spin estimator): it is asked for by name.
    IN_ALL: ClassVar[bool] = True

    # ------------------------------------------------------------------ construction
    @classmethod
    def _build(cls, values: dict, dtype=None) -> "Effect":
        dtype = dtype or jnp.zeros(()).dtype
        fields = {}
        for key, p in cls.PARAMS.items():
            arr = np.broadcast_to(np.asarray(values[key], np.float64), p.shape)
            fields[key] = jnp.asarray(arr, dtype)
        return cls(**fields)

    @classmethod
    def neutral(cls, dtype=None) -> "Effect":
        """The instance that changes nothing."""
        return cls._build({k: p.neutral for k, p in cls.PARAMS.items()}, dtype)

    @classmethod
    def default(cls, dtype=None) -> "Effect":
        """An instance with every parameter at its typical magnitude."""
        return cls._build({k: p.typical for k, p in cls.PARAMS.items()}, dtype)

    @classmethod
    def sample(cls, rng: np.random.Generator, dtype=None) -> "Effect":
        """A random instance of realistic magnitude (``rng``: a numpy Generator)."""
        return cls._build(cls._draw(rng), dtype)

    @classmethod
    def _draw(cls, rng: np.random.Generator) -> dict:
        """Parameter values of a random instance; subclasses override (default: typical)."""
        return {k: p.typical for k, p in cls.PARAMS.items()}

    @classmethod
    def from_dict(cls, values: dict, dtype=None, base: "Effect | None" = None, where: str = "") -> "Effect":
        """Builds an instance from ``{parameter: value}``; missing keys come from ``base``
        (default: the typical instance). Raises :class:`EffectError` naming key and value."""
        where = where or f"effect '{cls.NAME}'"
        out = (base if base is not None else cls.default(dtype)).to_dict()
        for key, value in values.items():
            if key not in cls.PARAMS:
                raise EffectError(f"{where}: unknown parameter '{key}' = {value!r}; parameters: {sorted(cls.PARAMS)}")
            p = cls.PARAMS[key]
            try:
                arr = np.asarray(value, np.float64)
            except (TypeError, ValueError):
                raise EffectError(f"{where}: parameter '{key}' = {value!r} must be a number or list of numbers ({p.unit})") from None
            try:
                np.broadcast_to(arr, p.shape)
            except ValueError:
                raise EffectError(f"{where}: parameter '{key}' = {value!r} must have shape {p.shape or 'scalar'}") from None
            if not np.all(np.isfinite(arr)):
                raise EffectError(f"{where}: parameter '{key}' = {value!r} must be finite")
            out[key] = arr
        return cls._build(out, dtype)

    def to_dict(self) -> dict:
        """``{parameter: value}`` with plain floats / nested lists (JSON-able)."""
        return {k: np.asarray(getattr(self, k), np.float64).tolist() for k in self.PARAMS}

    @classmethod
    def implausible(cls, values: dict) -> list[dict]:
        """The parameter values outside their plausible ranges, by more than :data:`AT_BOUND` of
        the parameter's typical magnitude (a fit that leaves a component at its neutral value on a
        bound, buckling's racket depth at 0, lands a hair either side of it).

        Arguments:
            values: ``{parameter: value}`` (missing parameters are not checked).

        Returns:
            One dict per parameter with a value outside its range: ``param``, ``value`` (the one
            furthest outside), ``index`` (its position in the parameter's array, ``[]`` for a
            scalar), ``low``, ``high`` and ``unit``.
        """
        out = []
        for key, p in cls.PARAMS.items():
            if key not in values:
                continue
            v = np.broadcast_to(np.asarray(values[key], np.float64), p.shape)
            lo = np.broadcast_to(np.asarray(p.plausible[0], np.float64), p.shape)
            hi = np.broadcast_to(np.asarray(p.plausible[1], np.float64), p.shape)
            tol = AT_BOUND * np.abs(np.broadcast_to(np.asarray(p.typical, np.float64), p.shape))
            outside = (v < lo - tol) | (v > hi + tol)
            if not outside.any():
                continue
            width = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
            beyond = np.where(outside, np.maximum(lo - v, v - hi) / np.maximum(width, 1e-30), -np.inf)
            i = np.unravel_index(int(np.argmax(beyond)), p.shape) if p.shape else ()
            out.append(dict(param=key, value=float(v[i]), index=[int(k) for k in i], low=float(lo[i]),
                            high=float(hi[i]), unit=p.unit))
        return out

    # ------------------------------------------------------------------ introspection
    @classmethod
    def hooks(cls) -> tuple[str, ...]:
        """Hook points (or record points) this effect defines."""
        return tuple(h for h in HOOK_POINTS + RECORD_POINTS if callable(getattr(cls, h, None)))

    @classmethod
    def describe(cls) -> str:
        """Multi-line description: name, where, scope, parameters with units and typical values."""
        lines = [f"{cls.NAME} ({cls.WHERE}, per {cls.SCOPE}; acts at: {', '.join(cls.hooks())})", f"  {cls.DESCRIPTION}"]
        for k, p in cls.PARAMS.items():
            shape = "" if not p.shape else f" shape {p.shape}"
            lines.append(f"  - {k} [{p.unit}]{shape}: {p.doc} (neutral {p.neutral}, typical {_fmt(p.typical)}, "
                         f"plausible {_fmt(p.plausible[0])} to {_fmt(p.plausible[1])})")
        return "\n".join(lines)


def _fmt(v) -> str:
    a = np.asarray(v, np.float64)
    return f"{float(a):.4g}" if a.ndim == 0 else np.array2string(a, precision=4, separator=", ")


def register(cls):
    """Class decorator: checks an effect class and adds it to :data:`CATALOGUE`."""
    if not cls.NAME or cls.NAME in CATALOGUE:
        raise ValueError(f"effect class {cls.__name__} needs a unique NAME (got {cls.NAME!r})")
    if cls.WHERE not in ("simulator", "record") or cls.SCOPE not in SCOPES:
        raise ValueError(f"effect {cls.NAME}: WHERE must be simulator|record, SCOPE one of {SCOPES}")
    fields = {f.name for f in dataclasses.fields(cls)}
    if fields != set(cls.PARAMS):
        raise ValueError(f"effect {cls.NAME}: fields {sorted(fields)} must match PARAMS {sorted(cls.PARAMS)}")
    for key, p in cls.PARAMS.items():
        if p.plausible is None or len(p.plausible) != 2:
            raise ValueError(f"effect {cls.NAME}: parameter {key} needs a plausible (low, high) range")
        lo, hi = (np.broadcast_to(np.asarray(b, np.float64), p.shape) for b in p.plausible)
        if not np.all((lo <= np.asarray(p.neutral)) & (np.asarray(p.neutral) <= hi) & (lo <= np.asarray(p.typical))
                      & (np.asarray(p.typical) <= hi)):
            raise ValueError(f"effect {cls.NAME}: parameter {key}'s neutral or typical value lies outside its plausible range")
    points = HOOK_POINTS if cls.WHERE == "simulator" else RECORD_POINTS
    if not any(callable(getattr(cls, h, None)) for h in points):
        raise ValueError(f"effect {cls.NAME} defines none of {points}")
    CATALOGUE[cls.NAME] = cls
    return cls


# ---------------------------------------------------------------------- smooth helpers
def smoothstep(x, edge, width=BAND_SOFTNESS):
    """0 below ``edge - width/2``, 1 above ``edge + width/2``, a C1 cubic in between.

    Exactly 0 / 1 outside the band, so an effect leaves contacts away from its region untouched,
    yet differentiable in ``edge`` (the region's boundary is a parameter that can be fitted).
    """
    s = jnp.clip((x - edge) / width + 0.5, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def signed(rng: np.random.Generator, low: float, high: float) -> float:
    """A magnitude uniform in [low, high) with a random sign (a draw of :meth:`Effect._draw`)."""
    return rng.choice([-1.0, 1.0]) * rng.uniform(low, high)


def onset(x, start, width):
    """1 - exp(-(max(x - start, 0) / width)^2): 0 up to ``start``, then rising smoothly (C1) to 1."""
    r = jnp.maximum(x - start, 0.0) / width
    return 1.0 - jnp.exp(-r * r)
