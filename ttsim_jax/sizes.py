"""The memory a job will need, estimated from its sizes before anything is allocated, against a budget.

A job asked for absurd sizes (a billion shots, games or environments) must be refused at once with
the size and the budget, not after minutes of growth on a machine that others share. Each entry
point estimates what it will hold from its own shapes (the kernel's state and event log, the
generator's observations, PPO's rollout buffer) and calls :func:`require` before it allocates.

The budget is, in this order: the ``budget`` argument of :func:`require`; the environment variable
``TTSIM_MEMORY_BUDGET`` (a size such as ``16G``; the ``ttsim --memory-budget`` option sets it);
otherwise :data:`DEFAULT_FRACTION` of the memory available when the job starts.
"""

from __future__ import annotations

import os
import re

from ttsim_jax.errors import UserError

ENV = "TTSIM_MEMORY_BUDGET"
#: Share of the available memory a job may plan to use by default: the rest stays to the operating
#: system, XLA's temporaries (which the estimates leave out) and whoever shares the machine.
DEFAULT_FRACTION = 0.5

_UNITS = {"": 1, "B": 1, "K": 2**10, "KB": 10**3, "KIB": 2**10, "M": 2**20, "MB": 10**6, "MIB": 2**20,
          "G": 2**30, "GB": 10**9, "GIB": 2**30, "T": 2**40, "TB": 10**12, "TIB": 2**40}


#: The largest size :func:`parse_size` takes (an exbibyte: beyond any machine's memory).
MAX_SIZE = 2**60


class SizeError(UserError, ValueError):
    """A job whose estimated memory exceeds the budget (the message gives both and the remedy)."""


def parse_size(text: str) -> int:
    """Bytes from a size such as ``512M``, ``16G``, ``2.5GiB`` or ``1000000`` (K, M, G, T are powers of 1024).

    Raises:
        ValueError: not a positive size.
    """
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([A-Za-z]*)\s*", str(text))
    if m is None or m.group(2).upper() not in _UNITS:
        raise ValueError(f"expected a size such as 512M, 16G or 2.5GiB, got {text!r}")
    value = float(m.group(1)) * _UNITS[m.group(2).upper()]
    if not value >= 1:
        raise ValueError(f"expected a positive size, got {text!r}")
    if not value <= MAX_SIZE:
        raise ValueError(f"expected a size of at most {format_size(MAX_SIZE)}, got {text!r}")
    return int(value)


def format_size(n: float) -> str:
    """``1.50 GiB``, ``12.0 MiB``, ``3.2 TiB``: a byte count for messages."""
    for unit, scale in (("EiB", 2**60), ("PiB", 2**50), ("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{int(n)} B"


def available_bytes() -> int:
    """Memory available to new allocations now (``MemAvailable`` on Linux, else the physical memory)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 8 * 2**30


def budget_bytes(budget: int | None = None) -> tuple[int, str]:
    """The budget in bytes and where it comes from (for messages).

    Raises:
        SizeError: ``TTSIM_MEMORY_BUDGET`` is set to something that is not a size.
    """
    if budget is not None:
        return int(budget), "the budget given"
    text = os.environ.get(ENV)
    if text:
        try:
            return parse_size(text), f"set by --memory-budget or {ENV}"
        except ValueError as e:
            raise SizeError(f"{ENV}: {e}") from None
    avail = available_bytes()
    return int(DEFAULT_FRACTION * avail), f"{DEFAULT_FRACTION:.0%} of the {format_size(avail)} available"


def require(what: str, need: float, *, remedy: str = "", budget: int | None = None) -> None:
    """Refuses a job whose estimated memory is above the budget, before it allocates.

    Arguments:
        what: the job and its sizes, as the user asked for them (``"--shots 1000000000"``).
        need: estimated bytes the job will hold at once.
        remedy: how to ask for less (an option, a config key).
        budget: bytes; default from ``TTSIM_MEMORY_BUDGET`` or the available memory.

    Raises:
        SizeError: naming the job, the estimate, the budget and how to lower the one or raise the other.
    """
    limit, source = budget_bytes(budget)
    if need > limit:
        hint = f"{remedy}, or raise" if remedy else "raise"
        raise SizeError(f"{what} needs about {format_size(need)} of memory, above the budget of "
                        f"{format_size(limit)} ({source}); {hint} the budget with ttsim --memory-budget SIZE "
                        f"or {ENV}=SIZE")
