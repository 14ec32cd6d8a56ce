"""The checkpoint container: one file of named arrays with a verified header, written atomically.

Layout:

    b"TTSIM-RESIDUAL\\n" + <JSON header, one line> + b"\\n" + <msgpack payload>

The header holds the format version, the file's kind (a residual network, a training state, ...),
the payload's length and SHA-256, every array's shape and dtype, whatever the writer adds (a
configuration, notes) and the SHA-256 of all that (``header_sha256``; files written before it are
read without); the payload (``flax.serialization`` msgpack) holds the arrays bit-exactly.
Reading checks all of it, so a truncated, padded, corrupted or foreign file is refused with a
:class:`CheckpointError` naming the file and the key, never loaded half. The magic bytes name the
residual network, whose files came first; every kind shares them.

Format versions: 1 had no ``sigma_scale`` in residual-network files; 2 (current) adds it. Which
versions a kind accepts is the reader's choice (:func:`read_container`).

Nothing here imports JAX at import time (Flax's msgpack is imported when a file is written or read).
"""

from __future__ import annotations

import hashlib
import json

import numpy as np

from ttsim_jax.errors import UserError
from ttsim_jax.files.atomic import atomic_write
from ttsim_jax.files.checksum import json_sum

CHECKPOINT_MAGIC = b"TTSIM-RESIDUAL\n"
CHECKPOINT_VERSION = 2
#: The header key of the header's own SHA-256.
HEADER_SUM_KEY = "header_sha256"


class CheckpointError(UserError, ValueError):
    """A checkpoint that cannot be read: missing, wrong magic, format version or kind, truncated,
    corrupted, or not matching its configuration. The message names the file and the offending key."""


def flatten_arrays(tree, prefix: str = "") -> dict:
    """``{"a/b/c": array}`` for a nested dict of arrays (keys joined with ``/``)."""
    out = {}
    for k, v in tree.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten_arrays(v, key + "/"))
        else:
            out[key] = v
    return out


def _to_plain(tree):
    """Nested dicts of numpy arrays (FrozenDicts and jax arrays turned plain)."""
    if hasattr(tree, "items"):
        return {str(k): _to_plain(v) for k, v in tree.items()}
    return np.asarray(tree)


def _check_finite(path, flat: dict) -> None:
    """Refuses non-finite floating arrays: a checkpoint holding NaN or inf weights is useless."""
    for k, v in flat.items():
        a = np.asarray(v)
        if np.issubdtype(a.dtype, np.floating) and not np.isfinite(a).all():
            first = np.unravel_index(int(np.flatnonzero(~np.isfinite(a))[0]), a.shape) if a.ndim else ()
            raise CheckpointError(f"{path}: key {k!r} holds non-finite values (first {a[first]} at index "
                                  f"{tuple(int(i) for i in first)})")


def write_container(path, kind: str, header: dict, arrays: dict) -> None:
    """Writes a checkpoint container (magic, JSON header, msgpack payload) atomically.

    Arguments:
        path: destination file.
        kind: what the file holds ("residual-model", or a training state).
        header: JSON-serialisable metadata stored in the header.
        arrays: nested dict of arrays (the payload).

    Raises :class:`CheckpointError` (before writing, so the previous file stays) when an array
    holds a non-finite value.
    """
    from flax import serialization

    arrays = _to_plain(arrays)
    flat = flatten_arrays(arrays)
    _check_finite(path, flat)
    payload = serialization.msgpack_serialize(arrays)
    head = dict(header, format_version=CHECKPOINT_VERSION, kind=kind, payload_bytes=len(payload),
                payload_sha256=hashlib.sha256(payload).hexdigest(),
                arrays={k: [list(v.shape), str(v.dtype)] for k, v in flat.items()})
    head[HEADER_SUM_KEY] = json_sum(head, HEADER_SUM_KEY)
    line = json.dumps(head, sort_keys=True).encode()
    atomic_write(path, CHECKPOINT_MAGIC + line + b"\n" + payload)


def read_container(path, kind: str, versions=(CHECKPOINT_VERSION,)) -> tuple[dict, dict]:
    """Reads and verifies a checkpoint container written by :func:`write_container`.

    Arguments:
        path: the file.
        kind: the expected kind.
        versions: the format versions accepted (default: the current one only).

    Returns:
        (header, arrays). Raises :class:`CheckpointError` naming the file (and key) if it is
        missing, not a checkpoint, of another format version or kind, truncated or corrupted.
    """
    from flax import serialization

    try:
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no such checkpoint file") from None
    if not data.startswith(CHECKPOINT_MAGIC):
        raise CheckpointError(f"{path}: not a ttsim residual checkpoint (bad magic bytes; truncated or another format)")
    end = data.find(b"\n", len(CHECKPOINT_MAGIC))
    if end < 0:
        raise CheckpointError(f"{path}: truncated inside the header")
    try:
        header = json.loads(data[len(CHECKPOINT_MAGIC):end])
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{path}: header is not valid JSON (corrupted): {e}") from None
    if not isinstance(header, dict):
        raise CheckpointError(f"{path}: header is not a JSON object (corrupted)")
    # files written before the header had its own sum carry none: their payload is still verified
    if HEADER_SUM_KEY in header and header[HEADER_SUM_KEY] != json_sum(header, HEADER_SUM_KEY):
        raise CheckpointError(f"{path}: corrupted: the header does not match key 'header_sha256'")
    version = header.get("format_version")
    if version not in versions:
        readable = " or ".join(str(v) for v in versions)
        hint = (" (a newer format: update ttsim_jax)" if isinstance(version, int) and version > max(versions)
                else " (written by an older ttsim_jax: retrain)")
        raise CheckpointError(f"{path}: key 'format_version' = {version!r}; this code reads "
                              f"{kind!r} files of version {readable}{hint}")
    if header.get("kind") != kind:
        raise CheckpointError(f"{path}: key 'kind' = {header.get('kind')!r}, expected {kind!r}")
    for key in ("payload_bytes", "payload_sha256", "arrays"):
        if key not in header:
            raise CheckpointError(f"{path}: header lacks key {key!r} (corrupted)")
    payload = data[end + 1:]
    if len(payload) != header["payload_bytes"]:
        raise CheckpointError(f"{path}: truncated or padded: key 'payload_bytes' says {header['payload_bytes']} "
                              f"bytes, the file holds {len(payload)}")
    if hashlib.sha256(payload).hexdigest() != header["payload_sha256"]:
        raise CheckpointError(f"{path}: corrupted: the payload does not match key 'payload_sha256'")
    try:
        arrays = serialization.msgpack_restore(payload)
    except Exception as e:  # msgpack raises several unrelated types
        raise CheckpointError(f"{path}: payload cannot be decoded (corrupted): {e}") from None
    flat = flatten_arrays(arrays)
    listed = header["arrays"]
    if set(flat) != set(listed):
        raise CheckpointError(f"{path}: arrays {sorted(set(flat) ^ set(listed))} differ between header and payload")
    for k, v in flat.items():
        if [list(np.shape(v)), str(np.asarray(v).dtype)] != listed[k]:
            raise CheckpointError(f"{path}: key {k!r} is {np.shape(v)} {np.asarray(v).dtype} in the payload, "
                                  f"the header says {listed[k]}")
    _check_finite(path, flat)
    return header, arrays
