"""Reading a TOML file, with errors that name the file (and the line of a byte that is not text)."""

from __future__ import annotations

import tomllib

from ttsim_jax.errors import ConfigError


def read_toml(path, what: str = "configuration file", error: type = ConfigError) -> dict:
    """Parses a UTF-8 TOML file.

    Arguments:
        path: the file.
        what: what the file is, for the messages ("configuration file", "model file", ...).
        error: the error class raised (a :class:`~ttsim_jax.errors.UserError` of the caller's kind).

    Returns:
        The parsed document. Raises ``error`` naming the file when
        it does not exist, holds a byte that is not UTF-8 text (with its line and offset) or is
        not valid TOML.
    """
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except FileNotFoundError:
        raise error(f"{path}: no such {what}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise error(f"{path}: line {line}: byte {raw[exc.start:exc.start + 1]!r} at offset {exc.start} is not "
                          f"UTF-8 text; a {what} is a UTF-8 TOML text file") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}") from None
