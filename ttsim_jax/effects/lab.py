"""Effects of a lab's conditions: its air, its table's surface, its tracker's clock and calibration.

* in the simulator: :class:`AirDensity` (hook ``air_properties``), :class:`TableFriction` (hook
  ``table_friction``), exactly neutral and differentiable like those of :mod:`.physical`;
* on the record, applied by the reality generator: :class:`ClockRate` (``record_times``),
  :class:`CameraScale` (``observe_positions``), :class:`SpinCalibration` and
  :class:`SpinUnmeasured` (``measure_spin``), numpy like those of :mod:`.record`. The last two are
  left out of ``"all"`` (:attr:`~.base.Effect.IN_ALL`): they take a record's spin away or falsify
  it, which a generated record is asked for by name.

They register after the effects of :mod:`.physical` and :mod:`.record`: the generator seeds each
effect's random draws by its position in the catalogue, so effects added later come last and the
datasets of earlier configurations stay reproducible.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from .base import Effect, Param, register, signed
from .record import _np, rotation_matrix


# ---------------------------------------------------------------------- simulator
@register
@struct.dataclass
class AirDensity(Effect):
    """Air denser or thinner than the model's (temperature, altitude, humidity).

    The density becomes rho_air (1 + d_rho): drag, Magnus force and buoyancy, all proportional to
    it, scale by (1 + d_rho). The air's dynamic viscosity is held, so its kinematic viscosity
    becomes nu / (1 + d_rho) and the Reynolds number of a C_D(Re, Sp) table scales by (1 + d_rho)
    too. Against the model's 1.204 kg/m^3 (20 C, sea level): 30 C is -0.03, 1,500 m of altitude
    -0.16, 2,500 m and 35 C -0.25.
    """

    d_rho: jnp.ndarray

    NAME = "air_density"
    DESCRIPTION = ("air density off the model's (temperature, altitude, humidity): drag, Magnus and buoyancy "
                   "times (1 + d_rho)")
    SCOPE = "session"
    # fitted at twice its typical step, so that a descent reaches a hall at altitude (-0.25 at 2,500 m)
    PARAMS = {"d_rho": Param("1", 0.0, -0.05, "relative change of the air density (altitude 0-2,500 m, 10-35 C)",
                             plausible=(-0.30, 0.05), fit_scale=0.1)}

    @classmethod
    def _draw(cls, rng):
        return {"d_rho": rng.uniform(-0.12, 0.03)}

    def air_properties(self, value, **_):
        rho, nu = value
        scale = 1.0 + self.d_rho
        return rho * scale, nu / scale


@register
@struct.dataclass
class TableFriction(Effect):
    """More or less grip of the playing surface (coating, dust, wear): mu (1 + d_mu).

    The friction coefficient of the table contact law (Nakashima: grip fraction
    min(alpha_roll, mu (1 + e_n) |v_n| / |u|)) and of a ball sliding on the table. It changes the
    tangential velocity and spin after a bounce that slides throughout (a fast contact point,
    e.g. heavy spin or a flat approach); a bounce that ends rolling (grip alpha_roll: the friction
    suffices to stop the contact point's slip) is unchanged, and so is the normal velocity.
    """

    d_mu: jnp.ndarray

    NAME = "table_friction"
    DESCRIPTION = "table surface with more or less grip (coating, dust, wear): friction coefficient mu times (1 + d_mu)"
    SCOPE = "dataset"
    PARAMS = {"d_mu": Param("1", 0.0, 0.2, "relative change of the table's friction coefficient",
                            plausible=(-0.5, 0.5))}

    @classmethod
    def _draw(cls, rng):
        return {"d_mu": signed(rng, 0.1, 0.35)}

    def table_friction(self, value, *, vn=None, **_):
        return value * (1.0 + self.d_mu)


# ---------------------------------------------------------------------- record
@register
@struct.dataclass
class ClockRate(Effect):
    """The tracker's clock runs fast (or slow) and lags: recorded t = t_true (1 + rate) + latency.

    Applied to every recorded time (observations and events, hence segments and racket contacts).
    The latency shifts all times alike and is mostly invisible; the rate scales every duration, so
    a flight's accelerations appear (1 + rate)^-2 times the true ones (gravity included).
    """

    rate: jnp.ndarray
    latency: jnp.ndarray

    NAME = "clock_rate"
    DESCRIPTION = "tracker clock off: recorded times t (1 + rate) + latency (durations scaled by 1 + rate)"
    WHERE = "record"
    SCOPE = "dataset"
    PARAMS = {
        "rate": Param("1", 0.0, 0.001, "relative rate error of the clock (29.97 vs 30 frames/s: 0.001)",
                      plausible=(-0.01, 0.01)),
        "latency": Param("s", 0.0, 0.02, "constant lag of every recorded time", plausible=(-0.1, 0.1)),
    }

    @classmethod
    def _draw(cls, rng):
        return {"rate": signed(rng, 0.0005, 0.002), "latency": rng.uniform(0.0, 0.05)}

    def record_times(self, t):
        """Recorded times of (N,) true times [s]."""
        return _np(t) * (1.0 + _np(self.rate)) + _np(self.latency)


@register
@struct.dataclass
class CameraScale(Effect):
    """A scale error of the triangulation (camera calibration): positions recorded times
    (1 + scale) about the table centre (the frame's origin)."""

    scale: jnp.ndarray

    NAME = "camera_scale"
    DESCRIPTION = "triangulation scale error: recorded positions times (1 + scale) about the table centre"
    WHERE = "record"
    SCOPE = "dataset"
    PARAMS = {"scale": Param("1", 0.0, 0.003, "relative scale error of recorded positions", plausible=(-0.02, 0.02))}

    @classmethod
    def _draw(cls, rng):
        return {"scale": signed(rng, 0.001, 0.006)}

    def observe_positions(self, pos, rng: np.random.Generator | None = None):
        """Recorded copies of (N, 3) positions (``rng`` unused: the error is the same for all)."""
        return _np(pos) * (1.0 + _np(self.scale))


@register
@struct.dataclass
class SpinCalibration(Effect):
    """A spin estimator that reads wrong the same way on every segment: the recorded spin is
    (1 + scale) R w, R the rotation by the rotation vector ``rotation`` (a spin frame turned against
    the world's, an axis convention off), with the sign flipped on a ``flip`` share of the segments
    (a top/backspin sign read wrong on some trajectories). The confidence is left as it was:
    nothing in the record says the spin is wrong, which only the spin check
    (:mod:`ttsim_jax.fit.spin_check`) against the flights can show.
    """

    scale: jnp.ndarray
    rotation: jnp.ndarray
    flip: jnp.ndarray

    NAME = "spin_calibration"
    DESCRIPTION = "spin estimates times (1 + scale), turned by a rotation vector, the sign flipped on a share"
    WHERE = "record"
    SCOPE = "dataset"
    IN_ALL = False
    PARAMS = {
        "scale": Param("1", 0.0, 0.1, "relative scale error of the spin estimate", plausible=(-0.5, 0.5)),
        "rotation": Param("rad", 0.0, (0.0, 0.0, 0.17), "rotation vector turning the estimate, world frame", (3,),
                          plausible=((-0.8, -0.8, -0.8), (0.8, 0.8, 0.8))),
        "flip": Param("1", 0.0, 0.0, "share of segments whose spin's sign is flipped", plausible=(0.0, 1.0)),
    }

    @classmethod
    def _draw(cls, rng):
        axis = rng.normal(size=3)
        return {"scale": signed(rng, 0.1, 0.2), "rotation": list(axis / np.linalg.norm(axis) * rng.uniform(0.1, 0.3)),
                "flip": 0.0}

    def measure_spin(self, spin, rng: np.random.Generator):
        """Recorded copies of (S, 3) spin estimates (``rng`` draws which are flipped)."""
        out = (1.0 + _np(self.scale)) * _np(spin) @ rotation_matrix(_np(self.rotation)).T
        flipped = rng.random(len(out)) < _np(self.flip)
        return np.where(flipped[:, None], -out, out)


@register
@struct.dataclass
class SpinUnmeasured(Effect):
    """A tracker that measures no spin (most do not): a ``fraction`` of the segments (1: all) is
    recorded with spin 0 and confidence 0, as the importers write a record without spin columns."""

    fraction: jnp.ndarray

    NAME = "spin_unmeasured"
    DESCRIPTION = "no spin measured on a share of the segments (1: a tracker without spin): spin 0, confidence 0"
    WHERE = "record"
    SCOPE = "dataset"
    IN_ALL = False
    PARAMS = {"fraction": Param("1", 0.0, 1.0, "share of segments without a measured spin", plausible=(0.0, 1.0))}

    def measure_spin(self, spin, conf, rng: np.random.Generator):
        """(spin (S, 3), conf (S,)) as recorded, from the estimates and their confidences."""
        gone = rng.random(len(conf)) < _np(self.fraction)
        return np.where(gone[:, None], 0.0, _np(spin)), np.where(gone, 0.0, _np(conf))
