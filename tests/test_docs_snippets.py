"""Every Python snippet of the guides runs: each page's ```python blocks, in order, as one script in
a fresh process and an empty working directory (what a reader who pastes them gets)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)
PAGES = sorted(p for p in (REPO / "docs").rglob("*.md") if BLOCK.search(p.read_text()))


def test_the_guides_have_snippets():
    assert len(PAGES) >= 4, [p.name for p in PAGES]


#: Pages whose snippets run for minutes on two cores, with what else covers their code by default:
#: they run with ``-m slow``.
SLOW = {
    "functional-env.md": "a jitted scan of 64 environments of the default task: examples/functional_loop.py runs "
                         "the same loop on a small task (tests/env/test_single.py)",
    "simulate.md": "jax.grad of an 800-step rollout, a reverse pass through the kernel (the slow mark's kind); "
                   "simulate, rollout and the reference path are the kernel tests'",
}


@pytest.mark.parametrize("page", [pytest.param(p, marks=pytest.mark.slow) if p.name in SLOW else p for p in PAGES],
                         ids=[str(p.relative_to(REPO / "docs")) for p in PAGES])
def test_guide_snippets_run(page, tmp_path):
    script = "\n\n".join(BLOCK.findall(page.read_text()))
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONPATH=str(REPO))
    done = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=900)
    assert done.returncode == 0, f"{page.name}:\n{done.stderr[-3000:]}"
