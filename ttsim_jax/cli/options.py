"""What the ``ttsim`` subcommands share: :class:`UsageError`, the ``type=`` validators of their
options, and :func:`command_group` for the commands grouped under one word (``train``,
``evaluate``).

Nothing here imports JAX, so that parsing the arguments (and ``--help``) answers at once.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

from ttsim_jax.errors import UserError


class UsageError(UserError):
    """A user error a command finds after parsing (refused overwrite, inconsistent options);
    :func:`ttsim_jax.cli.main.main` prints ``error: MESSAGE`` and returns 2."""


# ---------------------------------------------------------------------------------------------
# argparse ``type=`` validators: each returns the converted value or raises ArgumentTypeError,
# which argparse reports as "argument OPTION: MESSAGE" (exit status 2).

def number(text: str, kind, what: str):
    """``kind(text)`` (``int`` or a finite ``float``), or an ArgumentTypeError saying that ``what`` was expected."""
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1 (counts: shots, games, epochs, clusters)."""
    value = number(text, int, "a positive integer")
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def seed(text: str) -> int:
    """A random seed: an integer in [0, 2**32)."""
    value = number(text, int, "an integer seed in [0, 2**32)")
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"expected an integer seed in [0, 2**32), got {text!r}")
    return value


def finite_float(text: str) -> float:
    """A finite number (not nan or inf)."""
    return number(text, float, "a finite number")


def positive_float(text: str) -> float:
    """A finite number > 0 (durations, steps, tolerances)."""
    value = number(text, float, "a positive finite number")
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text!r}")
    return value


def existing_file(text: str) -> Path:
    """A file that exists (not a directory)."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: is a directory, expected a file")
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"{text}: no such file")
    return path


def text_file(text: str) -> Path:
    """An existing UTF-8 text file (TOML configs and models): a binary file is refused here."""
    path = existing_file(text)
    try:
        path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise argparse.ArgumentTypeError(f"{text}: not a text file (byte {e.start} is not UTF-8)") from None
    except OSError as e:
        raise argparse.ArgumentTypeError(f"{text}: cannot be read: {e.strerror}") from None
    return path


def existing_dir(text: str) -> Path:
    """A directory that exists (datasets)."""
    path = Path(text)
    if path.is_file():
        raise argparse.ArgumentTypeError(f"{text}: is a file, expected a directory")
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: no such directory")
    return path


def existing_path(text: str) -> Path:
    """A file or directory that exists (an importer's input)."""
    if not Path(text).exists():
        raise argparse.ArgumentTypeError(f"{text}: no such file or directory")
    return Path(text)


def check_creatable(path: Path, text: str) -> None:
    """Refuses a path whose nearest existing ancestor is not a directory in which a file can be
    created (tried with a probe file), so that an output the command would only write at the end
    is checked before the work starts."""
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: cannot be created, {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{text}: cannot be created, {parent} is not writable")
    from ttsim_jax.files.atomic import probe_writable

    reason = probe_writable(parent)
    if reason is not None:
        raise argparse.ArgumentTypeError(f"{text}: cannot be created, no file can be made in {parent} ({reason})")


def writable_file(text: str) -> Path:
    """An output file: not a directory, writable if it exists, else creatable (missing parent
    directories are created when it is written)."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: is a directory, expected a file name")
    if path.exists() and not os.access(path, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text}: is not writable")
    check_creatable(path, text)
    return path


#: The formats a figure is written in (matplotlib's, by file suffix).
FIGURE_SUFFIXES = (".png", ".pdf", ".svg", ".svgz", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".eps", ".ps")


def file_of(*suffixes: str, what: str):
    """An argparse type: a :func:`writable_file` whose name ends in one of ``suffixes`` (checked
    while parsing, not after the work that produces it), ``what`` naming it in the message."""
    def parse(text: str) -> Path:
        path = writable_file(text)
        if path.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"{text}: the name of {what} must end in {' or '.join(suffixes)} "
                                             "(its format follows the name)" if len(suffixes) < 3 else
                                             f"{text}: the name of {what} must end in {suffixes[0]} (or one of "
                                             f"{', '.join(suffixes[1:])}: its format follows the name)")
        return path
    return parse


def writable_dir(text: str) -> Path:
    """An output directory: a writable directory if it exists, else creatable."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: exists and is not a directory")
    if path.is_dir() and not os.access(path, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{text}: is not writable")
    check_creatable(path, text)
    return path


def memory_size(text: str) -> int:
    """A memory size such as 512M, 16G or 2.5GiB, in bytes."""
    from ttsim_jax.sizes import parse_size

    try:
        return parse_size(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def model_name_or_file(text: str) -> str:
    """A bundled model name or the path of a model TOML file, optionally ``+RACKET`` (a bundled racket
    configuration: ``conti2026+racket_05``)."""
    from ttsim_jax.params import ConfigError, resolve_model_path, resolve_racket_path, split_model_name

    model, racket = split_model_name(text)
    try:
        path = resolve_model_path(model)
        if racket is not None:
            resolve_racket_path(racket)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    if path == Path(text):  # a file given by path, not a bundled name
        text_file(text)
    return text


def fraction(text: str) -> float:
    """A fraction in [0, 1) (held-out shares of sessions)."""
    value = finite_float(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a fraction in [0, 1), got {text!r}")
    return value


def open_fraction(text: str) -> float:
    """A number strictly between 0 and 1."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: not a number") from None
    if not 0.0 < v < 1.0:
        raise argparse.ArgumentTypeError(f"{text!r}: must be between 0 and 1 (exclusive)")
    return v


def command_group(subparsers, name: str, help: str, description: str):
    """The sub-subparsers of the top-level command ``name`` (``train``, ``evaluate``), created if
    no other module did, so that several modules can add commands to one group.

    Arguments:
        subparsers: what ``ArgumentParser.add_subparsers()`` returned.
        name: the group's word; help, description: its help line and description (used when the
            group is created here).

    Returns:
        The group's subparsers object (``add_parser`` adds a command to it).
    """
    parser = subparsers.choices.get(name) if hasattr(subparsers, "choices") else None
    if parser is not None:
        for action in parser._actions:  # another module registered the group: extend it
            if isinstance(action, argparse._SubParsersAction):
                return action
    parser = subparsers.add_parser(name, help=help, description=description)
    sub = parser.add_subparsers(dest=f"{name}_command", metavar="WHAT")
    sub.required = True
    return sub


def add_spin_option(parser, what: str) -> None:
    """``--spin``: where a flight segment's spin comes from (:data:`ttsim_jax.fit.choices.SPIN_SOURCES`);
    ``what``: what the spins are used for, in the help."""
    from ttsim_jax.fit.choices import SPIN_SOURCES

    parser.add_argument("--spin", choices=SPIN_SOURCES, default="auto",
                        help=f"{what}: 'auto' the measured spin where there is one and the latent spin fitted from "
                        "the segment's samples elsewhere; 'measured' only the segments with a measured spin (every "
                        "segment with spin 0 when none has one); 'latent' the latent spin everywhere; 'zero' spin 0 "
                        "everywhere (default: %(default)s)")
