"""The JSON ending of a benchmark script: written to ``--out`` (folders made), or printed."""

from __future__ import annotations

import json
from pathlib import Path


def emit(report: dict, out: Path | None) -> None:
    """Writes ``report`` as indented JSON to ``out`` and says so, or prints it when ``out`` is None."""
    text = json.dumps(report, indent=2)
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n")
        print(f"written {out}")
    else:
        print(text)
