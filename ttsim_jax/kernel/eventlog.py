"""The event log: each ball's contacts and terminal events, in order, in a fixed number of slots.

A log is an *output* of :func:`~ttsim_jax.kernel.rollout.rollout` (the events of that call), not
part of the rally state: a resumed rally starts a fresh log, so an RL environment stepping 10 ms at a
time gets the events of each 10 ms.

Only the balls that have an event in a step are written (a scatter of a few rows into the log),
never the whole batch.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.state import Ball


@struct.dataclass
class EventLog:
    """Events of a batch of balls, in order; a fixed capacity K of slots per ball.

    Attributes:
        kind: (B, K) event kind (``physics.events.KIND_NAMES``), 0 in unused slots.
        time: (B, K) time of the event [s].
        racket: (B, K) index of the racket hit, -1 for other events.
        pre, post: :class:`~ttsim_jax.state.Ball` with (B, K, 3) fields: the state just before and
            just after the event.
        contact: (B, K, 2) contact position on the racket face (d_y, d_z) [m].
        sigma: (B, K, 6) the residual network's predicted standard deviations of the racket-frame
            post-contact velocity and spin (zeros without a network).
        count: (B,) number of events that happened; more than K means the last ones were dropped.
    """

    kind: jnp.ndarray
    time: jnp.ndarray
    racket: jnp.ndarray
    pre: Ball
    post: Ball
    contact: jnp.ndarray
    sigma: jnp.ndarray
    count: jnp.ndarray

    @classmethod
    def empty(cls, batch: int, capacity: int, dtype) -> "EventLog":
        """A log of ``capacity`` slots for each of ``batch`` balls, with no events."""
        z3 = jnp.zeros((batch, capacity, 3), dtype)
        zb = Ball(z3, z3, z3)
        return cls(kind=jnp.zeros((batch, capacity), jnp.int32), time=jnp.zeros((batch, capacity), dtype),
                   racket=-jnp.ones((batch, capacity), jnp.int32), pre=zb, post=zb,
                   contact=jnp.zeros((batch, capacity, 2), dtype), sigma=jnp.zeros((batch, capacity, 6), dtype),
                   count=jnp.zeros((batch,), jnp.int32))

    @property
    def capacity(self) -> int:
        return self.kind.shape[-1]

    def write(self, rows, happened, kind, time, racket, pre: Ball, post: Ball, contact, sigma) -> "EventLog":
        """Appends one event to each of the balls ``rows``.

        Arguments:
            rows: (C,) ball indices; an index out of range (>= B) is an unused buffer row.
            happened: (C,) whether that row has an event to log.
            kind, time, racket, pre, post, contact, sigma: (C, ...) the event's fields.

        Returns:
            The log with the events appended (a full log only counts them).
        """
        b, k = self.kind.shape
        count = jnp.take(self.count, rows, mode="clip")
        write = happened & (rows < b) & (count < k)
        # rows not written are sent out of range, where the scatter drops them
        r = jnp.where(write, rows, b)
        s = jnp.minimum(count, k - 1)

        def put(buf, value):
            return buf.at[r, s].set(value.astype(buf.dtype), mode="drop")

        return EventLog(
            kind=put(self.kind, kind), time=put(self.time, time), racket=put(self.racket, racket),
            pre=jax.tree.map(put, self.pre, pre), post=jax.tree.map(put, self.post, post),
            contact=put(self.contact, contact), sigma=put(self.sigma, sigma),
            count=self.count.at[jnp.where(happened & (rows < b), rows, b)].add(1, mode="drop"))
