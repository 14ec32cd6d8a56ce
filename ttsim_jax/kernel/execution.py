"""How a rollout runs, apart from what it computes: :class:`Execution`.

Every option here leaves the results unchanged (within float32 rounding on the fused path); they
trade memory, compile time and speed, and differ between a CPU and an accelerator. Grouping them
keeps :func:`~ttsim_jax.kernel.rollout.rollout`'s own arguments to the physics and the outputs, as
diffrax groups a solver's step-size controller and its options.
"""

from __future__ import annotations

import dataclasses

@dataclasses.dataclass(frozen=True)
class Execution:
    """Execution options of a rollout (frozen, compared and hashed by value).

    Arguments:
        contact_capacity: balls per step handled in the gathered event buffer (default B/32, at
            least 8); a step with more runs the buffer several times, with the same result.
        remat: rematerialise steps and chunks in reverse mode (saves memory; no cost forward).
        reference: run the exact event detection for every ball at every step instead of only for
            the balls whose gaps change sign (same results, slower; for testing).
        block_size: run the batch in blocks of this many balls, one after the other, each through
            the whole rollout (same results); default (None) none
            (:func:`~ttsim_jax.kernel.rollout.default_block`); 0 for none.
        buffering: how a step hands its flagged balls to the contact models (same results):
            ``"loop"`` (default on CPU) or ``"single"`` (default on GPU and other accelerators);
            see :func:`~ttsim_jax.kernel.step.step`.
        fused: the fused flight path (:mod:`~ttsim_jax.kernel.fused`: a kernel flies the balls
            many steps per launch up to their next possible event; same results within float32
            rounding): ``"auto"`` (default: wherever it covers the rollout and pays,
            :func:`~ttsim_jax.kernel.rollout.fused_pays`: on a GPU, and on a CPU from 1,024 balls
            and 300 steps without a racket schedule per ball; nowhere with a racket policy),
            True (refused with the reason where it does not cover the rollout) or False (the
            reference path). The kernel is a Pallas (Triton) kernel on a GPU; on a CPU its body runs
            as plain XLA over the whole batch (benchmarks/README.md). ``jax.grad`` always
            differentiates the reference path.
        memory_budget_bytes: a rollout whose state, event log and recording
            (:func:`~ttsim_jax.kernel.rollout.memory_bytes`) need more is refused before compiling,
            with the sizes; default None: the package's one budget (:func:`ttsim_jax.sizes.budget_bytes`:
            ``TTSIM_MEMORY_BUDGET``, ``ttsim --memory-budget``, else half the memory available).
    """

    contact_capacity: int | None = None
    remat: bool = True
    reference: bool = False
    block_size: int | None = None
    buffering: str | None = None
    fused: bool | str = "auto"
    memory_budget_bytes: int | None = None

    def __post_init__(self):
        if self.fused not in (True, False, "auto"):
            raise ValueError(f"fused must be True, False or 'auto', got {self.fused!r}")
        if self.buffering not in (None, "loop", "single"):
            raise ValueError(f"buffering must be 'loop' or 'single', got {self.buffering!r}")
        if self.contact_capacity is not None and (not isinstance(self.contact_capacity, int)
                                                  or self.contact_capacity <= 0):
            raise ValueError(f"contact_capacity must be a positive int, got {self.contact_capacity!r}")
        if self.block_size is not None and (not isinstance(self.block_size, int) or self.block_size < 0):
            raise ValueError(f"block_size must be an int >= 0, got {self.block_size!r}")

    def replace(self, **changes) -> Execution:
        """A copy with ``changes``."""
        return dataclasses.replace(self, **changes)
