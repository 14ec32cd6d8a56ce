"""The README's API example runs as written (as the start of docs/simulate.md's snippets), its
two commands are the ones CI uses, it stays a front page whose links (and the docs pages' links)
resolve, and the throughput tables of the docs and of benchmarks/README.md are those of the
committed benchmark JSON."""

import re

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
GRAD = re.compile(r"^(?:\w+ = )?jax\.grad\((.+)\)\((\w+)\)", re.M)  # the example's line ``g = jax.grad(f)(x)``


def api_example() -> str:
    text = (REPO / "README.md").read_text()
    return re.search(r"## The API in ten lines\n\n```python\n(.*?)```", text, re.S).group(1)


def run(code: str) -> dict:
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    return namespace


@pytest.mark.slow  # compiles the reverse pass through the kernel (about a minute)
def test_readme_api_example_runs():
    namespace = run(api_example())
    assert namespace["out"].events.kind.shape[0] == 1


def test_readme_api_example_is_the_simulate_guides_first_which_runs():
    """The README's example is, line for line, the start of docs/simulate.md's snippets, which
    test_docs_snippets.py runs as a reader pastes them (the gradient compiled and evaluated; with
    ``-m slow``, as a reverse pass through the kernel): one run covers both pages instead of
    tracing the same reverse pass twice."""
    blocks = re.findall(r"^```python\n(.*?)^```", (REPO / "docs" / "simulate.md").read_text(), re.S | re.M)
    assert blocks and blocks[0].startswith(api_example()), (
        "README.md's 'The API in ten lines' must be the first lines of docs/simulate.md's first snippet")
    assert GRAD.search(api_example()), "the README example has no line jax.grad(f)(x) any more"


def test_ci_runs_the_readme_test_command():
    text = (REPO / "README.md").read_text()
    command = re.search(r"\*\*Run the tests:\*\*\n\n```bash\n(.*?)\n```", text, re.S).group(1).strip()
    assert command in (REPO / ".ci" / "run").read_text()


LINK = re.compile(r"\]\(([^)\s]+)\)")  # a Markdown link's or image's target


def test_readme_is_a_front_page_and_every_relative_link_resolves():
    """At most 250 lines; every relative link of the README and of the docs pages names a file of
    the repository (``mkdocs build --strict`` checks the anchors too, but needs the docs extra)."""
    readme = (REPO / "README.md").read_text()
    assert len(readme.splitlines()) <= 250
    pages = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    assert len(pages) > 10, "the docs pages are missing"
    broken = []
    for page in pages:
        for target in LINK.findall(page.read_text()):
            path = target.split("#")[0]
            if path and not re.match(r"^[a-z]+:", path) and not (page.parent / path).exists():
                broken.append(f"{page.relative_to(REPO)}: {target}")
    assert not broken, broken


def test_throughput_tables_are_the_committed_benchmark_json():
    import importlib.util

    spec = importlib.util.spec_from_file_location("readme_tables", REPO / "benchmarks" / "readme_tables.py")
    tables = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tables)
    blocks = tables.rendered()
    assert set(blocks) == {"peers-table", "peers-gpu-table", "peers-gpu-fused-table", "peers-gpu-lean-table",
                           "peers-gpu-now-table", "peers-network-table", "peers-cpu-fused-table",
                           "peers-cpu-fused-long-table", "peers-gpu-d0605a4-table",
                           "peers-gpu-be0ffe5-table"}
    for name in ("docs/measurements/performance.md", "benchmarks/README.md"):
        for marker, table in blocks.items():
            assert tables.block_of((REPO / name).read_text(), marker) == table, (
                f"{name}: rerun python benchmarks/readme_tables.py --write docs/measurements/performance.md "
                "benchmarks/README.md")
    expected = blocks["peers-table"]
    # the check can fail: a changed number is caught
    assert tables.block_of(tables.replace_block("x\n" + tables.START + "\n" + tables.END, expected.replace("M", "k"),
                                                "t")) != expected
