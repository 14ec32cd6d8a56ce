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


def test_throughput_tables_are_the_committed_benchmark_json():
    import importlib.util
    import json

    spec = importlib.util.spec_from_file_location("readme_tables", REPO / "benchmarks" / "readme_tables.py")
    tables = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tables)
    blocks = tables.rendered()
    assert set(blocks) == {"peers-table", "peers-gpu-table", "peers-gpu-fused-table"}
    for name in ("README.md", "benchmarks/README.md"):
        for marker, table in blocks.items():
            assert tables.block_of((REPO / name).read_text(), marker) == table, \
                f"{name}: rerun python benchmarks/readme_tables.py --write README.md benchmarks/README.md"
    expected = blocks["peers-table"]
    # the check can fail: a changed number is caught
    assert tables.block_of(tables.replace_block("x\n" + tables.START + "\n" + tables.END, expected.replace("M", "k"),
                                                "t")) != expected
