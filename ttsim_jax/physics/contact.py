"""The instantaneous point-contact model shared by table and racket contact (Nakashima 2011).

Everything here is written in a *contact frame*: its z-axis is the surface normal pointing towards
the ball, so the contact point sits at (0, 0, -r) from the ball centre. Velocities are relative to
the surface. With alpha the grip fraction of each tangential axis:

    A_vv = diag(1 - a_x, 1 - a_y, -e_n)          A_vw = [[0, a_x r, 0], [-a_y r, 0, 0], [0, 0, 0]]
    A_ww = diag(1 - k a_y, 1 - k a_x, e_s)       A_wv = [[0, -k a_y / r, 0], [k a_x / r, 0, 0], [0, 0, 0]]

(the paper's matrices, Eqs. (tcm_v, tcm_w); a_x = a_y = alpha unless the surface is anisotropic,
and e_s = 1 except for the racket's normal spin damping). The surface velocity of the contact point,
u = v_t + w x (0, 0, -r), then changes to u (1 - (1 + k) alpha): a fully gripping contact
alpha = (1 + e_t) / (1 + k) reverses it by the tangential restitution e_t.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from ttsim_jax.physics.numerics import matvec, safe_norm


@struct.dataclass
class ContactCoefficients:
    """Coefficients of one contact, passed through the ``racket_coefficients`` hook.

    Attributes:
        e_n: normal restitution.
        alpha: (2,) grip fraction along the two tangential axes of the contact frame.
        e_s: damping of the normal spin component (1 = none).
    """

    e_n: jnp.ndarray
    alpha: jnp.ndarray
    e_s: jnp.ndarray


def surface_velocity(vel, spin, radius):
    """Tangential velocity (3,) of the contact point: (v_x, v_y, 0) + w x (0, 0, -r)."""
    return jnp.stack([vel[0] - radius * spin[1], vel[1] + radius * spin[0], jnp.zeros_like(vel[0])])


def contact_matrices(coef: ContactCoefficients, radius, kappa):
    """The four 3x3 matrices (A_vv, A_vw, A_wv, A_ww) of the point-contact model."""
    ax, ay = coef.alpha[0], coef.alpha[1]
    z = jnp.zeros_like(ax)
    one = jnp.ones_like(ax)
    a_vv = jnp.array([[1 - ax, z, z], [z, 1 - ay, z], [z, z, -coef.e_n * one]])
    a_vw = jnp.array([[z, ax * radius, z], [-ay * radius, z, z], [z, z, z]])
    a_wv = jnp.array([[z, -kappa * ay / radius, z], [kappa * ax / radius, z, z], [z, z, z]])
    # w_x couples to the y surface velocity and w_y to the x one, hence the crossed alphas.
    a_ww = jnp.array([[1 - kappa * ay, z, z], [z, 1 - kappa * ax, z], [z, z, coef.e_s * one]])
    return a_vv, a_vw, a_wv, a_ww


def apply_matrices(mats, vel, spin):
    """v+ = A_vv v + A_vw w,  w+ = A_wv v + A_ww w."""
    a_vv, a_vw, a_wv, a_ww = mats
    return matvec(a_vv, vel) + matvec(a_vw, spin), matvec(a_wv, vel) + matvec(a_ww, spin)


def sliding_alpha(mu, e_n, vel, spin, radius, alpha_roll=0.4):
    """Nakashima's table grip fraction: min(2/5, mu (1 + e_n) |v_z| / |u|).

    Continuous across the rolling/sliding boundary; equals ``alpha_roll`` (rolling) when the
    surface velocity u vanishes, so no division by zero.
    """
    u = safe_norm(surface_velocity(vel, spin, radius))
    slide = mu * (1.0 + e_n) * jnp.abs(vel[2])
    rolling = slide >= alpha_roll * u
    return jnp.where(rolling, alpha_roll, slide / jnp.where(rolling, 1.0, u))
