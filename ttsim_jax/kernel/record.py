"""What a rollout records: :class:`Record`.

The event log's size, the trajectory's sampling and the stop after a number of events change what a
rollout returns (and, for ``until_events``, where each ball ends), not how it computes a step; they
are one frozen value, as :class:`~ttsim_jax.kernel.execution.Execution` groups how it runs.
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Record:
    """What a rollout records (frozen, compared and hashed by value: it is static under ``jit``).

    Arguments:
        every: record the ball every that many steps (0, default: no recording); must divide the
            rollout's ``n_steps``.
        max_events: slots of each ball's event log (0: no log; default 8).
        until_events: each ball stops advancing once this rollout's event log has counted that many
            of its events (after the step that reached it, whose further events, such as a bounce
            just after a net crossing, are logged too; its state is frozen there, still ``alive``; a
            later rollout, with a fresh log, moves it on), and a step where no ball advances is
            skipped whole: a branch per step, which pays where most of a batch finishes early (a
            shot's flight to its landing, through a horizon long enough for the slowest; forward or
            reverse mode) and costs a device-to-host copy per step on a GPU. 0 (default): balls run
            to the end. At most ``max_events``; not on the fused path.
    """

    every: int = 0
    max_events: int = 8
    until_events: int = 0

    def __post_init__(self):
        for name in ("every", "max_events", "until_events"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(f"Record({name}=...) must be an int >= 0, got {value!r}")
        if self.until_events > self.max_events:
            raise ValueError(f"Record(until_events={self.until_events}) must be at most "
                             f"max_events={self.max_events}")

    def check(self, n_steps: int) -> None:
        """Refuses a recording interval that does not divide ``n_steps``."""
        if self.every and n_steps % self.every:
            raise ValueError(f"Record(every={self.every}) must divide n_steps={n_steps}")

    def replace(self, **changes) -> Record:
        """A copy with ``changes``."""
        return dataclasses.replace(self, **changes)
