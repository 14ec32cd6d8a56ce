"""Where ttsim-jax keeps what is slow to make: aimed shot banks and compiled programs.

Everything lives under ``$XDG_CACHE_HOME/ttsim_jax`` (default ``~/.cache/ttsim_jax``); deleting it
only costs the time to make it again.
"""

from __future__ import annotations

import contextlib
import os
import platform
import sys
import threading
from pathlib import Path

#: Compile time [s] above which a program is kept in the compilation cache (JAX's default: 1 s).
MIN_COMPILE_S = 0.1


def cache_root() -> Path:
    """``$XDG_CACHE_HOME/ttsim_jax`` (default ``~/.cache/ttsim_jax``); not created here."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "ttsim_jax"


def enable_compilation_cache() -> str | None:
    """Turns on JAX's persistent compilation cache, so that a command run again (a sensitivity study,
    a fit, training) or a new Python process loads its compiled programs instead of compiling them
    for minutes. The ``ttsim`` commands call it, and so do :func:`ttsim_jax.load_model` (a library
    user's first step) and every ReturnBall environment when it is made (``ttsim_jax.env``).

    The folder is ``$TTSIM_COMPILE_CACHE`` if set (``off`` turns the cache off), else
    ``cache_root()/xla/<host name>``: one per machine, since an executable compiled for one CPU may
    not load on another that shares the home folder. A cache JAX was already given (its
    ``JAX_COMPILATION_CACHE_DIR``, or the config) is left as it is. The folder must be trusted: JAX
    runs what it loads from there.

    Returns:
        The folder in use, or None when the cache stays off.
    """
    import jax

    chosen = os.environ.get("TTSIM_COMPILE_CACHE", "")
    if chosen.lower() in ("off", "0", "false", "no"):
        return None
    current = jax.config.jax_compilation_cache_dir
    if current:
        return current
    folder = Path(chosen) if chosen else cache_root() / "xla" / (platform.node() or "local")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home: compile every time, as without the cache
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    if jax.config.jax_persistent_cache_min_compile_time_secs == 1.0:  # JAX's default, not the user's choice
        # JAX keeps only programs that took a second to compile; a diagnosis or a fit also compiles
        # dozens of small ones (0.1-0.4 s each), seconds in all that a run again would spend anew
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
    return str(folder)


@contextlib.contextmanager
def compile_notice(what: str, expected_s: float, after_s: float = 3.0):
    """Prints one line to stderr if the block is still running after ``after_s`` seconds: a first
    call is compiling ``what`` (about ``expected_s`` seconds the first time) or loading it from the
    persistent compilation cache (seconds), and the line says what each takes; quick calls (a
    program in memory) print nothing.

    Arguments:
        what: the program, as the line names it ("the ReturnBall step for 8 environments").
        expected_s: its compile time measured on 2 CPU cores [s].
        after_s: how long the block runs before the line is printed [s].
    """
    def say():
        import jax

        # whether XLA compiles or loads the program from the persistent cache is not known here
        # (JAX decides inside the call), so the line says what either takes, not which it is
        cache = jax.config.jax_compilation_cache_dir
        how = (f"compiling takes about {expected_s:.0f} s the first time on 2 CPU cores, loading it from the "
               f"compilation cache a few seconds" if cache else
               f"compiling takes about {expected_s:.0f} s on 2 CPU cores (the compilation cache is off)")
        print(f"ttsim_jax: preparing {what}: {how}", file=sys.stderr, flush=True)

    timer = threading.Timer(after_s, say)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
