"""docs/data_format.md documents every column of the schema and the schema version."""

from __future__ import annotations

from pathlib import Path

from ttsim_jax.data import schema

DOC = Path(__file__).resolve().parents[2] / "docs" / "data_format.md"


def test_every_column_and_the_version_are_documented():
    text = DOC.read_text()
    assert f"Schema version: **{schema.SCHEMA_VERSION}**" in text
    assert schema.CANONICAL_FRAME in text
    for table, cols in schema.TABLES.items():
        assert f"### {table}" in text, table
        section = text.split(f"### {table}", 1)[1].split("\n### ", 1)[0]
        for c in cols:
            assert f"`{c.name}`" in section, f"{table}.{c.name} is not documented"
    for kind in schema.EVENT_KINDS:
        assert f"`{kind}`" in text
