"""Candidate tracks as groups of plots, and the birth of a track state from a group.

A :class:`Groups` is a flat, CSR-like list: ``plot[k]`` belongs to candidate ``group[k]``
(labels ``0..count-1``).  Every initiator returns one, so the track manager treats them alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.geo import FloatArray
from service.tracking import kalman
from service.tracking.measurement import Measurements

IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class Groups:
    """Candidate tracks: ``plot[k]`` is a plot index of candidate ``group[k]``."""

    plot: IntArray
    group: IntArray
    count: int

    @staticmethod
    def empty() -> Groups:
        return Groups(np.empty(0, dtype=np.intp), np.empty(0, dtype=np.intp), 0)

    @staticmethod
    def from_lists(members: list[IntArray] | list[list[int]]) -> Groups:
        if not members:
            return Groups.empty()
        sizes = np.array([len(m) for m in members], dtype=np.intp)
        plot = np.concatenate([np.asarray(m, dtype=np.intp) for m in members])
        return Groups(plot, np.repeat(np.arange(len(members), dtype=np.intp), sizes), len(members))

    def to_lists(self) -> list[IntArray]:
        order = np.argsort(self.group, kind="stable")
        bounds = np.searchsorted(self.group[order], np.arange(self.count + 1))
        p = self.plot[order]
        return [p[bounds[g] : bounds[g + 1]] for g in range(self.count)]

    def sizes(self) -> IntArray:
        return np.bincount(self.group, minlength=self.count).astype(np.intp)


@dataclass(frozen=True)
class Births:
    """States fitted to candidate groups, at the time of each group's last plot."""

    x: FloatArray  # (g, 6)
    P: FloatArray  # (g, 6, 6)
    time_s: FloatArray  # (g,)
    mean_nis: FloatArray  # (g,) mean NIS of updates after the second plot (0 if none)
    plots: NDArray[np.int64]  # (g,)


def fit_groups(meas: Measurements, groups: Groups, q: float, velocity_sigma_mps: float) -> Births:
    """CV Kalman filter run over each group's plots in time order, all groups at once.

    Initialised on the first plot (position ``z_1``, covariance ``R_1``; velocity 0 with
    ``velocity_sigma_mps``), then updated plot by plot; the loop runs over the plot rank
    within a group (a handful of steps), never over groups.
    """
    g = groups.count
    if g == 0:
        return Births(np.empty((0, 6)), np.empty((0, 6, 6)), np.empty(0), np.empty(0), np.empty(0, np.int64))
    order = np.lexsort((meas.time_s[groups.plot], groups.group))
    grp = groups.group[order]
    plot = groups.plot[order]
    sizes = np.bincount(grp, minlength=g)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    rank = np.arange(grp.shape[0]) - starts[grp]
    length = int(sizes.max())
    table = np.full((g, length), -1, dtype=np.intp)
    table[grp, rank] = plot

    first = table[:, 0]
    x = np.zeros((g, 6))
    x[:, :3] = meas.enu_m[first]
    P = np.zeros((g, 6, 6))
    P[:, :3, :3] = meas.covariance[first]
    P[:, 3:, 3:] = np.eye(3) * velocity_sigma_mps**2
    t = meas.time_s[first].copy()
    nis_sum = np.zeros(g)
    nis_n = np.zeros(g)
    for k in range(1, length):
        active = table[:, k] >= 0
        idx = table[active, k]
        xa, pa = kalman.predict(x[active], P[active], meas.time_s[idx] - t[active], q)
        xa, pa, nis = kalman.update(xa, pa, meas.enu_m[idx], meas.covariance[idx])
        x[active], P[active], t[active] = xa, pa, meas.time_s[idx]
        if k >= 2:
            nis_sum[active] += nis
            nis_n[active] += 1
    mean_nis = np.where(nis_n > 0, nis_sum / np.maximum(nis_n, 1), 0.0)
    return Births(x, P, t, mean_nis, sizes.astype(np.int64))
