"""The games of the reality generator: rallies played lane by lane, chunk by chunk.

:class:`Game` runs every game of a configuration. Each game (session) has its own lane of one
batch simulated with :func:`ttsim_jax.kernel.simulate` in chunks of ``chunk_steps`` steps; between
chunks the host reads each lane's event log and trajectory and plays the rules: a toss and a serve
start a rally, a ball is hit after it bounced on the receiver's half when it reaches the receiver's
hitting distance, and a rally ends on the net, a miss, a bounce on the wrong half, or after a
planned number of shots. Racket contacts are chosen and aimed in :mod:`.strokes` and played through
:mod:`.inversion`. What the games record (observations and events with their true states) is
turned into a dataset by :mod:`.assembly`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax import effects as fx
from ttsim_jax.kernel import Record, simulate
from ttsim_jax.params import load_model, stack_models
from ttsim_jax.physics import events as ev
from ttsim_jax.physics.dimensions import TABLE_HALF_LENGTH
from ttsim_jax.shots import SHOT_TYPES
from ttsim_jax.state import Ball

from .config import GeneratorConfig
from .inversion import invert_batch, true_contact_batch
from .padding import bucket, pad
from .strokes import aim_shots, choose_shot, sample_contact_points

ROBOT, OPPONENT = 0, 1
PLAYERS = ("robot", "opponent")


def _jax_dtype(cfg: GeneratorConfig):
    return jnp.float64 if cfg.dtype == "float64" else jnp.float32


@jax.jit
def lane_models(stacked, index, time_origin):
    """Per-lane truth models: the sessions' models, with time-varying effects on each lane's clock.

    Arguments:
        stacked: the sessions' truth models, stacked (:func:`ttsim_jax.params.stack_models`).
        index: (B,) session of each lane.
        time_origin: (B,) session time [s] at which each lane's simulation starts.

    Returns:
        The (B,) batched models.
    """
    models = jax.tree.map(lambda a: a[index], stacked)
    effects = tuple(e.replace(time_origin=time_origin.astype(e.time_origin.dtype)) if hasattr(e, "time_origin") else e
                    for e in models.effects)
    return models.replace(effects=effects)


@dataclasses.dataclass
class _Session:
    sid: int
    rng: np.random.Generator
    n_rallies: int
    first_server: int
    models_index: int
    rally: int = -1
    obs: list = dataclasses.field(default_factory=list)       # arrays (n, 10): step, pos, vel, spin
    events: list = dataclasses.field(default_factory=list)    # dicts
    done: bool = False


@dataclasses.dataclass
class _Lane:
    session: _Session | None = None
    step: int = 0
    pos: Any = None
    vel: Any = None
    spin: Any = None
    mode: str = "idle"          # toss | flight | await | ending | idle
    hitter: int = ROBOT
    serve: bool = False
    bounces: int = 0
    hit_step: int = -1          # toss: the serve's step
    await_step: int = 0         # await: first (global) step eligible for the hit
    bounce_step: int = 0        # await: step of the bounce on the receiver's half
    plane: float = 0.0          # await: |x| where the receiver meets the ball
    flight_start: int = 0
    shots: int = 0
    planned: int = 1


def _row(pos, vel, spin):
    return np.concatenate([np.asarray(pos, np.float64), np.asarray(vel, np.float64), np.asarray(spin, np.float64)])


class Game:
    """Runs all games: lanes, chunks, hits, rally bookkeeping.

    Arguments:
        cfg: a checked configuration.
        progress: show a progress bar (rallies done).
    """

    def __init__(self, cfg: GeneratorConfig, progress: bool):
        self.cfg = cfg
        self.dtype = _jax_dtype(cfg)
        self.np_dtype = np.float64 if cfg.dtype == "float64" else np.float32
        self.plain = load_model(cfg.model, dtype=self.dtype)
        self.face = np.asarray(cfg.face, np.float64)
        self.draw_effects()
        self.sessions = []
        for sid in range(cfg.games):
            rng = np.random.default_rng([cfg.seed, 1, sid])
            n_r = int(rng.integers(cfg.rallies_per_game[0], cfg.rallies_per_game[1] + 1))
            self.sessions.append(_Session(sid=sid, rng=rng, n_rallies=n_r, first_server=int(rng.integers(0, 2)),
                                          models_index=sid))
        self.total_rallies = sum(s.n_rallies for s in self.sessions)
        self.progress = progress
        self.steps_simulated = 0
        self.chunks = 0

    # ------------------------------------------------------------------ effects
    def draw_effects(self):
        """Draws the effects of ``self.cfg`` (per dataset and per game) and builds the truth models."""
        cfg = self.cfg
        self.dataset_effects: dict[str, fx.Effect] = {}
        self.session_effects: list[dict[str, fx.Effect]] = [dict() for _ in range(cfg.games)]
        for name in cfg.effects:
            cls = fx.effect_class(name)
            fixed = cfg.effect_params.get(name, {})
            # one stream per effect (and game): switching one effect on or off leaves the others' draws
            index = list(fx.CATALOGUE).index(name)
            if cls.SCOPE == "dataset":
                rng = np.random.default_rng([cfg.seed, 0, index])
                self.dataset_effects[name] = cls.from_dict(fixed, base=cls.sample(rng, self.dtype), dtype=self.dtype)
            else:
                for sid in range(cfg.games):
                    rng = np.random.default_rng([cfg.seed, 2, sid, index])
                    self.session_effects[sid][name] = cls.from_dict(fixed, base=cls.sample(rng, self.dtype), dtype=self.dtype)
        models = []
        for sid in range(cfg.games):
            effs = tuple(self.effect(sid, n) for n in cfg.effects if fx.effect_class(n).WHERE == "simulator")
            models.append(self.plain.replace(effects=effs))
        self.truth_models = stack_models(models)
        self.any_racket_effect = any(callable(getattr(fx.effect_class(n), "racket_coefficients", None)) for n in cfg.effects)
        self.record = {n: None for n in cfg.effects if fx.effect_class(n).WHERE == "record"}

    def effect(self, sid: int, name: str):
        """The effect ``name`` as it acts in game ``sid``."""
        if name in self.dataset_effects:
            return self.dataset_effects[name]
        return self.session_effects[sid][name]

    # ------------------------------------------------------------------ rallies
    def _start_rally(self, lane: _Lane, start_step: int):
        s = lane.session
        s.rally += 1
        rng = s.rng
        server = s.first_server ^ ((s.rally // 2) % 2)
        side = self._end(server)
        every = self.cfg.obs_every
        if start_step % every == 0:
            start_step += 1
        pos = np.array([side * rng.uniform(1.42, 1.62), rng.uniform(-0.6, 0.6), rng.uniform(0.0, 0.12)])
        vz = rng.uniform(2.2, 3.2)
        vel = np.array([rng.normal(0.0, 0.05), rng.normal(0.0, 0.05), vz])
        spin = rng.normal(0.0, 3.0, 3)
        apex = pos[2] + vz * vz / (2 * 9.81)
        z_hit = min(rng.uniform(0.12, 0.3), apex - 0.05)  # struck on the way down
        t_hit = (vz + math.sqrt(vz * vz + 2 * 9.81 * (pos[2] - z_hit))) / 9.81
        hit = start_step + max(int(round(t_hit / self.cfg.dt)), 20)
        if hit % every == 0:
            hit += 1
        lane.step, lane.mode, lane.hitter, lane.serve, lane.bounces = start_step, "toss", server, True, 0
        lane.pos, lane.vel, lane.spin = (pos.astype(self.np_dtype), vel.astype(self.np_dtype), spin.astype(self.np_dtype))
        lane.hit_step, lane.flight_start, lane.shots = hit, start_step, 0
        mean = self.cfg.rally_hits_mean
        lane.planned = int(min(rng.geometric(1.0 / mean), self.cfg.max_rally_hits))
        self._event(s, start_step * self.cfg.dt, "other", "toss", pos, _row(pos, vel, spin), _row(pos, vel, spin), "")

    def _end(self, player: int) -> int:
        """+1 / -1: the end of the table a player stands at."""
        return self.cfg.robot_end if player == ROBOT else -self.cfg.robot_end

    def _event(self, s: _Session, t, kind, true_kind, pos, pre, post, player, shot="", racket=None, aim_=None):
        s.events.append(dict(t=float(t), kind=kind, true_kind=true_kind, pos=np.asarray(pos, np.float64), pre=pre, post=post,
                             player=player, shot=shot, rally=s.rally, racket=racket, aim=aim_))

    def _finish_rally(self, lane: _Lane, end_step: int):
        s = lane.session
        if s.rally + 1 < s.n_rallies:
            gap = s.rng.uniform(*self.cfg.rally_gap)
            self._start_rally(lane, end_step + int(round(gap / self.cfg.dt)))
        else:
            s.done = True
            lane.session, lane.mode = None, "idle"
        self.bar.update(1)

    def _assign(self, lanes, queue):
        for lane in lanes:
            if lane.session is None and queue:
                lane.session = queue.pop(0)
                self._start_rally(lane, int(lane.session.rng.integers(1, 1000)))

    # ------------------------------------------------------------------ main loop
    def run(self):
        """Plays every game to its end; the sessions then hold their observations and events."""
        from tqdm.auto import tqdm

        cfg = self.cfg
        n_lanes = min(cfg.lanes, cfg.games)
        lanes = [_Lane() for _ in range(n_lanes)]
        queue = list(self.sessions)
        if self.progress:  # the bar stays at 0 while the first chunk compiles
            print("generating (the first chunk compiles the game's kernels: up to a minute the first time) ...",
                  flush=True)
        self.bar = tqdm(total=self.total_rallies, desc="generating", unit="rally", disable=not self.progress)
        self._assign(lanes, queue)
        C = cfg.chunk_steps
        dt = cfg.dt
        while any(lane.session is not None for lane in lanes):
            idx = np.array([ln.session.models_index if ln.session else 0 for ln in lanes])
            origin = np.array([ln.step * dt if ln.session else 0.0 for ln in lanes])
            models = lane_models(self.truth_models, jnp.asarray(idx), jnp.asarray(origin, self.dtype))
            ball = Ball(*(jnp.asarray(np.stack([getattr(ln, f) if ln.session else np.array([0, 0, 1.0]) for ln in lanes])
                                      .astype(self.np_dtype)) for f in ("pos", "vel", "spin")))
            res = simulate(models, ball, C, dt, record=Record(every=1, max_events=6), model_axes=0)
            self.steps_simulated += C * sum(ln.session is not None for ln in lanes)
            self.chunks += 1
            traj = np.concatenate([np.asarray(res.trajectory.pos), np.asarray(res.trajectory.vel),
                                   np.asarray(res.trajectory.spin)], axis=-1)  # (B, C, 9)
            log = jax.tree.map(np.asarray, res.events)
            status = np.asarray(res.state.status)
            hits = []
            for b, lane in enumerate(lanes):
                if lane.session is not None:
                    h = self._advance(lane, traj[b], jax.tree.map(lambda a: a[b], log), int(status[b]))
                    if h is not None:
                        hits.append((lane, *h))
            if hits:
                self._hit(hits)
            self._assign(lanes, queue)
        self.bar.close()

    def _advance(self, lane: _Lane, traj, log, status: int = 0):
        """Reads one lane's chunk; returns (k, incoming state) when a racket contact is due.
        ``status``: the kernel's status of the lane's ball at the chunk's end."""
        cfg = self.cfg
        dt, C, s0 = cfg.dt, cfg.chunk_steps, lane.step
        s = lane.session
        n_ev = int(min(log.count, log.kind.shape[0]))
        cut = None  # ("hit", k) or ("end", t_end)
        k_from = 0
        if n_ev == 0 and status == ev.INVALID:
            # refused at the chunk's start, unlogged: a ball whose chunk began as it passed through
            # the net's top (the kernel reports a net crossing, it does not stop the ball) lies
            # within the net's band; it would stay frozen there, observed, until the flight's time
            # limit. The tracker loses it here.
            x = traj[0].astype(np.float64)
            t_abs = s0 * dt
            self._event(s, t_abs, "out", "lost", x[:3], x, x, "")
            n_ev, cut = -1, ("end", t_abs)
        for i in range(n_ev + 1):
            if i < n_ev:
                t_loc = float(log.time[i])
                k_e = max(int(math.ceil(t_loc / dt - 1e-6)) - 1, 0)
            else:
                t_loc, k_e = None, C
            k_hit = self._trigger(lane, traj, k_from, k_e)
            if k_hit is not None:
                cut = ("hit", k_hit)
                break
            if i == n_ev:
                break
            kind = int(log.kind[i])
            pre = _row(log.pre.pos[i], log.pre.vel[i], log.pre.spin[i])
            post = _row(log.post.pos[i], log.post.vel[i], log.post.spin[i])
            t_abs = s0 * dt + t_loc
            if kind == ev.TABLE:
                self._event(s, t_abs, "table", "table", pre[:3], pre, post, "")
                self._on_bounce(lane, float(pre[0]), s0 + k_e + 1)
                k_from = k_e + 1
            elif kind == ev.NET:
                self._event(s, t_abs, "net", "net", pre[:3], pre, post, "")
                cut = ("end", t_abs)
                break
            elif kind in (ev.FLOOR, ev.OUT, ev.INVALID):
                self._event(s, t_abs, "out", "floor" if kind == ev.FLOOR else "lost", pre[:3], pre, post, "")
                cut = ("end", t_abs)
                break
            else:  # pragma: no cover - no rackets in these simulations
                k_from = k_e + 1
        if cut is None and (s0 + C - lane.flight_start) * dt > cfg.max_flight_time and lane.mode != "toss":
            # followed long enough without a contact: the ball is lost to the tracker, half a step on
            x = traj[C - 1].astype(np.float64)
            t_abs = (s0 + C + 0.5) * dt
            self._event(s, t_abs, "out", "lost", x[:3], x, x, "")
            cut = ("end", t_abs)
        # observations up to the cut
        if cut is None:
            k_last = C - 1
        elif cut[0] == "hit":
            k_last = cut[1]
        else:
            k_last = int(math.ceil(cut[1] / dt - s0 - 1e-9)) - 2
        steps = s0 + 1 + np.arange(k_last + 1)
        keep = steps % cfg.obs_every == 0
        if cut is not None and cut[0] == "end":
            keep &= steps * dt < cut[1]
        if keep.any():
            s.obs.append(np.concatenate([steps[keep, None].astype(np.float64), traj[: k_last + 1][keep].astype(np.float64)], 1))
        if cut is None:
            lane.step = s0 + C
            lane.pos, lane.vel, lane.spin = traj[-1, :3], traj[-1, 3:6], traj[-1, 6:9]
            return None
        if cut[0] == "end":
            self._finish_rally(lane, int(math.ceil(cut[1] / dt)))
            return None
        k = cut[1]
        lane.step = s0 + k + 1
        return k, traj[k]

    def _on_bounce(self, lane: _Lane, x: float, step: int):
        """Rules after a table bounce at ``x`` (the state at global ``step`` is just after it)."""
        receiver = 1 - lane.hitter
        side = 1 if x >= 0 else -1
        if lane.mode == "flight":
            want = self._end(lane.hitter) if (lane.serve and lane.bounces == 0) else self._end(receiver)
            if side != want:
                lane.mode = "ending"
            elif lane.serve and lane.bounces == 0:
                lane.bounces = 1
            elif lane.shots >= lane.planned:
                lane.mode = "ending"
            else:
                lane.mode = "await"
                lane.await_step = step + 1
                lane.bounce_step = step
                lane.plane = lane.session.rng.uniform(*self.cfg.hit_distance)
        elif lane.mode == "await":
            lane.mode = "ending"  # bounced twice: the receiver missed it

    def _trigger(self, lane: _Lane, traj, k_from: int, k_to: int):
        """First step in [k_from, k_to) where the hitter meets the ball, or None."""
        if k_to <= k_from:
            return None
        if lane.mode == "toss":
            k = lane.hit_step - lane.step - 1
            return k if k_from <= k < k_to else None
        if lane.mode != "await":
            return None
        k0 = max(k_from, lane.await_step - lane.step - 1)
        seg = traj[k0:k_to]
        if len(seg) == 0:
            return None
        ax, z, vz = np.abs(seg[:, 0]), seg[:, 2], seg[:, 5]
        over = ax <= TABLE_HALF_LENGTH
        low = (vz < 0) & (z < np.where(over, 0.08, -0.25))
        waited = (lane.step + k0 + 1 + np.arange(len(seg)) - lane.bounce_step) * self.cfg.dt > 1.0
        fire = (ax >= lane.plane) | low | waited
        if not fire.any():
            return None
        k = k0 + int(np.argmax(fire))
        if (lane.step + k + 1) % self.cfg.obs_every == 0:  # keep contacts between frames
            k = k + 1 if k + 1 < k_to else k - 1 if k - 1 >= k0 else k
        return k

    # ------------------------------------------------------------------ racket contacts
    def _hit(self, hits):
        """Racket contacts of all lanes due in this chunk: choose, aim, invert, apply the truth."""
        cfg = self.cfg
        n = len(hits)
        start, target = np.zeros((n, 3)), np.zeros((n, 3))
        speed, top, side_spin, vz, first_x = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
        serve = np.zeros(n, bool)
        d, roll, ang = np.zeros((n, 2)), np.zeros(n), np.zeros((n, 3))
        shot = []
        for i, (lane, k, x) in enumerate(hits):
            rng = lane.session.rng
            hitter = lane.hitter if lane.mode == "toss" else 1 - lane.hitter
            end = self._end(hitter)
            name = "serve" if lane.mode == "toss" else choose_shot(rng, cfg.shot_weights, abs(float(x[0])), float(x[2]))
            st = SHOT_TYPES[name]
            u = lambda r: rng.uniform(r[0], r[1])  # noqa: E731
            start[i] = x[:3]
            target[i] = [-end * u(st.target_x), u(st.target_y), 0.02]
            speed[i], top[i], side_spin[i] = u(st.speed), u(st.topspin), u(st.sidespin)
            serve[i] = name == "serve"
            vz[i] = u((-1.0, 0.5))
            first_x[i] = end * u((0.7, 1.15))  # a serve's first bounce, on the server's half
            d[i] = sample_contact_points(rng, 1, cfg.face, cfg.contact_bands)[0]
            roll[i] = rng.uniform(-1.75, 1.75)
            ang[i] = rng.normal(0.0, 4.0, 3)
            shot.append(name)
            lane.hitter = hitter
        w_in = np.stack([h[2][6:9] for h in hits]).astype(np.float64)
        v_in = np.stack([h[2][3:6] for h in hits]).astype(np.float64)
        v_out, spin_out = aim_shots(self.plain, cfg.aim_iters, self.np_dtype, start, target, speed, top, side_spin, vz,
                                    first_x, serve, v_in, w_in)
        size = bucket(n)
        batch = pad(dict(pos=start, spin=spin_out, v_out=v_out, d=d, roll=roll, ang=ang, v_in=v_in, w_in=w_in,
                          sid=np.array([h[0].session.models_index for h in hits])), size)
        j = lambda a: jnp.asarray(np.asarray(a).astype(self.np_dtype))  # noqa: E731
        rk = invert_batch(self.plain.racket, self.plain.ball.radius, self.plain.ball.mass, j(batch["pos"]),
                          j(batch["v_in"]), j(batch["w_in"]), j(batch["v_out"]), j(batch["spin"]), j(batch["d"]),
                          j(batch["roll"]), j(batch["ang"]))
        models = lane_models(self.truth_models, jnp.asarray(batch["sid"]), jnp.zeros(size, self.dtype))
        rvel, v_new, w_new, d_true = true_contact_batch(
            models, rk["pos"], rk["rot"], rk["vel"], rk["ang_vel"], jnp.asarray(self.face, self.dtype),
            j(batch["pos"]), j(batch["v_in"]), j(batch["w_in"]), j(batch["v_out"]),
            jnp.asarray(2 if self.any_racket_effect else 0))
        rk["vel"] = rvel
        rk = {k: np.asarray(v)[:n].astype(np.float64) for k, v in rk.items()}
        v_new, w_new, d_true = np.asarray(v_new)[:n], np.asarray(w_new)[:n], np.asarray(d_true)[:n].astype(np.float64)
        v_aim = v_out
        for i, (lane, k, x) in enumerate(hits):
            s = lane.session
            t = lane.step * cfg.dt
            pre = _row(x[:3], x[3:6], x[6:9])
            post = _row(x[:3], v_new[i], w_new[i])
            player = PLAYERS[lane.hitter]
            racket = dict(pos=rk["pos"][i], rot=rk["rot"][i], vel=rk["vel"][i], ang_vel=rk["ang_vel"][i], d=d_true[i])
            self._event(s, t, "racket" if lane.hitter == ROBOT else "other", "serve" if shot[i] == "serve" else "hit",
                        x[:3], pre, post, player, shot[i], racket, np.concatenate([v_aim[i], spin_out[i]]))
            lane.pos, lane.vel, lane.spin = x[:3].astype(self.np_dtype), v_new[i].astype(self.np_dtype), w_new[i].astype(self.np_dtype)
            lane.mode, lane.serve, lane.bounces = "flight", shot[i] == "serve", 0
            lane.flight_start = lane.step
            lane.shots += 1
