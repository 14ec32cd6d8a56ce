"""The README's API example runs as written, and its two commands are the ones CI uses."""

import re

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_readme_api_example_runs():
    text = (REPO / "README.md").read_text()
    code = re.search(r"## The API in ten lines\n\n```python\n(.*?)```", text, re.S).group(1)
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert namespace["out"].events.kind.shape[0] == 1


def test_ci_runs_the_readme_test_command():
    text = (REPO / "README.md").read_text()
    command = re.search(r"\*\*Run the tests:\*\*\n\n```bash\n(.*?)\n```", text, re.S).group(1).strip()
    assert command in (REPO / ".ci" / "run").read_text()
