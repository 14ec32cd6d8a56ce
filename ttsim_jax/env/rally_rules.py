"""The rules of a ReturnBall rally: how an episode ends (the outcome codes) and how one logged
event of the kernel moves the rally on (:func:`advance`).

The ball must bounce once on the agent's half (x > 0), then meet the racket (a contact before that
bounce is a volley, a second bounce or a fall a miss); after the contact, the next table contact
must be on the opponent's half (x < 0): a legal return. The net, the agent's own half, the floor,
leaving play or a second contact end it as a fault.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from ttsim_jax.physics import events as ev

# How an episode ended (``info["outcome"]``); RUNNING while it goes on.
RUNNING, LEGAL, NET, OUT, MISS, VOLLEY, SHOT_FAULT = range(7)
OUTCOME_NAMES = ("running", "legal", "net", "out", "miss", "volley", "shot_fault")


@struct.dataclass
class Rally:
    """Where a rally stands (fields (B,)).

    Attributes:
        bounced: the ball bounced on the agent's half. hit: the agent's racket met it (legally).
        outcome: RUNNING, or how it ended. landing: (B, 2) where the return landed (legal returns).
    """

    bounced: jnp.ndarray
    hit: jnp.ndarray
    outcome: jnp.ndarray
    landing: jnp.ndarray


def advance(p: Rally, kind, pos, valid) -> Rally:
    """The rally after one logged event (``kind`` (B,), position ``pos`` (B, 3)); ``valid`` masks unused slots."""
    run = valid & (p.outcome == RUNNING)
    own = pos[:, 0] > 0.0
    table, racket, net = kind == ev.TABLE, kind == ev.RACKET, kind == ev.NET
    dead = (kind == ev.FLOOR) | (kind == ev.OUT) | (kind == ev.REST) | (kind == ev.INVALID)
    pre, post = run & ~p.hit, run & p.hit
    outcome = jnp.select(
        [pre & table & own & p.bounced, pre & racket & ~p.bounced, pre & dead & p.bounced, pre & dead & ~p.bounced,
         post & table & ~own, post & net, post & ((table & own) | racket | dead)],
        [MISS, VOLLEY, MISS, SHOT_FAULT, LEGAL, NET, OUT], p.outcome)
    return Rally(bounced=p.bounced | (pre & table & own), hit=p.hit | (pre & racket & p.bounced),
                 outcome=outcome.astype(jnp.int32),
                 landing=jnp.where((post & table & ~own)[:, None], pos[:, :2], p.landing))
