"""Named hook points at which effects augment the physics stages.

An *effect* (spin decay, wind, table tilt, racket heterogeneity, ...) is a ``flax.struct``
dataclass whose fields are its parameters (pytree leaves, so ``jax.grad`` reaches them) and
whose methods are named after the hook points it acts on. A model carries a tuple of effects;
each stage calls :func:`apply` at its hook points, which threads the value through every effect
that defines that hook, in order. Which effects are present is part of the pytree structure (one
compilation per set of effects); their parameter values are not (no recompilation).

Hook points, the value they receive, and the context passed as keyword arguments:

=====================  ==============================================  =========================
hook                   value (neutral)                                 context
=====================  ==============================================  =========================
``ball_properties``    (radius, mass) of the ball [m, kg]              none
``air_properties``     (density [kg/m^3], kinematic viscosity          none
                       [m^2/s]) of the air (the model's rho_air, nu)
``air_velocity``       (3,) air velocity in the world frame (zeros)    ``pos``, ``t``
``spin_derivative``    (3,) d(spin)/dt in flight (zeros)               ``vel``, ``spin``, ``t``
``table_surface``      (height, normal): surface height [m] above      ``pos`` (contact point)
                       z = 0 and its unit normal ((0, (0, 0, 1)))
``table_restitution``  e_n of the table contact                        ``vn`` (impact speed >= 0)
``table_friction``     friction coefficient mu of the table contact    ``vn`` (normal speed >= 0)
                       (the model's mu)
``racket_coefficients`` :class:`ContactCoefficients` of the racket     ``d`` (2,) contact point
                       contact                                         on the face [m], ``vn``,
                                                                       ``ut`` (2,) surface
                                                                       velocity, racket frame
=====================  ==============================================  =========================

Effects that act outside the simulator (racket-state error, sensor noise) are applied by the
data generator, not here.
"""

from __future__ import annotations

from typing import Any, Sequence

HOOK_POINTS = (
    "ball_properties",
    "air_properties",
    "air_velocity",
    "spin_derivative",
    "table_surface",
    "table_restitution",
    "table_friction",
    "racket_coefficients",
)


def apply(effects: Sequence[Any], hook: str, value, **context):
    """Threads ``value`` through every effect in ``effects`` that defines ``hook``.

    Arguments:
        effects: tuple of effect dataclasses (possibly empty).
        hook: one of :data:`HOOK_POINTS`.
        value: the stage's own value at that point.
        **context: the quantities the hook may depend on (see the module docstring).

    Returns:
        The value after all effects; ``value`` itself when no effect defines the hook.
    """
    if hook not in HOOK_POINTS:
        raise ValueError(f"unknown hook point {hook!r}; known: {HOOK_POINTS}")
    for effect in effects:
        fn = getattr(effect, hook, None)
        if fn is not None:
            value = fn(value, **context)
    return value
