"""ReturnBall: the functional environment (gymnax / brax style) of returning an opponent's shot.

The opponent plays from the -x end (a ball from a bank of realistic shots, ``ttsim_jax.shots``);
the agent's kinematic racket (:mod:`.racket`) defends the +x end. Each control step advances the
kernel's resumable :func:`~ttsim_jax.kernel.rollout.rollout` by ``substeps`` physics steps with the
racket schedule of that period, then reads the step's event log to follow the rally (the rules are
:mod:`.rally_rules`'s):

* the ball must bounce once on the agent's half (x > 0), then meet the racket (a contact before that
  bounce is a volley, a second bounce or a fall a miss);
* after the contact, the next table contact must be on the opponent's half (x < 0): a legal return,
  which ends the episode; the net, the agent's own half, the floor, leaving play or a second
  contact end it as a fault.

Everything is batched over a leading axis of ``num_envs`` environments (one ball per environment:
the kernel's batch axis) and pure: ``reset(key, params) -> (obs, state)`` and
``step(key, state, action, params) -> (obs, state, reward, terminated, truncated, info)``, with the
automatic reset of finished environments inside (:meth:`ReturnBall.step`; :meth:`ReturnBall.step_env`
without it). Both jit and vmap (e.g. over keys); :class:`~ttsim_jax.env.single.SingleReturnBall`
is one environment without the batch axis, for the user to vmap as in gymnax. Environments of
equal settings are equal (and hash alike), so they share their compiled programs.

Reward of a step (weights in ``[reward]`` of the task file):
``contact`` on the first legal racket contact; on a legal return ``legal + target * max(0, 1 - d /
target_scale)`` with d the landing point's distance to the episode's target (``target_point``, or a
point drawn within ``target_spread`` of it at each reset); ``net``, ``out``, ``miss``
on those faults; minus ``motion`` times the mean squared commanded acceleration (fraction of its
limit); plus ``approach`` times the reduction of the ball-racket distance before the contact. A
shot of the opponent that never reaches the agent's half ends the episode with no reward and is
counted apart (``info["outcome"] == SHOT_FAULT``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ttsim_jax.files.cache import compile_notice, enable_compilation_cache
from ttsim_jax.env import intercept
from ttsim_jax.env import racket as racket_kin
from ttsim_jax.env.bank import shot_bank
from ttsim_jax.env.config import ShotsConfig, TaskConfig, load_task_config
from ttsim_jax.env.rally_rules import LEGAL, MISS, NET, OUT, RUNNING, SHOT_FAULT, VOLLEY, Rally, advance
from ttsim_jax.env.spaces import OBS_BOUND, observation_fields
from ttsim_jax.kernel import Execution, RallyState, Record, init_state, per_ball_axes, rollout
from ttsim_jax.params import ConfigError, Model, load_model
from ttsim_jax.physics.numerics import safe_norm
from ttsim_jax.state import Ball

# The step info of an episode's first observation, where nothing has happened yet (``shot_type``
# aside, which is the episode's own).
RESET_INFO = {"outcome": RUNNING, "legal": False, "contact": False, "landing_error": -1.0}
# Slots of the event log of one control step (10 ms hold two or three events at most).
MAX_EVENTS = 4
# New episodes made per step by :meth:`ReturnBall.step`: for B / RESET_FRACTION environments, at
# least RESET_MIN_ROWS (an episode lasts 50-200 steps, so a step ends about B / 100 of them).
RESET_FRACTION, RESET_MIN_ROWS = 16, 8
# The kernel's contact buffer: B / CONTACT_FRACTION rows, at least CONTACT_MIN_ROWS (the kernel's
# default is B / 32). At 4,096 environments of the default task a kernel step flags about 50 balls
# (median; 90th percentile 91, at most 136: 32 near the table, 13 near the racket, 7 crossing the
# net); the buffer's cost grows with its rows, and a step with more runs it again: 32 rows made
# the 10 steps of a control step about a tenth faster than 128.
CONTACT_FRACTION, CONTACT_MIN_ROWS = 128, 8
# Cap of the ball-racket distance in the approach term [m].
APPROACH_CAP = 3.0


@struct.dataclass
class EnvState:
    """State of a batch of environments.

    Attributes:
        rally: the kernel's :class:`~ttsim_jax.kernel.state.RallyState` (B balls).
        racket: :class:`~ttsim_jax.env.racket.RacketState` with (B, ...) fields.
        progress: :class:`Rally`.
        model_values: (B, P) this episode's randomised model parameters (``[randomisation]`` order).
        shot: (B,) index of the incoming shot in the bank.
        t: (B,) control steps taken in the episode.
        distance: (B,) ball-racket distance after the last step [m].
        seen: :class:`Ball` with (B, L + 1, 3) fields: the ball as measured (observation noise
            included) at the end of each of the last L + 1 control steps, oldest first, L the
            configured ``latency_steps``; the policy (and the intercept tracker) see the oldest.
        plan: with ``[observation] plan``, (B, 8) the tracker's prediction from the ball seen now
            (:func:`~ttsim_jax.env.intercept.predict`: point, velocity, time to it, valid as 0 / 1),
            made once when the state is made and read by the observation and by the next step's
            tracker; (B, 0) otherwise.
        target: (B, 2) the episode's target point (x, y) [m]: ``[reward] target_point``, or drawn
            uniformly within ``target_spread`` of it at the reset.
    """

    rally: RallyState
    racket: racket_kin.RacketState
    progress: Rally
    model_values: jnp.ndarray
    shot: jnp.ndarray
    t: jnp.ndarray
    distance: jnp.ndarray
    seen: Ball
    plan: jnp.ndarray
    target: jnp.ndarray


@struct.dataclass
class EnvParams:
    """Everything a reset or a step reads that may change without recompiling.

    Attributes:
        model: the simulator :class:`~ttsim_jax.params.Model` (randomised leaves are replaced per
            environment at each step).
        shots: :class:`Ball` (S, 3) bank of incoming shots; shot_type: (S,) index into ``shot_types``.
        rand_lo, rand_hi: (P,) ranges of the randomised parameters, or mean and standard deviation
            where ``rand_normal`` (P,) is set.
        limits: :class:`~ttsim_jax.env.racket.RacketLimits`; start, start_jitter: (3,) racket start.
        noise: (2,) std of the observed ball position [m] and velocity [m/s].
        reward: dict of reward weights (see the module docstring); target: (2,) target point;
            target_spread: (2,) half-widths of the box each episode's target is drawn in [m].
        intercept: :class:`~ttsim_jax.env.intercept.InterceptParams` (read in "intercept" mode).
    """

    model: Model
    shots: Ball
    shot_type: jnp.ndarray
    rand_lo: jnp.ndarray
    rand_hi: jnp.ndarray
    rand_normal: jnp.ndarray
    limits: racket_kin.RacketLimits
    start: jnp.ndarray
    start_jitter: jnp.ndarray
    noise: jnp.ndarray
    reward: dict
    target: jnp.ndarray
    target_spread: jnp.ndarray
    intercept: intercept.InterceptParams


def _set_leaf(model, path: str, value):
    """``model`` with the leaf at the dotted ``path`` replaced by ``value``."""
    head, _, rest = path.partition(".")
    child = getattr(model, head)
    return model.replace(**{head: _set_leaf(child, rest, value) if rest else value})


class ReturnBall:
    """The ReturnBall task for ``num_envs`` environments: static settings plus pure functions.

    Arguments:
        config: a :class:`~ttsim_jax.env.config.TaskConfig`, a task file path or bundled task name
            (default ``return_ball``).
        num_envs: environments (balls) stepped together.
        block_size: the kernel's ``block_size`` (default: its own choice).
        reference: run the kernel's reference step (exact detection for every ball; same results);
            default: for batches of up to 64 environments, where it costs little and compiles about
            a third faster than the lean step.

    Attributes:
        obs_dim, action_dim: sizes of one environment's observation and action.
    """

    action_dim = 5

    def __init__(self, config: TaskConfig | str | None = None, num_envs: int = 1, block_size: int | None = None,
                 reference: bool | None = None):
        self.config = config if isinstance(config, TaskConfig) else load_task_config(config)
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be positive, got {num_envs}")
        self.num_envs = int(num_envs)
        self.block_size = block_size
        self.reference = self.num_envs <= 64 if reference is None else bool(reference)
        self.reset_rows = min(self.num_envs, max(RESET_MIN_ROWS, -(-self.num_envs // RESET_FRACTION)))
        self.contact_capacity = min(self.num_envs, max(CONTACT_MIN_ROWS, -(-self.num_envs // CONTACT_FRACTION)))
        self.substeps = self.config.substeps
        self.max_steps = self.config.max_steps
        self.period = 1.0 / self.config.control.rate_hz
        self.paths = tuple(r[0] for r in self.config.randomisation)
        self.obs_dim = len(observation_fields(self.config.observation))
        self.latency = self.config.observation.latency_steps
        self._params = None
        # what the compiled programs depend on: the task's settings (not the file they were read
        # from, nor where the bank's shots come from: the bank is a parameter), the batch and the
        # kernel's options (hashed once: jit hashes it at every call)
        self._identity = (dataclasses.replace(self.config, source="", shots=ShotsConfig(bank=self.config.shots.bank)),
                          self.num_envs, self.block_size, self.reference)
        self._hash = hash(self._identity)
        # environments made after this one (in another process too) load its compiled programs
        enable_compilation_cache()

    def resized(self, num_envs: int) -> "ReturnBall":
        """The same task over ``num_envs`` environments, on the kernel path of this one (a device's
        share of a batch split over several: :func:`ttsim_jax.rl.distributed.per_shard`); it takes
        this one's parameters."""
        return ReturnBall(self.config, num_envs, block_size=self.block_size, reference=self.reference)

    def __eq__(self, other) -> bool:
        return type(other) is type(self) and other._identity == self._identity

    def __hash__(self) -> int:
        # jit takes the environment as a static argument: equal settings share one compiled program
        return self._hash

    # ------------------------------------------------------------------ parameters
    def default_params(self) -> EnvParams:
        """The task file's parameters (the shot bank is drawn, and aimed, on the first call)."""
        if self._params is None:
            self._params = self._make_params(draw=True)
        return self._params

    def sizing_params(self) -> EnvParams:
        """The task file's parameters with a blank shot bank of the configured size (zeros, not drawn
        or aimed): their shapes are :meth:`default_params`'s, for sizing a job before it is refused
        or built (drawing and aiming the bank takes 20 s and more on a cold cache)."""
        if self._params is not None:
            return self._params
        return self._make_params(draw=False)

    def _make_params(self, draw: bool) -> EnvParams:
        c = self.config
        # a residual checkpoint holds float32 arrays, as the environment's model
        model = load_model(c.model, dtype=jnp.float32, residual=c.residual.checkpoint or None,
                           racket=c.racket_config or None)
        try:
            per_ball_axes(model, *self.paths)
        except ValueError as e:
            raise ConfigError(f"{c.source}: [randomisation] {e}") from None
        for path in self.paths:
            leaf = model
            for name in path.split("."):
                leaf = getattr(leaf, name)
            if not hasattr(leaf, "shape") or jnp.ndim(leaf) != 0:
                raise ConfigError(f"{c.source}: [randomisation] {path!r} is not a scalar model parameter")
        if draw:  # the flight has no racket: one bank
            shots, types = shot_bank(model.replace(residual=None), c)
        else:
            blank = np.zeros((c.shots.bank, 3), np.float32)
            shots, types = Ball(pos=blank, vel=blank, spin=blank), np.zeros(c.shots.bank, np.int32)
        r = c.racket
        f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
        limits = racket_kin.RacketLimits(
            lo=f32(r.workspace_lo), hi=f32(r.workspace_hi), max_speed=f32(r.max_speed), max_accel=f32(r.max_accel),
            angle_lo=f32(r.angle_lo), angle_hi=f32(r.angle_hi), max_rate=f32(r.max_angle_rate),
            max_angle_accel=f32(r.max_angle_accel), face=f32(r.face),
            # the playing surface is z = 0 of the world frame; the agent's half ends at length / 2
            table_x=f32(0.5 * model.table.length), table_z=f32(r.table_clearance))
        if float(racket_kin.clip_workspace(limits, f32(r.start))[2]) != float(f32(r.start[2])):
            raise ConfigError(f"{c.source}: [racket] start = {list(r.start)} lies over the table below "
                              f"table_clearance = {r.table_clearance} (the table ends at x = "
                              f"{0.5 * float(model.table.length)} m)")
        w = c.reward
        half_l, half_w = 0.5 * float(model.table.length), 0.5 * float(model.table.width)
        (x, y), (dx, dy) = w.target_point, w.target_spread
        if not (-half_l < x - dx and x + dx < 0.0 and abs(y) + dy < half_w):
            raise ConfigError(f"{c.source}: [reward] target_point = {list(w.target_point)} with target_spread = "
                              f"{list(w.target_spread)} reaches beyond the opponent's half of the table (x in "
                              f"({-half_l}, 0), |y| < {half_w} m): a legal return cannot land there")
        reward = {k: f32(getattr(w, k)) for k in ("contact", "legal", "target", "target_scale", "net", "out",
                                                  "miss", "motion", "approach")}
        return EnvParams(
            model=model, shots=jax.tree.map(f32, shots), shot_type=jnp.asarray(types),
            rand_lo=f32([r[1] for r in c.randomisation]), rand_hi=f32([r[2] for r in c.randomisation]),
            rand_normal=jnp.asarray([r[3] == "normal" for r in c.randomisation], bool),
            limits=limits, start=f32(r.start), start_jitter=f32(r.start_jitter),
            noise=f32([c.observation.noise_pos, c.observation.noise_vel]), reward=reward,
            target=f32(w.target_point), target_spread=f32(w.target_spread),
            intercept=intercept.intercept_params(self._planning_model(model), c))

    def _planning_model(self, model: Model) -> Model:
        """The model the tracker plans its stroke with: the task's, or, with a ``racket_config`` and
        ``[intercept] racket_known = false``, the same with the model's own racket (a robot that does
        not know the rubber it plays with)."""
        c = self.config
        if not c.racket_config or c.intercept.racket_known:
            return model
        return model.replace(racket=load_model(c.model, dtype=jnp.float32).racket)

    def draw_model_values(self, key, lo, hi, normal, n: int | None = None):
        """(n, P) randomised parameter values (n: default ``num_envs``): uniform in [lo, hi], or where
        ``normal`` (P,) is set, a normal law of mean ``lo`` and standard deviation ``hi`` truncated
        at three deviations."""
        shape = (self.num_envs if n is None else n, len(self.paths))
        u = jax.random.uniform(key, shape, jnp.float32)
        z = jax.random.truncated_normal(jax.random.fold_in(key, 1), -3.0, 3.0, shape, jnp.float32)
        return jnp.where(normal, lo + z * hi, lo + u * (hi - lo))

    def model_for(self, params: EnvParams, values):
        """(model with the randomised leaves set to ``values`` (B, P), its ``model_axes``)."""
        model = params.model
        for i, path in enumerate(self.paths):
            model = _set_leaf(model, path, values[:, i].astype(jnp.float32))
        return model, per_ball_axes(params.model, *self.paths)

    # ------------------------------------------------------------------ reset
    def reset(self, key, params: EnvParams):
        """Fresh episodes for all environments.

        Arguments:
            key: PRNG key. params: :class:`EnvParams`.

        Returns:
            (obs (B, obs_dim) float32, :class:`EnvState`).
        """
        return self._fresh(key, params, jnp.arange(self.num_envs, dtype=jnp.int32))

    def _fresh(self, key, params: EnvParams, ids):
        """(obs, :class:`EnvState`) of new episodes for the environments ``ids`` (n,): n rows, the
        kernel's ball ids those of the environments (its random draws follow a ball's id)."""
        b = ids.shape[0]
        k_shot, k_pos, k_rand, k_obs = jax.random.split(key, 4)
        shot = jax.random.randint(k_shot, (b,), 0, params.shots.pos.shape[0])
        ball = jax.tree.map(lambda a: a[shot], params.shots)
        pos = params.start + params.start_jitter * jax.random.uniform(k_pos, (b, 3), jnp.float32, -1.0, 1.0)
        pos = racket_kin.clip_workspace(params.limits, pos)
        zeros2 = jnp.zeros((b, 2), jnp.float32)
        rk = racket_kin.RacketState(pos=pos, vel=jnp.zeros_like(pos), angle=zeros2, rate=zeros2)
        values = self.draw_model_values(k_rand, params.rand_lo, params.rand_hi, params.rand_normal, b)
        progress = Rally(bounced=jnp.zeros(b, bool), hit=jnp.zeros(b, bool), outcome=jnp.zeros(b, jnp.int32),
                         landing=jnp.zeros((b, 2), jnp.float32))
        # nothing older than the first measurement exists: the history starts filled with it
        seen = jax.tree.map(lambda a: jnp.repeat(a[:, None], self.latency + 1, axis=1), measure(k_obs, ball, params))
        # a key of its own (not a fifth split): the other draws stay those of a task without a spread
        target = params.target + params.target_spread * jax.random.uniform(
            jax.random.fold_in(key, 5), (b, 2), jnp.float32, -1.0, 1.0)
        state = EnvState(rally=init_state(ball, ball_id=ids), racket=rk, progress=progress, model_values=values,
                         shot=shot, t=jnp.zeros(b, jnp.int32), distance=self._distance(ball, rk), seen=seen, plan=None,
                         target=target)
        state = state.replace(plan=self.plan(state, params))
        return self.observe(state), state

    @staticmethod
    def _distance(ball: Ball, rk):
        return jnp.minimum(safe_norm(ball.pos - rk.pos), APPROACH_CAP)

    # ------------------------------------------------------------------ observation
    def seen_ball(self, state: EnvState) -> Ball:
        """(B, 3) fields: the ball as the agent sees it now: measured ``latency_steps`` control
        steps ago, with the observation noise (spin zero when it is not observed)."""
        ball = jax.tree.map(lambda a: a[:, 0], state.seen)
        return ball if self.config.observation.spin else ball.replace(spin=jnp.zeros_like(ball.spin))

    def plan(self, state: EnvState, params: EnvParams):
        """:attr:`EnvState.plan` of ``state`` (whose other fields are set): (B, 8) or (B, 0)."""
        if not self.config.observation.plan:
            return jnp.zeros((state.t.shape[0], 0), jnp.float32)
        ball = self.seen_ball(state)
        point, v_hit, t_hit, valid = intercept.predict(params.intercept, ball.pos, ball.vel, state.progress.bounced,
                                                       ball.spin)
        return jnp.concatenate([point, v_hit, t_hit[:, None], valid[:, None]], -1).astype(jnp.float32)

    @property
    def observation_fields(self) -> tuple:
        """(name, unit) of each entry of an observation, in :meth:`observe`'s order
        (:func:`~ttsim_jax.env.spaces.observation_fields`): ``obs[:, env.observation_names.index(
        "racket.pos.z")]`` picks one."""
        return observation_fields(self.config.observation)

    @property
    def shot_type_names(self) -> tuple:
        """What ``info["shot_type"]`` codes: the task's ``[shots] types``, by index."""
        return tuple(self.config.shots.types)

    @property
    def observation_names(self) -> tuple:
        """The name of each entry of an observation (:attr:`observation_fields`)."""
        return tuple(n for n, _ in self.observation_fields)

    def observe(self, state: EnvState):
        """(B, obs_dim) float32: ball position, velocity / 10 [, spin / 300] (as
        :meth:`seen_ball`: noisy and ``latency_steps`` control steps old), racket position,
        velocity / 10, angles, angle rates / 10, ball minus racket position, time [s], bounced,
        hit (the racket's state and the rally's progress are current) [, with ``[observation] plan``:
        the tracker's predicted hit point, velocity there / 10, time to it [s] and whether one
        exists (:attr:`EnvState.plan`, the prediction from the seen ball), 0 where none does]
        [, with ``[observation] target``: the episode's target point (x, y) [m]].

        Every entry is finite (a non-finite state reads 0) and within +-1e3."""
        ball, rk = self.seen_ball(state), state.racket
        pos = ball.pos
        parts = [pos, ball.vel / 10.0]
        if self.config.observation.spin:
            parts.append(ball.spin / 300.0)
        parts += [rk.pos, rk.vel / 10.0, rk.angle, rk.rate / 10.0, pos - rk.pos,
                  (state.t.astype(jnp.float32) * self.period)[:, None],
                  state.progress.bounced[:, None].astype(jnp.float32), state.progress.hit[:, None].astype(jnp.float32)]
        if self.config.observation.plan:
            # the hit the tracker aims at: the stroke's adjustments depend on it more simply than on the ball
            keep = state.plan[:, 7:] > 0.5
            parts += [jnp.where(keep, state.plan[:, :3], 0.0), jnp.where(keep, state.plan[:, 3:6] / 10.0, 0.0),
                      jnp.where(keep, state.plan[:, 6:7], 0.0), keep.astype(jnp.float32)]
        if self.config.observation.target:
            parts.append(state.target)
        obs = jnp.concatenate([p.astype(jnp.float32) for p in parts], axis=-1)
        return jnp.clip(jnp.nan_to_num(obs, nan=0.0, posinf=OBS_BOUND, neginf=-OBS_BOUND), -OBS_BOUND, OBS_BOUND)

    # ------------------------------------------------------------------ step
    def step_env(self, key, state: EnvState, action, params: EnvParams):
        """One control step of every environment, without the automatic reset.

        Arguments:
            key: PRNG key; state: :class:`EnvState`; action: (B, 5) in [-1, 1]: in "accel" mode the
            racket's accelerations (:func:`~ttsim_jax.env.racket.command`), in "intercept" mode the
            stroke (:func:`~ttsim_jax.env.intercept.stroke`); params: :class:`EnvParams`.

        Returns:
            (obs, state, reward (B,), terminated (B,), truncated (B,), info): info holds
            ``outcome`` (B,) int (``OUTCOME_NAMES``), ``legal`` (B,), ``landing_error`` (B,) [m]
            (-1 unless legal), ``contact`` (B,) and ``shot_type`` (B,).
        """
        k_phys, k_obs = jax.random.split(key)
        action = jnp.asarray(action, jnp.float32)
        if action.shape != (self.num_envs, self.action_dim):
            raise ValueError(f"action of shape {action.shape}: expected ({self.num_envs}, {self.action_dim}), one "
                             f"action of {self.action_dim} numbers in [-1, 1] for each of the {self.num_envs} "
                             "environments")
        if self.config.control.action == "intercept":
            # the tracker reads the ball as the policy sees it (noise and latency included)
            seen = self.seen_ball(state)
            if self.config.observation.plan:  # made with the state, from the same ball
                pred = (state.plan[:, :3], state.plan[:, 3:6], state.plan[:, 6], state.plan[:, 7] > 0.5)
            else:
                pred = intercept.predict(params.intercept, seen.pos, seen.vel, state.progress.bounced, seen.spin)
            action = intercept.track(params.intercept, params.limits, params.start, state.target, state.racket,
                                     pred, seen.spin, state.progress.hit, action)
        rk, schedule, effort = racket_kin.command(params.limits, state.racket, action, self.period, self.substeps)
        # (T, B, 1, ...) as the rollout takes it, (B, T, 1, ...): the two transpositions cancel
        schedule = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), schedule)
        model, axes = self.model_for(params, state.model_values)
        # the clock restarts each control step: the kernel's time stays small and exact
        rally = state.rally.replace(step=jnp.zeros_like(state.rally.step), t0=jnp.zeros_like(state.rally.t0))
        rally, out = rollout(model, rally, self.substeps, self.config.control.physics_dt, schedule,
                             model_axes=axes, record=Record(max_events=MAX_EVENTS),
                             sample_key=k_phys if self.config.residual.sample else None,
                             execution=Execution(remat=False, block_size=self.block_size, reference=self.reference,
                                                 contact_capacity=self.contact_capacity))
        before = state.progress
        progress = before
        log = out.events
        for j in range(MAX_EVENTS):
            progress = advance(progress, log.kind[:, j], log.pre.pos[:, j], j < log.count)
        # a ball the kernel stopped with nothing to say (a full log) ends as what it would be
        stopped = ~rally.alive & (progress.outcome == RUNNING)
        progress = progress.replace(outcome=jnp.where(
            stopped, jnp.where(progress.hit, OUT, jnp.where(progress.bounced, MISS, SHOT_FAULT)), progress.outcome))
        contact = progress.hit & ~before.hit
        ended = (progress.outcome != RUNNING) & (before.outcome == RUNNING)
        distance = self._distance(rally.ball, rk)
        w = params.reward
        err = jnp.linalg.norm(progress.landing - state.target, axis=-1)
        legal = progress.outcome == LEGAL
        outcome_reward = jnp.select(
            [legal, progress.outcome == NET, progress.outcome == OUT,
             (progress.outcome == MISS) | (progress.outcome == VOLLEY)],
            [w["legal"] + w["target"] * jnp.maximum(0.0, 1.0 - err / w["target_scale"]), w["net"], w["out"],
             w["miss"]], 0.0)
        approach = jnp.where(before.hit, 0.0, state.distance - jnp.where(contact, state.distance, distance))
        reward = (w["contact"] * contact + jnp.where(ended, outcome_reward, 0.0) - w["motion"] * effort
                  + w["approach"] * approach)
        t = state.t + 1
        terminated = progress.outcome != RUNNING
        truncated = ~terminated & (t >= self.max_steps)
        seen = jax.tree.map(lambda h, now: jnp.concatenate([h[:, 1:], now[:, None]], 1), state.seen,
                            measure(k_obs, rally.ball, params))
        state = EnvState(rally=rally, racket=rk, progress=progress, model_values=state.model_values,
                         shot=state.shot, t=t, distance=distance, seen=seen, plan=None, target=state.target)
        state = state.replace(plan=self.plan(state, params))
        info = {"outcome": progress.outcome, "legal": legal, "contact": contact,
                "landing_error": jnp.where(legal, err, -1.0), "shot_type": params.shot_type[state.shot]}
        reward = jnp.nan_to_num(reward.astype(jnp.float32), nan=0.0, posinf=0.0, neginf=0.0)
        return self.observe(state), state, reward, terminated, truncated, info

    def step(self, key, state: EnvState, action, params: EnvParams):
        """:meth:`step_env`, then finished environments (terminated or truncated) start afresh.

        Returns:
            As :meth:`step_env`; for a finished environment, obs and state are those of its new
            episode and ``info["final_obs"]`` holds the last observation of the finished one
            (``info["final_obs"]`` is the plain observation elsewhere).
        """
        k_step, k_reset = jax.random.split(key)
        obs, nxt, reward, terminated, truncated, info = self.step_env(k_step, state, action, params)
        done = terminated | truncated
        obs_r, fresh = self._restarts(k_reset, params, done)
        info = dict(info, final_obs=obs)
        return jnp.where(done[:, None], obs_r, obs), select(done, fresh, nxt), reward, terminated, truncated, info

    def _restarts(self, key, params: EnvParams, done):
        """(obs, :class:`EnvState`) of new episodes where ``done`` (B,) is set (anything elsewhere).

        A step ends a few episodes out of thousands, so new ones are made for ``reset_rows`` rows
        (B / RESET_FRACTION) and each finished environment takes one of them; a step that ends more
        makes them for every environment, as :meth:`reset`. Making them for every environment at
        every step (the tracker's prediction included) cost a fifth of a step's time.
        """
        rows = self.reset_rows
        if rows >= self.num_envs:
            return self.reset(key, params)

        def few():
            ids = jnp.nonzero(done, size=rows, fill_value=0)[0].astype(jnp.int32)
            obs, fresh = self._fresh(key, params, ids)
            slot = jnp.clip(jnp.cumsum(done) - 1, 0, rows - 1)
            return obs[slot], jax.tree.map(lambda a: a if a.ndim == 0 else a[slot], fresh)

        return jax.lax.cond(jnp.sum(done) > rows, lambda: self.reset(key, params), few)


def select(mask, where_set: EnvState, elsewhere: EnvState) -> EnvState:
    """The environments of ``where_set`` where ``mask`` (B,) is set, of ``elsewhere`` elsewhere; the
    kernel's batch-wide clock (``rally.step``, ``t0``, ``dt``) is ``elsewhere``'s: a fresh ball
    resumes the running kernel state, not a new rally."""
    def pick(a, b):
        if a.ndim == 0:  # batch-wide scalars (the kernel's clock)
            return b
        return jnp.where(mask.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)

    return jax.tree.map(pick, where_set, elsewhere)


def measure(key, ball: Ball, params: EnvParams) -> Ball:
    """The ball as the sensors measure it: position and velocity with the configured Gaussian noise
    (``params.noise``), spin as it is."""
    k_p, k_v = jax.random.split(key)
    return ball.replace(pos=ball.pos + params.noise[0] * jax.random.normal(k_p, ball.pos.shape, jnp.float32),
                        vel=ball.vel + params.noise[1] * jax.random.normal(k_v, ball.vel.shape, jnp.float32))


def _key(key):
    """A key as the compiled functions expect it (a uint32 pair); actions are cast to float32 alike,
    so that a float64 or integer action does not compile the step anew."""
    return jnp.asarray(key, jnp.uint32)


_reset = jax.jit(lambda env, key, params: env.reset(key, params), static_argnums=(0,))
_step = jax.jit(lambda env, key, state, action, params: env.step(key, state, action, params), static_argnums=(0,))
_step_env = jax.jit(lambda env, key, state, action, params: env.step_env(key, state, action, params),
                    static_argnums=(0,))
_select = jax.jit(select)

# First-call compile times of the default (intercept) task on 2 busy CPU cores [s], cold cache: what
# the one-line notice announces (one environment's reset 12 s and step 82 s, see docs/rl.md; the
# step with the reset inside compiles both).
COMPILE_S = {"reset": 15.0, "step": 100.0, "step without reset": 90.0}
_compiled: set = set()


def _call(name: str, fn, env: ReturnBall, *args):
    """``fn(env, *args)``; its first call for an environment's settings in this process prints one
    line if it is still compiling after a few seconds."""
    what = (name, env._identity)  # not the environment: the set keeps no shot bank alive
    if what in _compiled:
        return fn(env, *args)
    n = env.num_envs
    with compile_notice(f"the ReturnBall {name} ({n} environment{'s' * (n > 1)})", COMPILE_S[name]):
        out = fn(env, *args)
    _compiled.add(what)
    return out


def jit_reset(env: ReturnBall, key, params):
    """Jitted :meth:`ReturnBall.reset`; environments of equal settings share the compiled program."""
    return _call("reset", _reset, env, _key(key), params)


def jit_step(env: ReturnBall, key, state, action, params):
    """Jitted :meth:`ReturnBall.step` (compiled once per settings, as :func:`jit_reset`)."""
    return _call("step", _step, env, _key(key), state, jnp.asarray(action, jnp.float32), params)


def jit_step_env(env: ReturnBall, key, state, action, params):
    """Jitted :meth:`ReturnBall.step_env` (compiled once per settings, as :func:`jit_reset`)."""
    return _call("step without reset", _step_env, env, _key(key), state, jnp.asarray(action, jnp.float32), params)


def jit_select(mask, where_set: EnvState, elsewhere: EnvState) -> EnvState:
    """Jitted :func:`select` (compiled in a second)."""
    return _select(jnp.asarray(mask), where_set, elsewhere)
