"""Row operations of the columnar tables: dataclasses whose fields are arrays of one length.

One implementation of taking rows and joining tables for every such table (plots, tracks,
decisions, members), so that a field added to a table is taken and joined without more code.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields
from functools import cache
from typing import Any, TypeVar

import numpy as np

T = TypeVar("T")


@cache
def column_names(cls: type) -> tuple[str, ...]:
    """The fields of the table class ``cls``, in order (once per class: :func:`fields` costs
    more than taking a small table's rows)."""
    return tuple(f.name for f in fields(cls))


def take_rows(table: T, index: Any, **given: Any) -> T:
    """The rows ``index`` (indices or a mask) of every column of ``table``; a field named in
    ``given`` takes that value instead (a column that is not an array)."""
    cls: Any = type(table)
    cols = {n: getattr(table, n)[index] for n in column_names(cls) if n not in given}
    return cls(**cols, **given)


def put_rows(table: T, index: Any, rows: T) -> T:
    """A copy of ``table`` with its rows ``index`` (indices) replaced by ``rows``, row for row:
    one copy of each column where taking and joining would make two."""
    cls: Any = type(table)
    cols = {}
    for n in column_names(cls):
        col = getattr(table, n).copy()
        col[index] = getattr(rows, n)
        cols[n] = col
    return cls(**cols)


def concat_rows(cls: type[T], parts: Sequence[T], **given: Any) -> T:
    """The rows of ``parts`` (at least one) one after the other, column by column; a field
    named in ``given`` takes that value instead."""
    names = column_names(cls)  # type: ignore[arg-type]  # (a class is hashable)
    cols = {n: np.concatenate([getattr(p, n) for p in parts]) for n in names if n not in given}
    return cls(**cols, **given)


def row_bits(columns: Sequence[tuple[Any, int]]) -> np.ndarray:
    """Float columns, each ``(values, width)`` with ``width`` values a row, as the 64-bit
    patterns of their values side by side, one row per table row: rows compared by these are
    equal exactly when every value is the same bit for bit (a NaN equals the same NaN, ``-0.0``
    differs from ``0.0``)."""
    n = len(columns[0][0]) if columns else 0
    parts = [np.asarray(values, dtype=np.float64).reshape(n, width) for values, width in columns]
    return np.ascontiguousarray(np.concatenate(parts, axis=1)).view(np.int64)
