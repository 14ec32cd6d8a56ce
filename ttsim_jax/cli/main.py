"""The ``ttsim`` command: the parser of every subcommand, the options before them, and the
handling of errors.

User errors never end in a traceback: option values are checked while parsing by the ``type=``
validators of :mod:`ttsim_jax.cli.options` (argparse then names the option and the value and exits
with status 2), and a :class:`~ttsim_jax.errors.UserError` (bad config, dataset, checkpoint or
size, :class:`~ttsim_jax.cli.options.UsageError` from a command) or a refused path is turned into
one ``error: ...`` line and status 2 by :func:`main`. Any other exception is a bug and keeps its
traceback. Each subcommand is a module of :mod:`ttsim_jax.cli` with a ``register(subparsers)``
that sets ``func(args) -> int`` (the exit status) on the parsed namespace.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

from ttsim_jax.cli import data, diagnose, evaluate, fit, generate, residual, rl, sensitivity, simulate
from ttsim_jax.cli.options import memory_size
from ttsim_jax.errors import UserError

#: Refused paths the library raises as the operating system's errors (their messages name the path).
PATH_ERRORS = (FileExistsError, FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError)


def build_parser() -> argparse.ArgumentParser:
    """The ``ttsim`` parser: the options before the subcommand, and every subcommand.

    Returns:
        An ``argparse.ArgumentParser`` whose parsed namespace carries ``func(args) -> int``.
    """
    from ttsim_jax import __version__

    parser = argparse.ArgumentParser(
        prog="ttsim", description="Differentiable table tennis ball physics in JAX: simulate shots, import, "
                                  "generate and inspect data, fit aerodynamics, compare models on data, diagnose the sim-to-real gap, train and evaluate the racket "
                                  "residual network, train and play a racket policy (PPO). "
                                  "World frame: origin at the centre of the table surface, x along the table, z "
                                  "up; SI units.")
    parser.add_argument("--version", action="version", version=f"ttsim-jax {__version__}")
    parser.add_argument("--memory-budget", type=memory_size, default=None, metavar="SIZE",
                        help="memory a command may plan to use, e.g. 16G (default: the TTSIM_MEMORY_BUDGET "
                             "variable, else half the memory available when it starts); a job whose sizes "
                             "(shots, games, environments, episodes) need more is refused before it starts")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    simulate.register(sub)
    sensitivity.register(sub)
    data.register(sub)
    generate.register(sub)
    fit.register(sub)
    residual.register(sub)  # makes the 'train' and 'evaluate' groups
    evaluate.register(sub)  # after residual: the model comparison is the 'evaluate' group's own command
    diagnose.register(sub)
    rl.register(sub)  # adds to the 'train' group
    _everywhere(parser, next(a for a in parser._actions if "--memory-budget" in a.option_strings))
    return parser


def _everywhere(parser: argparse.ArgumentParser, action: argparse.Action) -> None:
    """Lets a global option also follow the subcommand (``ttsim generate ... --memory-budget 32G``):
    every subparser gets a copy whose default leaves the global value in place."""
    option = action.option_strings[0]
    for sub in (a for a in parser._actions if isinstance(a, argparse._SubParsersAction)):
        for child in sub.choices.values():
            _everywhere(child, action)
            if option not in child._option_string_actions:
                child.add_argument(option, type=action.type, default=argparse.SUPPRESS, metavar=action.metavar,
                                   help=action.help)


def main(argv=None) -> int:
    """Runs ``ttsim ARGV``.

    Arguments:
        argv: the arguments after ``ttsim`` (default: ``sys.argv[1:]``).

    Returns:
        The exit status: 0 done, 2 a user error (bad option, file or value; reported in one
        ``error:`` line naming it), otherwise what the command returns.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help and --version (0), or argparse's usage error (2), already printed
        return int(e.code or 0)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from ttsim_jax.files.cache import enable_compilation_cache

    enable_compilation_cache()  # a command run again loads its compiled programs
    from ttsim_jax.sizes import ENV

    before = os.environ.get(ENV)
    if args.memory_budget is not None:  # the library's size checks read it (ttsim_jax.sizes)
        os.environ[ENV] = str(args.memory_budget)
    from ttsim_jax.data.errors import DataWarning

    shown = warnings.showwarning

    def show(message, category, *where):  # a warning about the user's data: one 'warning:' line
        if issubclass(category, DataWarning):
            print(f"warning: {message}", file=sys.stderr)
        else:
            shown(message, category, *where)

    warnings.showwarning = show
    try:
        status = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
        return status
    except (UserError, *PATH_ERRORS) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except MemoryError as e:  # an allocation the size checks did not foresee: still no traceback
        what = str(e).split(" for an array")[0] or "an allocation failed"  # numpy: "Unable to allocate 8 GiB"
        print(f"error: ttsim {args.command}: out of memory ({what}); ask for fewer shots, games, environments "
              "or episodes, or run it where more memory is free", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader went away (``ttsim data info DIR | head``): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except OSError as e:  # a write outside the atomic writers on a full disk or a read-only place
        from ttsim_jax.files.atomic import write_error

        refused = write_error(e, e.filename or "a file", atomic=False)
        if refused is None:
            raise
        print(f"error: {refused}", file=sys.stderr)
        return 2
    finally:
        warnings.showwarning = shown
        if args.memory_budget is not None:
            if before is None:
                os.environ.pop(ENV, None)
            else:
                os.environ[ENV] = before

