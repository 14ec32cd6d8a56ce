"""Effects that act inside the simulator, at the hook points of ``ttsim_jax/physics/hooks.py``.

Each is differentiable in every parameter and exactly neutral at its neutral values (the hook
returns its input unchanged, bit for bit), so the sim-to-real gap diagnosis can start every
parameter at neutral and fit it with ``jax.grad`` through the simulator.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from ttsim_jax.physics.dimensions import TABLE_HALF_LENGTH, TABLE_HALF_WIDTH
from ttsim_jax.physics.numerics import safe_norm

from .base import Effect, Param, onset, register, signed, smoothstep

#: Steepest plausible table slope: 0.75 deg, a 3.6 cm drop over the table's length, which anyone
#: setting up a table sees; a fit steeper than this names the wrong cause.
TILT_MAX = 0.0131


# ---------------------------------------------------------------------- flight
@register
@struct.dataclass
class SpinDecay(Effect):
    """Spin decays in flight: d(spin)/dt = -(rate + quadratic |spin|) spin (air friction torque)."""

    rate: jnp.ndarray
    quadratic: jnp.ndarray

    NAME = "spin_decay"
    DESCRIPTION = "spin decays in flight under the air's friction torque (linear and quadratic in |spin|)"
    SCOPE = "dataset"
    PARAMS = {
        "rate": Param("1/s", 0.0, 0.15, "linear decay rate", plausible=(0.0, 1.0)),
        "quadratic": Param("1/rad", 0.0, 1.0e-4, "decay rate per rad/s of spin", plausible=(0.0, 1.0e-3)),
    }

    @classmethod
    def _draw(cls, rng):
        return {"rate": rng.uniform(0.05, 0.3), "quadratic": rng.uniform(0.0, 2.0e-4)}

    def spin_derivative(self, value, *, vel=None, spin=None, t=None, **_):
        return value - (self.rate + self.quadratic * safe_norm(spin)) * spin


@register
@struct.dataclass
class AirFlow(Effect):
    """Moving air in the hall: a steady wind plus gusts, sums of sinusoids in time.

    air(t) = wind + sum_k gust_amp[k] sin(2 pi gust_freq[k] (t + time_origin) + gust_phase[k]).
    ``time_origin`` is the session time at simulation time t = 0, so that balls simulated from
    different moments of a session share one simulation clock (0 for a simulation that runs in
    session time).
    """

    wind: jnp.ndarray
    gust_amp: jnp.ndarray
    gust_freq: jnp.ndarray
    gust_phase: jnp.ndarray
    time_origin: jnp.ndarray

    NAME = "air_flow"
    DESCRIPTION = "air flow from ventilation: steady wind plus time-varying gusts (world-frame air velocity)"
    SCOPE = "session"
    # the gusts' frequencies are not found by descent: the diagnosis's first descent fits the steady
    # wind, the gusts follow in a second (ttsim_jax.diagnose.gusts)
    PARAMS = {
        "wind": Param("m/s", 0.0, (0.2, 0.0, 0.0), "steady air velocity, world frame", (3,), plausible=((-0.5, -0.5, -0.05), (0.5, 0.5, 0.05))),
        "gust_amp": Param("m/s", 0.0, ((0.1, 0.0, 0.0), (0.0, 0.1, 0.0), (0.0, 0.0, 0.03)),
                          "amplitude vector of each gust component", (3, 3), plausible=((-0.3, -0.3, -0.1), (0.3, 0.3, 0.1)),
                          fit_scale=0.0),
        "gust_freq": Param("Hz", 0.0, (0.1, 0.3, 0.7), "frequency of each gust component", (3,), plausible=(0.0, 2.0),
                           fit_scale=0.0),
        "gust_phase": Param("rad", 0.0, 0.0, "phase of each gust component", (3,), plausible=(-np.inf, np.inf),
                            fit_scale=0.0),
        "time_origin": Param("s", 0.0, 0.0, "session time at simulation time 0", plausible=(-np.inf, np.inf)),
    }

    @classmethod
    def _draw(cls, rng):
        heading = rng.uniform(0.0, 2 * np.pi)
        speed = rng.uniform(0.05, 0.4)
        # Indoor air: the draws stay inside the parameters' plausible ranges.
        wind = [speed * np.cos(heading), speed * np.sin(heading), np.clip(rng.normal(0.0, 0.03), -0.045, 0.045)]
        amp = np.clip(rng.normal(0.0, 0.08, (3, 3)) * np.array([1.0, 1.0, 0.3]), [-0.28, -0.28, -0.045], [0.28, 0.28, 0.045])
        return {"wind": wind, "gust_amp": amp, "gust_freq": rng.uniform(0.05, 1.0, 3),
                "gust_phase": rng.uniform(0.0, 2 * np.pi, 3), "time_origin": 0.0}

    def air_velocity(self, value, *, pos=None, t=0.0, **_):
        arg = 2.0 * jnp.pi * self.gust_freq * (t + self.time_origin) + self.gust_phase  # (K,)
        return value + self.wind + jnp.sum(self.gust_amp * jnp.sin(arg)[:, None], axis=0)


# ---------------------------------------------------------------------- table
def _add_slope(normal, slope_xy):
    """Unit normal of a surface whose slopes (dh/dx, dh/dy) are those of ``normal`` plus ``slope_xy``.

    A surface z = h(x, y) has its normal along (-h_x, -h_y, 1), so adding slopes adds
    -n_z (s_x, s_y, 0) to the normal n. With zero slope and n = (0, 0, 1) the result is n exactly.
    """
    n = normal - normal[2] * jnp.stack([slope_xy[0], slope_xy[1], jnp.zeros_like(slope_xy[0])])
    return n / jnp.sqrt(jnp.sum(n * n))


@register
@struct.dataclass
class TableTilt(Effect):
    """The playing surface is a tilted plane: height = offset + slope . (x, y)."""

    slope: jnp.ndarray
    offset: jnp.ndarray

    NAME = "table_tilt"
    DESCRIPTION = "table not level: a tilted plane (height and normal of the surface change)"
    SCOPE = "dataset"
    PARAMS = {
        "slope": Param("1", 0.0, (0.006, 0.002), "dh/dx, dh/dy (0.0087 = 0.5 deg)", (2,), plausible=(-TILT_MAX, TILT_MAX)),
        "offset": Param("m", 0.0, 0.0, "height of the surface at the table centre", plausible=(-0.005, 0.005)),
    }

    @classmethod
    def _draw(cls, rng):
        return {"slope": np.clip(rng.normal(0.0, 0.004, 2), -0.009, 0.009), "offset": rng.normal(0.0, 0.001)}

    def table_surface(self, value, *, pos=None, **_):
        height, normal = value
        h = height + self.offset + self.slope[0] * pos[0] + self.slope[1] * pos[1]
        return h, _add_slope(normal, self.slope)


@register
@struct.dataclass
class TableUnevenness(Effect):
    """Local warps of the playing surface: Gaussian bumps and dips of a few millimetres.

    height += sum_k amplitude[k] exp(-|p - center[k]|^2 / (2 width[k]^2)); the normal follows the
    local slope.
    """

    center: jnp.ndarray
    amplitude: jnp.ndarray
    width: jnp.ndarray

    NAME = "table_unevenness"
    DESCRIPTION = "local unevenness of the playing surface (mm-high bumps and dips, 0.1-0.5 m wide)"
    SCOPE = "dataset"
    N_BUMPS = 6
    # the diagnosis fits the bumps' heights and moves their centres from the typical ones; the
    # widths start at theirs, held (freed by its second descent)
    PARAMS = {
        "center": Param("m", 0.0, ((0.9, 0.3), (-0.9, -0.3), (0.5, -0.5), (-0.5, 0.5), (1.2, 0.0), (-1.2, 0.0)),
                        "(x, y) of each bump", (6, 2), plausible=((-TABLE_HALF_LENGTH - 0.1, -TABLE_HALF_WIDTH - 0.1),
                                                                     (TABLE_HALF_LENGTH + 0.1, TABLE_HALF_WIDTH + 0.1)),
                        fit_scale=0.3, fit_start="typical"),
        "amplitude": Param("m", 0.0, (0.0015, -0.001, 0.001, -0.0015, 0.001, -0.001), "height of each bump", (6,), plausible=(-0.008, 0.008)),
        "width": Param("m", 0.25, 0.25, "standard deviation of each bump's Gaussian", (6,), plausible=(0.05, 1.0),
                       fit_scale=0.0, fit_start="typical"),
    }

    @classmethod
    def _draw(cls, rng):
        k = cls.N_BUMPS
        return {"center": rng.uniform(-1.0, 1.0, (k, 2)) * np.array([TABLE_HALF_LENGTH, TABLE_HALF_WIDTH]),
                "amplitude": rng.normal(0.0, 0.0012, k), "width": rng.uniform(0.12, 0.45, k)}

    def table_surface(self, value, *, pos=None, **_):
        height, normal = value
        rel = pos[:2] - self.center  # (K, 2)
        g = self.amplitude * jnp.exp(-jnp.sum(rel * rel, axis=-1) / (2.0 * self.width**2))  # (K,)
        grad = -jnp.sum((g / self.width**2)[:, None] * rel, axis=0)  # dh/d(x, y)
        return height + jnp.sum(g), _add_slope(normal, grad)


# ---------------------------------------------------------------------- ball
@register
@struct.dataclass
class BallVariation(Effect):
    """Ball-to-ball variation of size and mass (within the ITTF tolerances of 40+ balls)."""

    d_radius: jnp.ndarray
    d_mass: jnp.ndarray

    NAME = "ball_variation"
    DESCRIPTION = "ball-to-ball variation of radius and mass (one ball per game)"
    SCOPE = "session"
    PARAMS = {
        "d_radius": Param("m", 0.0, 1.5e-4, "radius minus the model's (ITTF: 20.0-20.3 mm)", plausible=(-0.5e-4, 3.5e-4)),
        "d_mass": Param("kg", 0.0, 2.0e-5, "mass minus the model's (ITTF: 2.67-2.77 g)", plausible=(-3.5e-5, 7.5e-5)),
    }

    @classmethod
    def _draw(cls, rng):
        # within the ITTF tolerances of a 40+ ball: diameter 40.0-40.6 mm, mass 2.67-2.77 g
        return {"d_radius": rng.uniform(0.0, 3.0e-4), "d_mass": rng.uniform(-3.0e-5, 7.0e-5)}

    def ball_properties(self, value, **_):
        radius, mass = value
        return radius + self.d_radius, mass + self.d_mass


@register
@struct.dataclass
class WornBall(Effect):
    """A worn (softened) ball bounces less: e_n of table and racket contacts times (1 - loss)."""

    loss: jnp.ndarray

    NAME = "worn_ball"
    DESCRIPTION = "worn ball: lower normal restitution on table and racket"
    SCOPE = "session"
    PARAMS = {"loss": Param("1", 0.0, 0.02, "relative loss of normal restitution", plausible=(-0.03, 0.15))}

    @classmethod
    def _draw(cls, rng):
        return {"loss": rng.uniform(0.0, 0.04)}

    def table_restitution(self, value, *, vn=None, **_):
        return value * (1.0 - self.loss)

    def racket_coefficients(self, value, *, d=None, vn=None, ut=None, **_):
        return value.replace(e_n=value.e_n * (1.0 - self.loss))


@register
@struct.dataclass
class Buckling(Effect):
    """Non-linear loss of restitution at high impact speed (the shell buckles).

    e_n -= depth (1 - exp(-(max(v_n - onset, 0) / width)^2)), separately for table and racket
    contacts (v_n: normal impact speed relative to the surface).
    """

    table_onset: jnp.ndarray
    table_width: jnp.ndarray
    table_depth: jnp.ndarray
    racket_onset: jnp.ndarray
    racket_width: jnp.ndarray
    racket_depth: jnp.ndarray

    NAME = "buckling"
    DESCRIPTION = "ball buckling: restitution drops non-linearly above an impact speed (table and racket)"
    SCOPE = "dataset"
    # the diagnosis fits the onsets too; the widths are held (freed by its second descent)
    PARAMS = {
        "table_onset": Param("m/s", 5.0, 5.0, "table impact speed where the loss starts", plausible=(0.0, 40.0),
                             fit_scale=1.0),
        "table_width": Param("m/s", 3.0, 3.0, "speed scale of the table loss", plausible=(0.1, 40.0), fit_scale=0.0),
        "table_depth": Param("1", 0.0, 0.06, "largest loss of the table e_n", plausible=(0.0, 0.3)),
        "racket_onset": Param("m/s", 15.0, 15.0, "racket impact speed where the loss starts", plausible=(0.0, 40.0),
                              fit_scale=3.0),
        "racket_width": Param("m/s", 10.0, 10.0, "speed scale of the racket loss", plausible=(0.1, 40.0),
                              fit_scale=0.0),
        "racket_depth": Param("1", 0.0, 0.1, "largest loss of the racket e_n", plausible=(0.0, 0.3)),
    }

    @classmethod
    def _draw(cls, rng):
        return {"table_onset": rng.uniform(4.0, 6.0), "table_width": rng.uniform(2.0, 4.0),
                "table_depth": rng.uniform(0.03, 0.1), "racket_onset": rng.uniform(12.0, 18.0),
                "racket_width": rng.uniform(6.0, 12.0), "racket_depth": rng.uniform(0.05, 0.15)}

    def table_restitution(self, value, *, vn=None, **_):
        return value - self.table_depth * onset(vn, self.table_onset, self.table_width)

    def racket_coefficients(self, value, *, d=None, vn=None, ut=None, **_):
        return value.replace(e_n=value.e_n - self.racket_depth * onset(vn, self.racket_onset, self.racket_width))


# ---------------------------------------------------------------------- racket surface
@register
@struct.dataclass
class RacketLogo(Effect):
    """The embossed logo near the handle: less grip and a different bounce.

    Region (smooth 2 mm edges): r_in <= -d_z <= r_out and |d_y| <= half_width, i.e. 5-8 cm from the
    face centre towards the handle (racket -z). Inside it alpha *= (1 - grip_loss) and
    e_n += d_restitution.
    """

    grip_loss: jnp.ndarray
    d_restitution: jnp.ndarray
    r_in: jnp.ndarray
    r_out: jnp.ndarray
    half_width: jnp.ndarray

    NAME = "racket_logo"
    DESCRIPTION = "embossed logo 5-8 cm from the face centre towards the handle: less grip, other restitution"
    SCOPE = "dataset"
    PARAMS = {
        "grip_loss": Param("1", 0.0, 0.35, "relative loss of tangential grip alpha in the logo", plausible=(0.0, 1.0)),
        "d_restitution": Param("1", 0.0, -0.03, "change of e_n in the logo", plausible=(-0.2, 0.1)),
        "r_in": Param("m", 0.05, 0.05, "start of the logo along -z", plausible=(0.02, 0.12)),
        "r_out": Param("m", 0.08, 0.08, "end of the logo along -z", plausible=(0.03, 0.15)),
        "half_width": Param("m", 0.03, 0.03, "half width of the logo along y", plausible=(0.005, 0.08)),
    }

    @classmethod
    def _draw(cls, rng):
        return {"grip_loss": rng.uniform(0.2, 0.5), "d_restitution": rng.uniform(-0.06, 0.01),
                "r_in": 0.05, "r_out": 0.08, "half_width": 0.03}

    def weight(self, d):
        """How much of the contact at d = (d_y, d_z) lies in the logo (0..1)."""
        along = -d[1]
        return (smoothstep(along, self.r_in) * (1.0 - smoothstep(along, self.r_out))
                * (1.0 - smoothstep(jnp.abs(d[0]), self.half_width)))

    def racket_coefficients(self, value, *, d=None, vn=None, ut=None, **_):
        w = self.weight(d)
        return value.replace(e_n=value.e_n + w * self.d_restitution, alpha=value.alpha * (1.0 - w * self.grip_loss))


@register
@struct.dataclass
class RacketEdge(Effect):
    """The face's rim beyond ``radius`` from the centre: a deader bounce and less grip.

    Inside (|d| > radius, smooth 2 mm edge) e_n *= (1 - dead) and alpha *= (1 - grip_loss).
    """

    dead: jnp.ndarray
    grip_loss: jnp.ndarray
    radius: jnp.ndarray

    NAME = "racket_edge"
    DESCRIPTION = "face rim beyond 8 cm from the centre: deader bounce, less grip"
    SCOPE = "dataset"
    PARAMS = {
        "dead": Param("1", 0.0, 0.12, "relative loss of e_n at the rim", plausible=(0.0, 0.5)),
        "grip_loss": Param("1", 0.0, 0.1, "relative loss of grip alpha at the rim", plausible=(0.0, 1.0)),
        "radius": Param("m", 0.08, 0.08, "distance from the face centre where the rim starts", plausible=(0.05, 0.09)),
    }

    @classmethod
    def _draw(cls, rng):
        return {"dead": rng.uniform(0.05, 0.2), "grip_loss": rng.uniform(0.0, 0.2), "radius": 0.08}

    def weight(self, d):
        """How much of the contact at d = (d_y, d_z) lies on the rim (0..1)."""
        return smoothstep(safe_norm(d), self.radius)

    def racket_coefficients(self, value, *, d=None, vn=None, ut=None, **_):
        w = self.weight(d)
        return value.replace(e_n=value.e_n * (1.0 - w * self.dead), alpha=value.alpha * (1.0 - w * self.grip_loss))


@register
@struct.dataclass
class RubberAnisotropy(Effect):
    """Anisotropic rubber: more grip along racket y than along z (or less, for negative values).

    alpha of the contact frame (y, z, x of the racket) becomes alpha * (1 + a, 1 - a).
    """

    anisotropy: jnp.ndarray

    NAME = "rubber_anisotropy"
    DESCRIPTION = "anisotropic rubber: grip along racket y vs z scaled by (1 + a, 1 - a)"
    SCOPE = "dataset"
    PARAMS = {"anisotropy": Param("1", 0.0, 0.08, "relative grip difference between the face's y and z", plausible=(-0.3, 0.3))}

    @classmethod
    def _draw(cls, rng):
        return {"anisotropy": signed(rng, 0.03, 0.12)}

    def racket_coefficients(self, value, *, d=None, vn=None, ut=None, **_):
        scale = jnp.stack([1.0 + self.anisotropy, 1.0 - self.anisotropy])
        return value.replace(alpha=value.alpha * scale)
