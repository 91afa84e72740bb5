"""Classic and probabilistic-grid Hough transforms for track initiation (2-D plane).

Hough paper (Wang et al., Control and Decision 28(4), 2013), Section 1, after Zhao, Rao,
Wang (Acta Aeronautica 2010):

* classic Hough: every plot ``(x, y)`` votes once for each normal angle ``theta`` into the
  cell of ``rho = x cos(theta) + y sin(theta)``; peaks of the accumulator are lines;
* probabilistic grid (Eq. 2-6): each plot becomes a probability over the cells of a grid of
  the surveillance plane: the Gaussian density of the plot (Eq. 2), truncated at 3 sigma,
  integrated over each cell (Eq. 4, midpoint rule on a sub-lattice) and normalised (Eq. 5);
  the grids of all plots of all radars are summed (Eq. 6) and the Hough transform runs over
  the non-empty cells, each voting with its probability.

Eq. (2) is written in the bistatic measurement space ``(rho, theta)``.  Here the density is
its first-order image in the plane: ``N(x; x_hat, C)`` with ``C = J diag(s_rho^2, s_theta^2)
J^T`` the plot's position covariance.  This is exact to first order in the errors (a few
hundred metres at tens of kilometres) and works for any sensor whose plots carry a covariance
(monostatic or bistatic), which is what the paper's "location error" already assumes.

Lines are extracted sequentially (the usual way to stop one target's plots feeding several
peaks): the strongest peak at or above ``min_votes`` gives a line, its preliminary track is
the plots close to it (classic: a fixed half-band; PG: ``member_sigma`` times each plot's own
sigma normal to the line, so accurate plots get tight bands), those plots are removed and the
accumulator is rebuilt from the rest, up to ``max_lines`` times.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter

from service.geo import FloatArray
from service.tracking.groups import Groups, IntArray
from service.tracking.params import HoughParams


@dataclass(frozen=True)
class Accumulator:
    """A (theta, rho) accumulator around ``centre`` (coordinates are relative to it)."""

    votes: FloatArray  # (theta_bins, rho_bins)
    theta: FloatArray  # (theta_bins,) cell angles (rad)
    rho0: float  # rho of the first cell's centre
    rho_step: float
    centre: FloatArray  # (2,)

    def line(self, ti: IntArray, ri: IntArray) -> tuple[FloatArray, FloatArray]:
        return self.theta[ti], self.rho0 + ri.astype(float) * self.rho_step


def accumulate(
    points: FloatArray, weights: FloatArray, centre: FloatArray, p: HoughParams, extent: float | None = None
) -> Accumulator:
    """Hough accumulator of weighted points (classic: weights 1; PG: cell probabilities).

    ``extent`` (m) fixes the rho range to ``[-extent, extent]`` (default: the points' own), so
    that accumulators of different subsets share their cells.
    """
    theta = (np.arange(p.theta_bins) + 0.5) * np.pi / p.theta_bins
    rel = points - centre
    if extent is None:
        extent = float(np.max(np.linalg.norm(rel, axis=1))) if rel.shape[0] else 0.0
    n_rho = 2 * int(np.ceil(extent / p.rho_step_m)) + 3
    rho0 = -(n_rho // 2) * p.rho_step_m
    rho = rel[:, 0, None] * np.cos(theta) + rel[:, 1, None] * np.sin(theta)  # (n, theta_bins)
    ri = np.rint((rho - rho0) / p.rho_step_m).astype(np.intp)
    flat = np.arange(p.theta_bins)[None, :] * n_rho + ri
    votes = (
        np.bincount(flat.ravel(), weights=np.repeat(weights, p.theta_bins), minlength=p.theta_bins * n_rho)
        .reshape(p.theta_bins, n_rho)
        .astype(float)
    )
    return Accumulator(votes, theta, rho0, p.rho_step_m, centre)


def peaks(
    acc: Accumulator, p: HoughParams, min_votes: float | None = None
) -> tuple[IntArray, IntArray, FloatArray]:
    """Local maxima at or above ``min_votes`` (default ``p.min_votes``), strongest first."""
    v = acc.votes
    floor = p.min_votes if min_votes is None else min_votes
    mx = maximum_filter(v, size=p.peak_neighbourhood, mode="nearest")
    ti, ri = np.nonzero((v >= mx) & (v >= floor) & (v > 0))
    h = v[ti, ri]
    order = np.lexsort((ri, ti, -h))
    return ti[order], ri[order], h[order]


def _sequential(
    n: int, min_plots: int, max_lines: int, line_members: Callable[[IntArray], IntArray | None]
) -> Groups:
    """Sequential extraction: strongest line of the remaining plots, remove its plots, repeat.

    ``line_members(remaining)`` returns the members (indices into all plots) of the strongest
    peak of the accumulator built from ``remaining`` plots, or None when no peak is left.
    The loop runs over extracted lines (a handful), never over plots.
    """
    remaining = np.arange(n)
    out: list[IntArray] = []
    for _ in range(max_lines):
        if remaining.shape[0] < min_plots:
            break
        members = line_members(remaining)
        if members is None or members.shape[0] < min_plots:
            break
        out.append(members)
        remaining = np.setdiff1d(remaining, members)
    return Groups.from_lists(out)


def _centre(xy: FloatArray) -> FloatArray:
    return 0.5 * (xy.min(axis=0) + xy.max(axis=0))


def classic_hough(xy: FloatArray, p: HoughParams) -> Groups:
    """Classic Hough transform: preliminary tracks from unit votes (Table 1 baseline)."""
    if xy.shape[0] < p.min_plots:
        return Groups.empty()
    centre = _centre(xy)

    def members(rem: IntArray) -> IntArray | None:
        acc = accumulate(xy[rem], np.ones(rem.shape[0]), centre, p)
        ti, ri, _ = peaks(acc, p)
        if ti.shape[0] == 0:
            return None
        th, rh = acc.line(ti[:1], ri[:1])
        rel = xy[rem] - centre
        dist = np.abs(rel[:, 0] * np.cos(th[0]) + rel[:, 1] * np.sin(th[0]) - rh[0])
        return rem[dist <= p.member_band_m]

    return _sequential(xy.shape[0], p.min_plots, p.max_lines, members)


def probability_grid(xy: FloatArray, cov: FloatArray, p: HoughParams) -> tuple[FloatArray, FloatArray]:
    """Eq. (2)-(6): summed cell probabilities; returns (cell centres (m, 2), probabilities (m,)).

    Only non-empty cells are returned (a sparse form of the matrix P of Eq. 6).
    """
    n = xy.shape[0]
    cell = p.cell_m
    sd = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))  # (n, 2)
    half = int(min(np.ceil(p.truncate_sigma * float(sd.max()) / cell) + 1, 64))
    origin = xy.min(axis=0) - cell * (half + 1)  # every cell index below is >= 0
    offs = np.arange(-half, half + 1)
    k = offs.shape[0]
    s = p.subsamples
    sub = (np.arange(s) + 0.5) / s - 0.5  # sub-lattice offsets within a cell, in cells
    base = np.floor((xy - origin) / cell).astype(np.intp)  # (n, 2) cell of each plot
    # Cell indices and sub-sample points: (n, k, k) cells, each with s*s points.
    ci = base[:, 0, None, None] + offs[None, :, None]
    cj = base[:, 1, None, None] + offs[None, None, :]
    ci = np.broadcast_to(ci, (n, k, k))
    cj = np.broadcast_to(cj, (n, k, k))
    px = origin[0] + (ci[..., None, None] + 0.5 + sub[:, None]) * cell  # (n, k, k, s, 1)
    py = origin[1] + (cj[..., None, None] + 0.5 + sub[None, :]) * cell  # (n, k, k, 1, s)
    dx = px - xy[:, 0, None, None, None, None]
    dy = py - xy[:, 1, None, None, None, None]
    dx, dy = np.broadcast_arrays(dx, dy)
    inv = np.linalg.inv(cov)  # (n, 2, 2)
    a = inv[:, 0, 0, None, None, None, None]
    b = inv[:, 0, 1, None, None, None, None]
    c = inv[:, 1, 1, None, None, None, None]
    m2 = a * dx * dx + 2 * b * dx * dy + c * dy * dy
    det = np.linalg.det(cov)[:, None, None, None, None]
    dens = np.exp(-0.5 * m2) / (2 * np.pi * np.sqrt(det))  # Eq. (2), first-order image
    dens = np.where(m2 <= p.truncate_sigma**2, dens, 0.0)  # 3-sigma truncation
    p2 = dens.mean(axis=(-1, -2)) * cell * cell  # Eq. (4), midpoint rule
    tot = p2.sum(axis=(1, 2))
    p2 = p2 / np.where(tot > 0, tot, 1.0)[:, None, None]  # Eq. (5)
    keep = p2 > 0
    flat_i = ci[keep]
    flat_j = cj[keep]
    w = p2[keep]
    key = flat_i.astype(np.int64) * (1 << 31) + flat_j.astype(np.int64)
    uk, inv_k = np.unique(key, return_inverse=True)
    summed = np.bincount(inv_k, weights=w)  # Eq. (6): sum over all plots of all radars
    ii = uk // (1 << 31)
    jj = uk % (1 << 31)
    centres = origin + (np.stack([ii, jj], axis=1).astype(float) + 0.5) * cell
    return np.asarray(centres, dtype=float), np.asarray(summed, dtype=float)


def pg_hough(xy: FloatArray, cov: FloatArray, p: HoughParams) -> Groups:
    """Probabilistic-grid Hough transform: preliminary tracks (Table 1 baseline, stage 1)."""
    if xy.shape[0] < p.min_plots:
        return Groups.empty()
    centre = _centre(xy)

    def members(rem: IntArray) -> IntArray | None:
        centres, prob = probability_grid(xy[rem], cov[rem], p)  # Eq. (2)-(6) of remaining plots
        acc = accumulate(centres, prob, centre, p)
        ti, ri, _ = peaks(acc, p, p.pg_min_votes)
        if ti.shape[0] == 0:
            return None
        th, rh = acc.line(ti[:1], ri[:1])
        return rem[line_band(xy[rem], cov[rem], centre, float(th[0]), float(rh[0]), p)]

    return _sequential(xy.shape[0], p.min_plots, p.max_lines, members)


def line_band(
    xy: FloatArray, cov: FloatArray, centre: FloatArray, theta: float, rho: float, p: HoughParams
) -> np.ndarray:
    """Plots within ``member_sigma`` of their own sigma normal to the line (PG membership)."""
    c, s = float(np.cos(theta)), float(np.sin(theta))
    rel = xy - centre
    dist = np.abs(rel[:, 0] * c + rel[:, 1] * s - rho)
    var_n = cov[:, 0, 0] * c * c + 2 * cov[:, 0, 1] * c * s + cov[:, 1, 1] * s * s
    return np.asarray(dist <= p.member_sigma * np.sqrt(var_n))


def pg_hough_bands(xy: FloatArray, cov: FloatArray, p: HoughParams) -> list[tuple[IntArray, float]]:
    """Preliminary tracks for velocity clustering: the band of every peak (Eq. 2-6).

    The paper runs the Hough transform once and clusters each preliminary track.  Unlike
    :func:`pg_hough` (a baseline, sequential: a line's plots are removed before the next
    line), the bands here may share plots: a strong line cutting across several targets must
    not steal their plots before velocity clustering has looked at them.  Peaks are taken
    strongest first, at or above ``pg_min_votes``, at most ``max_lines``, non-maximum suppressed
    over ``peak_neighbourhood`` cells; bands with fewer than ``min_plots`` plots are dropped.
    Which plots start which track is decided afterwards over all bands together
    (:func:`service.tracking.velocity_tracks.global_tracks`).  Returns ``(plots, theta)``
    per band, ``theta`` the line's normal angle (rad).
    """
    if xy.shape[0] < p.min_plots:
        return []
    centre = _centre(xy)
    centres, prob = probability_grid(xy, cov, p)  # Eq. (2)-(6)
    acc = accumulate(centres, prob, centre, p)
    ti, ri, _ = peaks(acc, p, p.pg_min_votes)
    th, rh = acc.line(ti[: p.max_lines], ri[: p.max_lines])
    bands = []
    for a, r in zip(th.tolist(), rh.tolist(), strict=True):  # loop over peaks (lines)
        band = np.flatnonzero(line_band(xy, cov, centre, a, r, p))
        if band.shape[0] >= p.min_plots:
            bands.append((band, float(a)))
    return bands
