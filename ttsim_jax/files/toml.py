"""Reading a TOML file, with errors that name the file (and the line of a byte that is not text),
and the checksum line of the TOML files ttsim writes.

A file that ttsim writes (a fitted model) starts with ``# ttsim-sha256: <hex>``, the SHA-256 of
the text after that line, so that a byte changed since (a damaged disk, a bad copy) is refused on
reading instead of loading as a changed coefficient. Editing such a file on purpose: delete that
line. Files without it (the bundled configs, files people write) are read as they are.
"""

from __future__ import annotations

import hashlib
import re
import tomllib

from ttsim_jax.errors import ConfigError

SUM_PREFIX = "# ttsim-sha256: "
_SUM_LINE = re.compile(re.escape(SUM_PREFIX) + r"([0-9a-f]{64})\n")


def signed(text: str) -> str:
    """``text`` with the checksum line in front (what :func:`read_toml` verifies)."""
    return f"{SUM_PREFIX}{hashlib.sha256(text.encode('utf-8')).hexdigest()}\n{text}"


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
    line = _SUM_LINE.match(text)
    if line and hashlib.sha256(text[line.end():].encode("utf-8")).hexdigest() != line.group(1):
        raise error(f"{path}: changed since ttsim wrote it (damaged, or edited): its text does not match the "
                    f"SHA-256 on line 1; restore it from a copy, or, edited on purpose, delete line 1")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}") from None
