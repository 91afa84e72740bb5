"""The recent reports of the bias-free references (ADS-B, AIS), interpolated to any time.

Reports are kept for ``history_s`` of data time and indexed by (id, time) once per assessment
step, so that looking up any number of (id, time) pairs is one ``searchsorted``.  Memory: one
row (about 60 bytes) per report kept, e.g. 1 500 aircraft reporting twice a second over 80 s:
240 000 rows, 14 MB.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ReferencePoints:
    """References at the asked times: ``ok`` where interpolated (else the row is NaN / None)."""

    ok: NDArray[np.bool_]
    ecef: FloatArray  # (n, 3)
    flight_level: FloatArray
    mode_3a: NDArray[np.object_]


class ReferenceHistory:
    """Reports by id: time, ECEF position, barometric flight level, Mode 3/A (None: none)."""

    def __init__(self, history_s: float, max_report_gap_s: float) -> None:
        self.history_s = history_s
        self.max_report_gap_s = max_report_gap_s
        self._codes: dict[str, int] = {}
        self._parts: list[
            tuple[FloatArray, NDArray[np.int64], FloatArray, FloatArray, NDArray[np.object_]]
        ] = []
        self.time_s = np.empty(0)
        self.code = np.empty(0, dtype=np.int64)
        self.ecef = np.empty((0, 3))
        self.flight_level = np.empty(0)
        self.mode_3a = np.empty(0, dtype=object)
        self._key = np.empty(0)
        self._base = 0.0
        self._span = 1.0
        self.newest_s = -np.inf

    def __len__(self) -> int:
        return int(self.time_s.size) + sum(p[0].size for p in self._parts)

    def codes(self, ids: NDArray[np.str_] | list[str]) -> NDArray[np.int64]:
        """Each id's number (new ids get new numbers)."""
        codes = self._codes
        return np.fromiter(
            (codes.setdefault(str(i), len(codes)) for i in ids), dtype=np.int64, count=len(ids)
        )

    def add(
        self,
        time_s: FloatArray,
        ids: NDArray[np.str_],
        ecef: FloatArray,
        flight_level: FloatArray,
        mode_3a: NDArray[np.object_],
    ) -> None:
        """One batch of reports (rows with a non-finite time or position are left out)."""
        good = np.isfinite(time_s) & np.isfinite(ecef).all(axis=1)
        if not good.any():
            return
        self._parts.append(
            (
                np.asarray(time_s, dtype=float)[good],
                self.codes(np.asarray(ids)[good]),
                np.asarray(ecef, dtype=float)[good],
                np.asarray(flight_level, dtype=float)[good],
                np.asarray(mode_3a, dtype=object)[good],
            )
        )
        self.newest_s = max(self.newest_s, float(np.max(time_s[good])))

    def index(self, now_s: float) -> None:
        """Take the batches added, forget reports older than ``history_s`` before ``now_s``,
        and sort by (id, time) for :meth:`at`."""
        if self._parts:
            parts = [(self.time_s, self.code, self.ecef, self.flight_level, self.mode_3a), *self._parts]
            self.time_s, self.code, self.ecef, self.flight_level, self.mode_3a = (
                np.concatenate([p[k] for p in parts]) for k in range(5)
            )
            self._parts = []
        keep = self.time_s >= now_s - self.history_s
        if not keep.all():
            self.time_s, self.code, self.ecef = self.time_s[keep], self.code[keep], self.ecef[keep]
            self.flight_level, self.mode_3a = self.flight_level[keep], self.mode_3a[keep]
        if len(self._codes) > 4 * max(64, np.unique(self.code).size):  # renumber: bounded by live ids
            names = np.array(list(self._codes), dtype=object)
            live = np.unique(self.code)
            self._codes = {str(names[c]): k for k, c in enumerate(live)}
            self.code = np.searchsorted(live, self.code).astype(np.int64)
        order = np.lexsort((self.time_s, self.code))
        self.time_s, self.code, self.ecef = self.time_s[order], self.code[order], self.ecef[order]
        self.flight_level, self.mode_3a = self.flight_level[order], self.mode_3a[order]
        self._base = float(self.time_s.min()) if self.time_s.size else 0.0
        self._span = (
            2.0 * (float(self.time_s.max()) - self._base + self.history_s) + 1.0 if self.time_s.size else 1.0
        )
        self._key = self.code * self._span + (self.time_s - self._base)

    def known(self, ids: list[str]) -> NDArray[np.int64]:
        """The numbers of ``ids`` (-1: never reported)."""
        return np.fromiter((self._codes.get(i, -1) for i in ids), dtype=np.int64, count=len(ids))

    def at(self, code: NDArray[np.int64], time_s: FloatArray) -> ReferencePoints:
        """Each id ``code[i]`` at ``time_s[i]``: linear between the reports on either side (no
        further apart than ``max_report_gap_s``); the Mode 3/A of the report before."""
        n = code.size
        ecef = np.full((n, 3), np.nan)
        fl = np.full(n, np.nan)
        m3a = np.full(n, None, dtype=object)
        if n == 0 or self._key.size == 0:
            return ReferencePoints(np.zeros(n, dtype=bool), ecef, fl, m3a)
        q = code * self._span + (time_s - self._base)
        hi = np.searchsorted(self._key, q, side="left")  # first report at or after
        lo = hi - 1
        last = self._key.size - 1
        hi_c, lo_c = np.minimum(hi, last), np.maximum(lo, 0)
        exact = (hi <= last) & (self.code[hi_c] == code) & (self.time_s[hi_c] == time_s)
        ok = (
            (lo >= 0)
            & (hi <= last)
            & (self.code[lo_c] == code)
            & (self.code[hi_c] == code)
            & (self.time_s[hi_c] - self.time_s[lo_c] <= self.max_report_gap_s)
        ) | exact
        lo_c = np.where(exact, hi_c, lo_c)
        t0, t1 = self.time_s[lo_c], self.time_s[hi_c]
        dt = t1 - t0
        w = np.where(dt > 0, (time_s - t0) / np.where(dt > 0, dt, 1.0), 0.0)[:, None]
        ecef[ok] = ((1.0 - w) * self.ecef[lo_c] + w * self.ecef[hi_c])[ok]
        f0, f1 = self.flight_level[lo_c], self.flight_level[hi_c]
        both = np.isfinite(f0) & np.isfinite(f1)
        wf = w[:, 0]
        level = np.where(both, (1.0 - wf) * f0 + wf * f1, np.where(np.isfinite(f0), f0, f1))
        fl[ok] = level[ok]
        m3a[ok] = np.where(
            np.array([x is not None for x in self.mode_3a[lo_c]], dtype=bool),
            self.mode_3a[lo_c],
            self.mode_3a[hi_c],
        )[ok]
        return ReferencePoints(ok, ecef, fl, m3a)
