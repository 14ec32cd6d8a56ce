"""MuJoCo (and MJX) peer: free spheres with MuJoCo's ellipsoid fluid model bouncing on a box table.

Similar physics, not the same: MuJoCo's fluid model has its own drag and lift (Magnus) laws rather
than the paper's C_D(Re, Sp) and C_M(v, w) tables, its contact is soft (solref/solimp) rather than
the instantaneous restitution law with residual matrices, and it runs in float64. Flight + table
only; no rackets.

Many balls share one model (``chunk`` balls per model, batches run chunk after chunk): the balls
collide with the table only (contype/conaffinity), so the model is N independent balls.
"""

from __future__ import annotations

import numpy as np

import mujoco

RADIUS, MASS, DENSITY, VISCOSITY = 0.02, 2.7e-3, 1.204, 1.8e-5
# MuJoCo's ellipsoid-model coefficients (blunt drag, slender drag, angular drag, Kutta lift, Magnus
# lift). MuJoCo's default blunt drag 0.5 decelerates a spinless ball about twice as hard as the
# paper's C_D ~ 0.5 (8 m/s shot over 0.15 s: 17 cm short of vacuum against 9 cm), so 0.25. The
# model's added-mass term lifts a topspin ball as a Magnus coefficient of -0.5 would (with all lift
# coefficients zero, a 300 rad/s topspin ball rises 18 cm in 0.15 s), so a Magnus coefficient of
# 0.7 leaves a net 0.2, a typical value of the paper's C_M(v, w) table.
FLUIDCOEF = "0.25 0.25 1.5 1.0 0.7"
# The table's playing surface is z = 0 (ttsim_jax frame); ITTF 2.74 m x 1.525 m.
TABLE_HALF = (1.37, 0.7625, 0.02)


def model_xml(n_balls: int, dt: float = 1e-3) -> str:
    """MJCF of ``n_balls`` free spheres and a box table, RK4 at ``dt``.

    A contact time constant of 2 dt (MuJoCo's smallest stable one) with little damping gives a
    lively bounce; friction 0.25 is the table's mu.
    """
    balls = "\n".join(
        f'<body name="b{i}" pos="0 0 1"><freejoint/><geom type="sphere" size="{RADIUS}" mass="{MASS}" '
        f'shellinertia="true" fluidshape="ellipsoid" fluidcoef="{FLUIDCOEF}" contype="1" conaffinity="0" friction="0.25 0.005 0.0001" '
        f'solref="-200000 -1" solimp="0.99 0.99 0.001"/></body>' for i in range(n_balls))
    hx, hy, hz = TABLE_HALF
    return f"""<mujoco model="ttsim_peer">
  <option timestep="{dt}" integrator="RK4" density="{DENSITY}" viscosity="{VISCOSITY}" gravity="0 0 -9.81"/>
  <worldbody>
    <geom name="table" type="box" size="{hx} {hy} {hz}" pos="0 0 {-hz}" contype="0" conaffinity="1"
          friction="0.25 0.005 0.0001"/>
{balls}
  </worldbody>
</mujoco>"""


class MujocoPeer:
    """Batches of balls run through one compiled model of ``chunk`` balls.

    ``mujoco.rollout`` steps ``group`` chunks at a time on ``threads`` threads (faster here than a
    Python loop of ``mj_step``, 90k against 66k ball-steps/s on 2 cores); it records every step's
    state, so groups bound its memory.
    """

    def __init__(self, chunk: int = 64, dt: float = 1e-3, threads: int = 2, group: int = 16):
        self.chunk, self.group = chunk, group
        self.model = mujoco.MjModel.from_xml_string(model_xml(chunk, dt))
        self.data = mujoco.MjData(self.model)
        self.datas = [mujoco.MjData(self.model) for _ in range(threads)]
        self.spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.size = mujoco.mj_stateSize(self.model, self.spec)

    def _initial(self, pos, vel, spin):
        """Full-physics state of one chunk; unused balls are parked far below, at rest."""
        n = len(pos)
        qpos = np.zeros((self.chunk, 7))
        qpos[:, 2] = -100.0 - np.arange(self.chunk)  # parked balls never touch anything
        qpos[:, 3] = 1.0
        qvel = np.zeros((self.chunk, 6))
        qpos[:n, :3] = pos
        qvel[:n, :3] = vel
        qvel[:n, 3:] = spin  # a free joint's angular velocity is in the body frame: identity here
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = qpos.ravel()
        self.data.qvel[:] = qvel.ravel()
        state = np.empty(self.size)
        mujoco.mj_getState(self.model, self.data, state, self.spec)
        return state

    def rollout(self, balls, n_steps: int, track_bounce: bool = False):
        """Rolls ``balls`` ((B, 3) pos, vel, spin) on; returns (final pos (B, 3), first bounce (B, 3)).

        With ``track_bounce`` the first table bounce (the ball's lowest point where its vertical
        velocity turns from down to up, near the surface) is read from the recorded states (NaN rows
        without it, or where none).
        """
        from mujoco import rollout

        pos, vel, spin = (np.asarray(a, np.float64) for a in (balls.pos, balls.vel, balls.spin))
        b, c = len(pos), self.chunk
        nq = 7 * c
        final = np.zeros((b, 3))
        first = np.full((b, 3), np.nan)
        per_group = c * self.group
        for g0 in range(0, b, per_group):
            starts = list(range(g0, min(b, g0 + per_group), c))
            init = np.stack([self._initial(pos[s:s + c], vel[s:s + c], spin[s:s + c]) for s in starts])
            states, _ = rollout.rollout(self.model, self.datas, init, nstep=n_steps)
            for k, s in enumerate(starts):
                n = min(c, b - s)
                qpos = states[k, :, 1:1 + nq].reshape(n_steps, c, 7)[:, :n]
                final[s:s + n] = qpos[-1, :, :3]
                if track_bounce:
                    z = qpos[:, :, 2]
                    vz = states[k, :, 1 + nq:1 + nq + 6 * c].reshape(n_steps, c, 6)[:, :n, 2]
                    turn = (vz[:-1] < 0.0) & (vz[1:] >= 0.0) & (z[:-1] < RADIUS + 0.01)
                    has = turn.any(axis=0)
                    step = np.argmax(turn, axis=0)
                    low = qpos[step, np.arange(n), :3]
                    first[s:s + n] = np.where(has[:, None], low, np.nan)
        return final, first


def mjx_rollout_fn(n_balls: int, dt: float = 1e-3):
    """A jitted MJX rollout ``(qpos (B, 7), qvel (B, 6), n_steps) -> qpos`` of one-ball models, vmapped.

    ``n_steps`` is traced (a new step count does not recompile).

    Raises whatever MJX raises when it cannot run this model (the caller records why).
    """
    import jax
    from mujoco import mjx

    m = mujoco.MjModel.from_xml_string(model_xml(1, dt))
    mx = mjx.put_model(m)
    d0 = mjx.make_data(mx)

    def one(qpos, qvel, n_steps):
        d = d0.replace(qpos=qpos, qvel=qvel)
        d = jax.lax.fori_loop(0, n_steps, lambda _, x: mjx.step(mx, x), d)
        return d.qpos

    return jax.jit(jax.vmap(one, in_axes=(0, 0, None)))


VERSION = mujoco.__version__
