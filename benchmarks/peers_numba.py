"""The rally physics re-written by hand for numba: a CPU loop (``prange`` over balls) and a CUDA loop.

The same single-ball code serves both targets: :func:`make_physics` builds every function with the
decorator it is given (``numba.njit`` or ``numba.cuda.jit(device=True)``), so the CPU and GPU loops
cannot drift apart. Vectors are tuples of scalars (no array allocation inside a CUDA thread) and
everything stays float32: literals are float32 module constants, because numba would promote a
float32 times a Python float to float64.

The physics is conti2026's, as ``ttsim_jax.physics`` evaluates it without effects: the C_D(Re, Sp)
and C_M(v, w) tables with buoyancy, RK4, table contact with the restitution law and the local
residual matrices, the "updated" racket contact against the two tracking rackets of
``ttsim_jax.policies`` (one face in play at a time), floor and play-box stops. Times of impact
follow ``ttsim_jax.physics.events``: the linear zero of the gap refined by one Newton step on the
cubic Hermite path; the rest of a step after a contact is a second-order Taylor step. Net crossings
(only logged by the kernel) are left out.

The lean loop (:func:`make_lean_physics`, ``lean=True``) is flight + table only, as one writes it
for speed: the same stages (:func:`make_stages`), the tables read by bracketing, the table as the
plane z = r with a linear time of impact.

numba is a benchmark-only extra (``pip install -e .[bench]``); importing this module without it
raises ImportError.
"""

from __future__ import annotations

import math

import numpy as np
import numba
# Some numba-cuda releases overload np.row_stack, which numpy 2.5 removed; their first CUDA
# compilation then fails (seen with numba 0.68 and numpy 2.5.2). row_stack was vstack.
if "row_stack" not in dir(np):
    np.row_stack = np.vstack

from numba import cuda, njit, prange  # noqa: E402

F = np.float32
ZERO, ONE, TWO, HALF, THREE, SIX = F(0.0), F(1.0), F(2.0), F(0.5), F(3.0), F(6.0)
TINY, UNIT_TINY, DIV_TINY, MIN_SPEED = F(1e-12), F(1e-9), F(1e-12), F(1e-6)
INF = F(np.inf)
# ttsim_jax.physics.events: penetration tolerance (fraction of r), rest speed, play box
PEN_TOL, REST_SPEED = F(0.5), F(0.1)
BOX_X, BOX_Y, BOX_Z = F(8.0), F(6.0), F(8.0)
# ttsim_jax.policies.tracking_rackets_fn clips
Y_CLIP, Z_LOW, Z_HIGH = F(1.0), F(0.05), F(1.5)

# status codes, as ttsim_jax.physics.events
NONE, TABLE, RACKET, FLOOR, OUT, REST = 0, 1, 2, 4, 5, 7

# indices into the packed scalar parameters (see pack_params)
(I_R, I_DRAG_K, I_MAG_K, I_GX, I_GY, I_GZ, I_NU, I_RE_LAST, I_CD_MIN, I_E0, I_E1, I_EMIN, I_EMAX, I_MU,
 I_KAPPA, I_ALPHA_ROLL, I_HALF_L, I_HALF_W, I_FLOOR, I_RE0, I_RE1, I_RET0, I_RET1, I_RES, I_RKAPPA, I_REMAX,
 I_TX, I_TSWING, I_TLIFT, I_TFACE, N_SCALARS) = range(31)


def pack_params(model, policy_params) -> dict:
    """Host float32 arrays of a ttsim_jax Model (no effects) and tracking-racket parameters.

    Arguments:
        model: a :class:`ttsim_jax.Model` with table drag and Magnus models and an "updated" racket.
        policy_params: dict x, swing, lift, tilt of :func:`ttsim_jax.policies.tracking_rackets`.

    Returns:
        dict of numpy arrays: ``scalars`` (N_SCALARS,), ``re_ref``, ``sp``, ``cd``, ``v_ref``,
        ``mag`` (K, 6), ``residual`` (4, 3, 3), ``rot`` (2, 3, 3) the two rackets' frames.
    """
    g = lambda x: np.asarray(x, np.float64)  # noqa: E731
    a, t, rk, b = model.aero, model.table, model.racket, model.ball
    if model.effects:
        raise ValueError("the numba peer implements the model without effects")
    if rk.kind != "updated":
        raise ValueError(f"the numba peer implements the 'updated' racket model, not {rk.kind!r}")
    r, m = float(g(b.radius)), float(g(b.mass))
    ratio = float(g(a.rho_air)) * (4.0 / 3.0) * math.pi * r**3 / m
    re_ref = g(a.drag.re_ref)
    s = np.zeros(N_SCALARS)
    s[I_R], s[I_DRAG_K], s[I_MAG_K] = r, 3.0 / (8.0 * r) * ratio, ratio
    s[[I_GX, I_GY, I_GZ]] = (1.0 - float(g(a.buoyancy)) * ratio) * g(a.gravity)
    s[I_NU] = float(g(a.nu))
    s[I_RE_LAST] = (float(g(a.drag.re_cap)) - re_ref[-2]) / (re_ref[-1] - re_ref[-2])
    s[I_CD_MIN] = float(g(a.drag.cd_min))
    for i, v in ((I_E0, t.e0), (I_E1, t.e1), (I_EMIN, t.e_min), (I_EMAX, t.e_max), (I_MU, t.mu),
                 (I_KAPPA, t.kappa), (I_ALPHA_ROLL, t.alpha_roll), (I_FLOOR, t.floor_z),
                 (I_RE0, rk.e0), (I_RE1, rk.e1), (I_RET0, rk.et0), (I_RET1, rk.et1), (I_RES, rk.e_s),
                 (I_RKAPPA, rk.kappa), (I_REMAX, rk.e_max)):
        s[i] = float(g(v))
    s[I_HALF_L], s[I_HALF_W] = 0.5 * float(g(t.length)), 0.5 * float(g(t.width))
    p = {k: float(np.asarray(v)) for k, v in policy_params.items()}
    s[I_TX], s[I_TSWING], s[I_TLIFT], s[I_TFACE] = p["x"], p["swing"], p["lift"], 0.077
    rots = []
    for sign in (-1.0, 1.0):  # ttsim_jax.policies._facing
        c, sn = math.cos(p["tilt"]), math.sin(p["tilt"])
        n, z = np.array([-sign * c, 0.0, sn]), np.array([sign * sn, 0.0, c])
        rots.append(np.stack([n, np.cross(z, n), z], axis=-1))
    m_ = a.magnus
    mag = np.stack([g(m_.m1), g(m_.s), g(m_.w_b), g(m_.a), g(m_.b), g(m_.c)], axis=-1)
    f32 = lambda x: np.ascontiguousarray(x, np.float32)  # noqa: E731
    return dict(scalars=f32(s), re_ref=f32(re_ref), sp=f32(g(a.drag.sp)), cd=f32(g(a.drag.cd)),
                v_ref=f32(g(m_.v_ref)), mag=f32(mag), residual=f32(g(t.residual)), rot=f32(np.stack(rots)))


def make_stages(jit, bracket: bool = False):
    """The single-ball stages both loops share (flight, table bounce), built with decorator ``jit``.

    Arguments:
        jit: ``numba.njit`` or ``numba.cuda.jit(device=True)``.
        bracket: read the C_D and C_M tables by finding the bracketing breakpoints and interpolating
            once (a scalar loop's way); False: as the sum of clipped ramps over every interval, the
            kernel's branch-free form (``physics/aero.py``). The same function either way, up to
            float32 rounding; the bracket does a few divisions instead of one per interval.

    Returns:
        (norm3, clip, safe_div, rk4, finish, table_bounce, load, store).
    """

    @jit
    def load(state, i):
        """Ball ``i`` of ``state`` (B, 9) as nine scalars (pos, vel, spin)."""
        return (state[i, 0], state[i, 1], state[i, 2], state[i, 3], state[i, 4], state[i, 5],
                state[i, 6], state[i, 7], state[i, 8])

    @jit
    def store(state, i, px, py, pz, vx, vy, vz, wx, wy, wz):
        state[i, 0], state[i, 1], state[i, 2] = px, py, pz
        state[i, 3], state[i, 4], state[i, 5] = vx, vy, vz
        state[i, 6], state[i, 7], state[i, 8] = wx, wy, wz

    @jit
    def norm3(x, y, z):
        n2 = x * x + y * y + z * z
        return math.sqrt(n2) if n2 > TINY else ZERO

    @jit
    def clip(x, lo, hi):
        return min(max(x, lo), hi)

    @jit
    def safe_div(num, den):
        return num / den if abs(den) > DIV_TINY else ZERO

    @jit
    def drag_coef(sc, re_ref, sp_tab, cd_tab, speed, spin_rate):
        r = sc[I_R]
        re = TWO * speed * r / sc[I_NU]
        sp = spin_rate * r / max(speed, MIN_SPEED)
        n_re, n_sp = re_ref.shape[0], sp_tab.shape[1]
        prev = ZERO
        cd = ZERO
        for k in range(n_re):
            curve = cd_tab[k, 0]  # curve k at Sp: piecewise linear, held outside its breakpoints
            for j in range(1, n_sp):
                s = clip((sp - sp_tab[k, j - 1]) / (sp_tab[k, j] - sp_tab[k, j - 1]), ZERO, ONE)
                curve += (cd_tab[k, j] - cd_tab[k, j - 1]) * s
            if k == 0:
                cd = curve
            else:
                hi = sc[I_RE_LAST] if k == n_re - 1 else ONE
                s = clip((re - re_ref[k - 1]) / (re_ref[k] - re_ref[k - 1]), ZERO, hi)
                cd += (curve - prev) * s
            prev = curve
        return max(cd, sc[I_CD_MIN])

    @jit
    def magnus_coef(v_ref, mag, speed, w):
        c = (mag[0, 0], mag[0, 1], mag[0, 2], mag[0, 3], mag[0, 4], mag[0, 5])
        m1, s0, w_b, a, b, cc = c
        for k in range(1, v_ref.shape[0]):
            s = clip((speed - v_ref[k - 1]) / (v_ref[k] - v_ref[k - 1]), ZERO, ONE)
            m1 += (mag[k, 0] - mag[k - 1, 0]) * s
            s0 += (mag[k, 1] - mag[k - 1, 1]) * s
            w_b += (mag[k, 2] - mag[k - 1, 2]) * s
            a += (mag[k, 3] - mag[k - 1, 3]) * s
            b += (mag[k, 4] - mag[k - 1, 4]) * s
            cc += (mag[k, 5] - mag[k - 1, 5]) * s
        cm = m1 * w + s0 if w <= w_b else (a * w + b) * w + cc
        return max(cm, ZERO)

    @jit
    def find(xp, x):
        """The interval k of increasing ``xp`` that holds x (the first or last beyond the ends)."""
        k = 0
        while k < xp.shape[0] - 2 and x > xp[k + 1]:
            k += 1
        return k

    @jit
    def curve_at(sp_tab, cd_tab, k, x):
        """C_D curve k at spin ratio x: piecewise linear, held outside its breakpoints."""
        j = 0
        while j < sp_tab.shape[1] - 2 and x > sp_tab[k, j + 1]:
            j += 1
        s = clip((x - sp_tab[k, j]) / (sp_tab[k, j + 1] - sp_tab[k, j]), ZERO, ONE)
        return cd_tab[k, j] + (cd_tab[k, j + 1] - cd_tab[k, j]) * s

    @jit
    def drag_coef_bracket(sc, re_ref, sp_tab, cd_tab, speed, spin_rate):
        r = sc[I_R]
        re = TWO * speed * r / sc[I_NU]
        sp = spin_rate * r / max(speed, MIN_SPEED)
        k = find(re_ref, re)
        hi = sc[I_RE_LAST] if k == re_ref.shape[0] - 2 else ONE
        s = clip((re - re_ref[k]) / (re_ref[k + 1] - re_ref[k]), ZERO, hi)
        lo = curve_at(sp_tab, cd_tab, k, sp)
        return max(lo + (curve_at(sp_tab, cd_tab, k + 1, sp) - lo) * s, sc[I_CD_MIN])

    @jit
    def magnus_coef_bracket(v_ref, mag, speed, w):
        k = find(v_ref, speed)
        s = clip((speed - v_ref[k]) / (v_ref[k + 1] - v_ref[k]), ZERO, ONE)
        w_b = mag[k, 2] + (mag[k + 1, 2] - mag[k, 2]) * s
        if w <= w_b:
            cm = (mag[k, 0] + (mag[k + 1, 0] - mag[k, 0]) * s) * w + mag[k, 1] + (mag[k + 1, 1] - mag[k, 1]) * s
        else:
            a = mag[k, 3] + (mag[k + 1, 3] - mag[k, 3]) * s
            b = mag[k, 4] + (mag[k + 1, 4] - mag[k, 4]) * s
            cm = (a * w + b) * w + mag[k, 5] + (mag[k + 1, 5] - mag[k, 5]) * s
        return max(cm, ZERO)

    drag, magnus = (drag_coef_bracket, magnus_coef_bracket) if bracket else (drag_coef, magnus_coef)

    @jit
    def accel(sc, re_ref, sp_tab, cd_tab, v_ref, mag, vx, vy, vz, wx, wy, wz, spin_rate):
        speed = norm3(vx, vy, vz)
        kd = -sc[I_DRAG_K] * drag(sc, re_ref, sp_tab, cd_tab, speed, spin_rate) * speed
        km = magnus(v_ref, mag, speed, spin_rate) * sc[I_MAG_K]
        return (kd * vx + km * (wy * vz - wz * vy) + sc[I_GX],
                kd * vy + km * (wz * vx - wx * vz) + sc[I_GY],
                kd * vz + km * (wx * vy - wy * vx) + sc[I_GZ])

    @jit
    def rk4(sc, re_ref, sp_tab, cd_tab, v_ref, mag, px, py, pz, vx, vy, vz, wx, wy, wz, dt):
        # the spin does not change in flight (no spin-decay effect), so only (pos, vel) are staged
        h = HALF * dt
        spin_rate = norm3(wx, wy, wz)
        a1 = accel(sc, re_ref, sp_tab, cd_tab, v_ref, mag, vx, vy, vz, wx, wy, wz, spin_rate)
        v2 = (vx + h * a1[0], vy + h * a1[1], vz + h * a1[2])
        a2 = accel(sc, re_ref, sp_tab, cd_tab, v_ref, mag, v2[0], v2[1], v2[2], wx, wy, wz, spin_rate)
        v3 = (vx + h * a2[0], vy + h * a2[1], vz + h * a2[2])
        a3 = accel(sc, re_ref, sp_tab, cd_tab, v_ref, mag, v3[0], v3[1], v3[2], wx, wy, wz, spin_rate)
        v4 = (vx + dt * a3[0], vy + dt * a3[1], vz + dt * a3[2])
        a4 = accel(sc, re_ref, sp_tab, cd_tab, v_ref, mag, v4[0], v4[1], v4[2], wx, wy, wz, spin_rate)
        c = dt / SIX
        return (px + c * (vx + TWO * v2[0] + TWO * v3[0] + v4[0]),
                py + c * (vy + TWO * v2[1] + TWO * v3[1] + v4[1]),
                pz + c * (vz + TWO * v2[2] + TWO * v3[2] + v4[2]),
                vx + c * (a1[0] + TWO * a2[0] + TWO * a3[0] + a4[0]),
                vy + c * (a1[1] + TWO * a2[1] + TWO * a3[1] + a4[1]),
                vz + c * (a1[2] + TWO * a2[2] + TWO * a3[2] + a4[2]))

    @jit
    def finish(sc, re_ref, sp_tab, cd_tab, v_ref, mag, px, py, pz, vx, vy, vz, wx, wy, wz, rest):
        """Second-order Taylor flight over the rest of the step after a contact."""
        a = accel(sc, re_ref, sp_tab, cd_tab, v_ref, mag, vx, vy, vz, wx, wy, wz, norm3(wx, wy, wz))
        q = HALF * rest * rest
        return (px + rest * vx + q * a[0], py + rest * vy + q * a[1], pz + rest * vz + q * a[2],
                vx + rest * a[0], vy + rest * a[1], vz + rest * a[2])

    @jit
    def mv(res, m, row, x):
        """Row ``row`` of residual matrix ``m`` times the 3-tuple ``x``."""
        return res[m, row, 0] * x[0] + res[m, row, 1] * x[1] + res[m, row, 2] * x[2]

    @jit
    def table_bounce(sc, res, vx, vy, vz, wx, wy, wz):
        """Nakashima contact with e_n(v_z) minus the residual R^T dA R (table frame = world)."""
        r, k = sc[I_R], sc[I_KAPPA]
        e_n = clip(sc[I_E0] + sc[I_E1] * vz, sc[I_EMIN], sc[I_EMAX])
        u = norm3(vx - r * wy, vy + r * wx, ZERO)
        slide = sc[I_MU] * (ONE + e_n) * abs(vz)
        ar = sc[I_ALPHA_ROLL]
        a = ar if slide >= ar * u else slide / u
        nv = (ONE - a) * vx + a * r * wy, (ONE - a) * vy - a * r * wx, -e_n * vz
        nw = (ONE - k * a) * wx - k * a / r * vy, (ONE - k * a) * wy + k * a / r * vx, wz
        # residual frame rows h, z x h, z (h: unit horizontal velocity, x when it vanishes)
        hn = norm3(vx, vy, ZERO)
        hx, hy = (vx / hn, vy / hn) if hn > UNIT_TINY else (ONE, ZERO)
        lv = (hx * vx + hy * vy, -hy * vx + hx * vy, vz)
        lw = (hx * wx + hy * wy, -hy * wx + hx * wy, wz)
        d0 = mv(res, 0, 0, lv) + mv(res, 1, 0, lw)
        d1 = mv(res, 0, 1, lv) + mv(res, 1, 1, lw)
        d2 = mv(res, 0, 2, lv) + mv(res, 1, 2, lw)
        e0 = mv(res, 2, 0, lv) + mv(res, 3, 0, lw)
        e1 = mv(res, 2, 1, lv) + mv(res, 3, 1, lw)
        e2 = mv(res, 2, 2, lv) + mv(res, 3, 2, lw)
        return (nv[0] - (hx * d0 - hy * d1), nv[1] - (hy * d0 + hx * d1), nv[2] - d2,
                nw[0] - (hx * e0 - hy * e1), nw[1] - (hy * e0 + hx * e1), nw[2] - e2)

    return norm3, clip, safe_div, rk4, finish, table_bounce, load, store


def make_physics(jit):
    """The single-ball rollout with the kernel's full geometry and events, built with decorator ``jit``;
    returns ``run_ball``."""
    norm3, clip, safe_div, rk4, finish, table_bounce, load, store = make_stages(jit)

    @jit
    def hermite(p0, v0, p1, v1, dt, tau):
        """Position and d(position)/d(tau) (one component) on the cubic Hermite path."""
        t2 = tau * tau
        t3 = t2 * tau
        pos = (TWO * t3 - THREE * t2 + ONE) * p0 + (t3 - TWO * t2 + tau) * dt * v0 \
            + (-TWO * t3 + THREE * t2) * p1 + (t3 - t2) * dt * v1
        dpos = (SIX * t2 - SIX * tau) * p0 + (THREE * t2 - F(4.0) * tau + ONE) * dt * v0 \
            + (-SIX * t2 + SIX * tau) * p1 + (THREE * t2 - TWO * tau) * dt * v1
        return pos, dpos

    @jit
    def newton(tau, g, dg):
        t = tau - safe_div(g, dg)
        return t if (t >= ZERO and t <= ONE) else tau

    @jit
    def racket_bounce(sc, rot, j, side, px, py, pz, rvx, rvy, rvz, vx, vy, vz, wx, wy, wz):
        """The "updated" racket model, face turned by ``side``; racket at rest in rotation."""
        n = (side * rot[j, 0, 0], side * rot[j, 1, 0], side * rot[j, 2, 0])
        e1 = (side * rot[j, 0, 1], side * rot[j, 1, 1], side * rot[j, 2, 1])
        e2 = (rot[j, 0, 2], rot[j, 1, 2], rot[j, 2, 2])
        dx, dy, dz = vx - rvx, vy - rvy, vz - rvz
        # contact frame (y, z, x) of the racket frame: normal last
        vc = (e1[0] * dx + e1[1] * dy + e1[2] * dz, e2[0] * dx + e2[1] * dy + e2[2] * dz,
              n[0] * dx + n[1] * dy + n[2] * dz)
        wc = (e1[0] * wx + e1[1] * wy + e1[2] * wz, e2[0] * wx + e2[1] * wy + e2[2] * wz,
              n[0] * wx + n[1] * wy + n[2] * wz)
        r, k = sc[I_R], sc[I_RKAPPA]
        u = norm3(vc[0] - r * wc[1], vc[1] + r * wc[0], ZERO)
        e_n = clip(sc[I_RE0] + sc[I_RE1] * abs(vc[2]), ZERO, sc[I_REMAX])
        e_t = clip(sc[I_RET0] + sc[I_RET1] * u, ZERO, ONE)
        a = (ONE + e_t) / (ONE + k)
        v0, v1, v2 = (ONE - a) * vc[0] + a * r * wc[1], (ONE - a) * vc[1] - a * r * wc[0], -e_n * vc[2]
        w0 = -k * a / r * vc[1] + (ONE - k * a) * wc[0]
        w1 = k * a / r * vc[0] + (ONE - k * a) * wc[1]
        w2 = sc[I_RES] * wc[2]
        return (v2 * n[0] + v0 * e1[0] + v1 * e2[0] + rvx, v2 * n[1] + v0 * e1[1] + v1 * e2[1] + rvy,
                v2 * n[2] + v0 * e1[2] + v1 * e2[2] + rvz,
                w2 * n[0] + w0 * e1[0] + w1 * e2[0], w2 * n[1] + w0 * e1[1] + w1 * e2[1],
                w2 * n[2] + w0 * e1[2] + w1 * e2[2])

    @jit
    def run_ball(i, state, n_steps, dt, rackets, sc, re_ref, sp_tab, cd_tab, v_ref, mag, res, rot,
                 status, first):
        """Rolls ball ``i`` of ``state`` (B, 9) on for ``n_steps``; writes state, status, first bounce."""
        px, py, pz, vx, vy, vz, wx, wy, wz = load(state, i)
        r = sc[I_R]
        code = NONE
        bounced = False
        for _ in range(n_steps):
            q = rk4(sc, re_ref, sp_tab, cd_tab, v_ref, mag, px, py, pz, vx, vy, vz, wx, wy, wz, dt)
            kind = NONE
            best = INF
            # table: the surface is z = 0
            g0, g1 = pz - r, q[2] - r
            if g1 < ZERO and g0 >= -PEN_TOL * r:
                tau = clip(safe_div(g0, g0 - g1), ZERO, ONE)
                hz, dz = hermite(pz, vz, q[2], q[5], dt, tau)
                tau = newton(tau, hz - r, dz)
                hx, _ = hermite(px, vx, q[0], q[3], dt, tau)
                hy, _ = hermite(py, vy, q[1], q[4], dt, tau)
                hz, dz = hermite(pz, vz, q[2], q[5], dt, tau)
                if dz < ZERO and abs(hx) <= sc[I_HALF_L] and abs(hy) <= sc[I_HALF_W]:
                    kind, best = TABLE, tau
            g0, g1 = pz - r - sc[I_FLOOR], q[2] - r - sc[I_FLOOR]
            if g1 < ZERO:
                tau = clip(safe_div(g0, g0 - g1), ZERO, ONE)
                hz, dz = hermite(pz, vz, q[2], q[5], dt, tau)
                tau = newton(tau, hz - r - sc[I_FLOOR], dz)
                if tau < best:
                    kind, best = FLOOR, tau
            j = 1 if vx >= ZERO else 0  # the racket the ball flies towards; the other is parked
            rsign = ONE if j == 1 else -ONE
            rpx, rpy, rpz = rsign * sc[I_TX], clip(py, -Y_CLIP, Y_CLIP), clip(pz, Z_LOW, Z_HIGH)
            rvx, rvz = -rsign * sc[I_TSWING], sc[I_TLIFT]
            side = ONE
            if rackets:
                nx, ny, nz = rot[j, 0, 0], rot[j, 1, 0], rot[j, 2, 0]
                h0 = nx * (px - rpx) + ny * (py - rpy) + nz * (pz - rpz)
                h1 = nx * (q[0] - rpx - dt * rvx) + ny * (q[1] - rpy) + nz * (q[2] - rpz - dt * rvz)
                side = ONE if h0 >= ZERO else -ONE
                g0, g1 = side * h0 - r, side * h1 - r
                if g1 < ZERO and g0 >= -PEN_TOL * r:
                    tau = clip(safe_div(g0, g0 - g1), ZERO, ONE)
                    hx, dx_ = hermite(px, vx, q[0], q[3], dt, tau)
                    hy, dy_ = hermite(py, vy, q[1], q[4], dt, tau)
                    hz, dz_ = hermite(pz, vz, q[2], q[5], dt, tau)
                    g = side * (nx * (hx - rpx - tau * dt * rvx) + ny * (hy - rpy) + nz * (hz - rpz - tau * dt * rvz)) - r
                    dg = side * (nx * (dx_ - dt * rvx) + ny * dy_ + nz * (dz_ - dt * rvz))
                    tau = newton(tau, g, dg)
                    hx, dx_ = hermite(px, vx, q[0], q[3], dt, tau)
                    hy, dy_ = hermite(py, vy, q[1], q[4], dt, tau)
                    hz, dz_ = hermite(pz, vz, q[2], q[5], dt, tau)
                    ox, oy, oz = hx - rpx - tau * dt * rvx, hy - rpy, hz - rpz - tau * dt * rvz
                    ly = (rot[j, 0, 1] * ox + rot[j, 1, 1] * oy + rot[j, 2, 1] * oz) / sc[I_TFACE]
                    lz = (rot[j, 0, 2] * ox + rot[j, 1, 2] * oy + rot[j, 2, 2] * oz) / sc[I_TFACE]
                    closing = side * (nx * (dx_ / dt - rvx) + ny * (dy_ / dt) + nz * (dz_ / dt - rvz)) < ZERO
                    if ly * ly + lz * lz <= ONE and closing and tau < best:
                        kind, best = RACKET, tau
            if kind == NONE:
                px, py, pz, vx, vy, vz = q
                if abs(px) > BOX_X or abs(py) > BOX_Y or abs(pz) > BOX_Z:
                    code = OUT
                    break
                continue
            tau = best
            hx, dx_ = hermite(px, vx, q[0], q[3], dt, tau)
            hy, dy_ = hermite(py, vy, q[1], q[4], dt, tau)
            hz, dz_ = hermite(pz, vz, q[2], q[5], dt, tau)
            px, py, pz, vx, vy, vz = hx, hy, hz, dx_ / dt, dy_ / dt, dz_ / dt
            if kind == FLOOR:
                code = FLOOR
                break
            if kind == TABLE:
                if not bounced:
                    first[i, 0], first[i, 1], first[i, 2] = px, py, pz
                    bounced = True
                vx, vy, vz, wx, wy, wz = table_bounce(sc, res, vx, vy, vz, wx, wy, wz)
                pz = max(pz, r)
                if abs(vz) < REST_SPEED:
                    code = REST
                    break
            else:
                rvx_c = rvx
                side = ONE if (rot[j, 0, 0] * (px - rpx - tau * dt * rvx) + rot[j, 1, 0] * (py - rpy)
                               + rot[j, 2, 0] * (pz - rpz - tau * dt * rvz)) >= ZERO else -ONE
                vx, vy, vz, wx, wy, wz = racket_bounce(sc, rot, j, side, px, py, pz, rvx_c, ZERO, rvz,
                                                       vx, vy, vz, wx, wy, wz)
            px, py, pz, vx, vy, vz = finish(sc, re_ref, sp_tab, cd_tab, v_ref, mag, px, py, pz, vx, vy, vz,
                                            wx, wy, wz, (ONE - tau) * dt)
        store(state, i, px, py, pz, vx, vy, vz, wx, wy, wz)
        status[i] = code

    return run_ball


def make_lean_physics(jit):
    """The lean single-ball rollout, built with decorator ``jit``: flight + table as one writes it for speed.

    RK4 flight and the table as the plane z = r over the playing surface, met where a step's end
    points straddle it: the time of impact is the linear zero of the height, the state at impact
    the linear interpolation of the end points. The bounce and the rest of the step are the full
    loop's (:func:`make_stages`). A ball stops where a step ends below the floor plane or outside
    the play box, or at rest after a bounce. No Hermite time of impact, no table edges or sides,
    no net, no rackets.

    Returns:
        ``run_ball`` with the signature of :func:`make_physics`'s (``rackets`` and ``rot`` unused).
    """
    _, _, _, rk4, finish, table_bounce, load, store = make_stages(jit, bracket=True)

    @jit
    def run_ball(i, state, n_steps, dt, rackets, sc, re_ref, sp_tab, cd_tab, v_ref, mag, res, rot,
                 status, first):
        """Rolls ball ``i`` of ``state`` (B, 9) on for ``n_steps``; writes state, status, first bounce."""
        px, py, pz, vx, vy, vz, wx, wy, wz = load(state, i)
        r = sc[I_R]
        low = sc[I_FLOOR] + r
        code = NONE
        bounced = False
        for _ in range(n_steps):
            q = rk4(sc, re_ref, sp_tab, cd_tab, v_ref, mag, px, py, pz, vx, vy, vz, wx, wy, wz, dt)
            if q[2] < r and pz >= r:
                tau = (pz - r) / (pz - q[2])
                hx, hy, hvz = px + tau * (q[0] - px), py + tau * (q[1] - py), vz + tau * (q[5] - vz)
                if hvz < ZERO and abs(hx) <= sc[I_HALF_L] and abs(hy) <= sc[I_HALF_W]:
                    if not bounced:
                        first[i, 0], first[i, 1], first[i, 2] = hx, hy, r
                        bounced = True
                    vx, vy, vz, wx, wy, wz = table_bounce(sc, res, vx + tau * (q[3] - vx), vy + tau * (q[4] - vy),
                                                          hvz, wx, wy, wz)
                    px, py, pz = hx, hy, r
                    if abs(vz) < REST_SPEED:
                        code = REST
                        break
                    px, py, pz, vx, vy, vz = finish(sc, re_ref, sp_tab, cd_tab, v_ref, mag, px, py, pz, vx, vy, vz,
                                                    wx, wy, wz, (ONE - tau) * dt)
                    continue
            px, py, pz, vx, vy, vz = q
            if pz < low:
                code = FLOOR
                break
            if abs(px) > BOX_X or abs(py) > BOX_Y or abs(pz) > BOX_Z:
                code = OUT
                break
        store(state, i, px, py, pz, vx, vy, vz, wx, wy, wz)
        status[i] = code

    return run_ball


# numpy's error model, as on CUDA: a division by zero gives inf or nan instead of a check for a Python
# exception at every division (the lean loop runs about 15 % faster, the full one as fast as before)
_run_ball_cpu = make_physics(njit(error_model="numpy"))
_run_lean_cpu = make_lean_physics(njit(error_model="numpy"))


def _parallel(run_ball):
    """``run_ball`` over every ball of the batch, ``prange`` over balls."""

    @njit(parallel=True)
    def rollout(state, n_steps, dt, rackets, sc, re_ref, sp_tab, cd_tab, v_ref, mag, res, rot, status, first):
        for i in prange(state.shape[0]):
            run_ball(i, state, n_steps, dt, rackets, sc, re_ref, sp_tab, cd_tab, v_ref, mag, res, rot, status, first)

    return rollout


_ROLLOUT_CPU = {False: _parallel(_run_ball_cpu), True: _parallel(_run_lean_cpu)}  # keyed by ``lean``


def _outputs(balls):
    state = np.ascontiguousarray(np.concatenate([np.asarray(balls.pos), np.asarray(balls.vel),
                                                 np.asarray(balls.spin)], axis=-1), np.float32)
    b = state.shape[0]
    return state, np.zeros(b, np.int32), np.full((b, 3), np.nan, np.float32)


def _check_lean(lean: bool, rackets: bool) -> None:
    if lean and rackets:
        raise ValueError("the lean loop is flight + table only: no rackets")


def rollout_cpu(params: dict, balls, n_steps: int, dt: float, rackets: bool, lean: bool = False):
    """Rolls a batch on with the parallel CPU loop.

    Arguments:
        params: from :func:`pack_params`.
        balls: anything with (B, 3) ``pos``, ``vel``, ``spin``.
        n_steps, dt: steps and step length [s].
        rackets: whether the two tracking rackets play.
        lean: the lean loop (:func:`make_lean_physics`, flight + table only) instead of the full one.

    Returns:
        (state (B, 9), status (B,), first table bounce (B, 3), NaN where none).
    """
    _check_lean(lean, rackets)
    state, status, first = _outputs(balls)
    _ROLLOUT_CPU[lean](state, n_steps, F(dt), rackets, params["scalars"], params["re_ref"], params["sp"], params["cd"],
                       params["v_ref"], params["mag"], params["residual"], params["rot"], status, first)
    return state, status, first


def cuda_available() -> bool:
    try:
        return bool(cuda.is_available())
    except Exception:  # numba without its CUDA part, or a broken driver: no CUDA peer
        return False


_cuda_cache: dict = {}


def _cuda_kernel(lean: bool):
    if lean not in _cuda_cache:
        # ``cuda`` must stay a module global inside the kernel: numba's CUDA simulator swaps it there
        run_ball = (make_lean_physics if lean else make_physics)(cuda.jit(device=True))

        @cuda.jit
        def kernel(state, n_steps, dt, rackets, sc, re_ref, sp_tab, cd_tab, v_ref, mag, res, rot, status, first):
            i = cuda.grid(1)
            if i < state.shape[0]:
                run_ball(i, state, n_steps, dt, rackets, sc, re_ref, sp_tab, cd_tab, v_ref, mag, res, rot,
                         status, first)

        _cuda_cache[lean] = kernel
    return _cuda_cache[lean]


def rollout_cuda(params: dict, balls, n_steps: int, dt: float, rackets: bool, threads: int = 128,
                 lean: bool = False):
    """The same rollout as :func:`rollout_cpu`, one CUDA thread per ball (needs a GPU)."""
    _check_lean(lean, rackets)
    state, status, first = _outputs(balls)
    d = {k: cuda.to_device(v) for k, v in params.items()}
    d_state, d_status, d_first = cuda.to_device(state), cuda.to_device(status), cuda.to_device(first)
    blocks = (state.shape[0] + threads - 1) // threads
    _cuda_kernel(lean)[blocks, threads](d_state, n_steps, F(dt), rackets, d["scalars"], d["re_ref"], d["sp"],
                                        d["cd"], d["v_ref"], d["mag"], d["residual"], d["rot"], d_status, d_first)
    cuda.synchronize()
    return d_state.copy_to_host(), d_status.copy_to_host(), d_first.copy_to_host()


VERSION = numba.__version__
