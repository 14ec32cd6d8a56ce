"""The one exception the data layer raises for bad input, and the warning it gives for doubtful input."""

from __future__ import annotations

from typing import Any

from ttsim_jax.errors import UserError


class _Located:
    """Message and attributes of a problem located in measured data (file, table, row, column,
    value); the base of :class:`DataError` and :class:`DataWarning`."""

    def __init__(
        self,
        problem: str,
        *,
        file: Any = None,
        table: str | None = None,
        row: int | None = None,
        column: str | None = None,
        value: Any = None,
        row_label: str = "row",
    ) -> None:
        self.problem = problem
        self.file = None if file is None else str(file)
        self.table = table
        self.row = None if row is None else int(row)
        self.column = column
        self.value = value
        self.row_label = row_label
        where = []
        if self.file is not None:
            where.append(f"file {self.file}")
        if table is not None:
            where.append(f"table '{table}'")
        if row is not None:
            where.append(f"{row_label} {self.row}")
        if column is not None:
            where.append(f"column '{column}'")
        if value is not None:
            where.append(f"value {_show(value)}")
        super().__init__((", ".join(where) + ": " if where else "") + problem)


class DataError(_Located, UserError, ValueError):
    """Bad measured data, located as precisely as the input allows.

    The message names the file (or in-memory table), the row, the column and the offending value,
    so that a user can open the file and fix it without reading code.

    Attributes:
        problem: what is wrong, in words.
        file: path or label of the file (``None`` for in-memory data).
        table: table name (``observations``, ``events``, ...), if any.
        row: row of the offending value; for Parquet tables the 0-based row index, for CSV files
            the 1-based line number (``row_label`` says which).
        column: column name, if any.
        value: the offending value, if any.
    """


class DataWarning(_Located, UserWarning):
    """Doubtful measured data that is still used: a value at the edge of what table tennis
    produces, or a dataset that cannot show its own corruption (written without page checksums).

    Located and worded like :class:`DataError` (same attributes); emitted with
    :func:`warnings.warn`, so that a caller can show, record or silence it.
    """


def _show(value: Any) -> str:
    # repr() of numpy scalars is noisy ("np.float64(1.0)"); users want the number as in the file.
    try:
        import numpy as np

        if isinstance(value, np.generic):
            value = value.item()
    except ImportError:  # pragma: no cover - numpy is a hard dependency
        pass
    return repr(value)
