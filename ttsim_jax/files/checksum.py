"""The SHA-256 of a JSON document that carries its own checksum (a dataset's metadata, a
checkpoint's header): the sum of the document without that key, as JSON with sorted keys."""

from __future__ import annotations

import hashlib
import json


def json_sum(document: dict, own_key: str) -> str:
    """The hex SHA-256 of ``document`` with ``own_key`` (where its sum is kept) left out."""
    body = {k: v for k, v in document.items() if k != own_key}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()
