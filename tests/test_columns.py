"""The columnar tables' row operations (service.columns) against each field taken by hand."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from service.columns import take_rows
from service.correlation.base import Decisions
from service.fusion.members import _concat as members_concat
from service.fusion.system_tracks import Members
from service.tracking.base import PlotColumns, TrackTable

RNG = np.random.default_rng(7)


def _column(name: str, n: int) -> np.ndarray:
    if name in ("track_id", "source"):
        return np.array([f"{name}-{i}" for i in RNG.permutation(n)])
    if name in ("truth_id", "mode_3a", "mode_s"):
        return np.array([None if i % 3 else f"c{i}" for i in range(n)], dtype=object)
    if name in ("confirmed", "accepted", "reference"):
        return RNG.random(n) < 0.5
    if name in ("index_a", "index_b", "plots", "neighbors", "reason"):
        return RNG.integers(0, 50, n)
    if name in ("position_ecef_m", "velocity_ecef_mps", "position", "velocity"):
        return RNG.normal(size=(n, 3))
    if name == "covariance":
        return RNG.normal(size=(n, 6, 6))
    if name in ("pos_cov", "vel_cov"):
        return RNG.normal(size=(n, 3, 3))
    return RNG.normal(size=n)


def _table(cls: type, n: int) -> object:
    return cls(**{f.name: _column(f.name, n) for f in fields(cls) if f.name != "extras"})


def _concat(cls: type, parts: list[object]) -> object:
    if cls is Members:
        return members_concat(parts)  # type: ignore[arg-type]
    return cls.concat(parts)  # type: ignore[attr-defined]


@pytest.mark.parametrize("cls", [PlotColumns, TrackTable, Decisions, Members])
def test_take_and_concat_are_each_column_by_hand(cls: type) -> None:
    a, b = _table(cls, 9), _table(cls, 4)
    columns = [f.name for f in fields(cls) if f.name != "extras"]
    if hasattr(cls, "take"):
        for rows in (np.array([8, 0, 3, 3]), RNG.random(9) < 0.5):
            taken = a.take(rows)  # type: ignore[attr-defined]
            for name in columns:
                np.testing.assert_array_equal(getattr(taken, name), getattr(a, name)[rows])
    joined = _concat(cls, [a, b])
    for name in columns:
        want = np.concatenate([getattr(a, name), getattr(b, name)])
        np.testing.assert_array_equal(getattr(joined, name), want)


def test_decisions_keep_their_extras_and_fill_a_missing_one_with_nan() -> None:
    plain = Decisions.build(np.arange(3), np.arange(3))
    a = take_rows(plain, np.arange(3), extras={"stage": np.array([1.0, 2.0, 3.0])})
    b = Decisions.build(np.arange(2), np.arange(2))
    joined = Decisions.concat([a, b])
    np.testing.assert_array_equal(joined.extras["stage"], [1.0, 2.0, 3.0, np.nan, np.nan])
    np.testing.assert_array_equal(a.take(np.array([2, 0])).extras["stage"], [3.0, 1.0])
    np.testing.assert_array_equal(joined.index_a, [0, 1, 2, 0, 1])
