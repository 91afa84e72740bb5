"""Plots of one batch in one resolution cell: one detection.

A radar's plot extractor reports one plot per target and resolution cell in a scan, so two
plots of one batch that agree in range, azimuth and elevation to a small fraction of the
radar's own errors (and carry the same Mode S address, Mode 3/A code and altitude) are one
detection reported twice: a
bridge or a recorder repeating a plot, or a hostile feed.  Kept as they are, N such plots
start N tracks on one point, and the initiator's candidate triples grow with the cube of N
(200 identical plots a batch slowed a whole service below real time).  The first of them (in
batch order) is kept, the others are dropped and counted.

The cells are a grid of ``fraction`` times the site's sigma on each coordinate (range,
azimuth, and elevation where the plot has one; a plot without elevation is in no cell with
one that has it), so two plots closer than that may fall on either side of a cell's edge and
both be kept: the rule removes repeats, it does not decide resolution.  At the default 0.05
sigma two distinct aircraft's plots share a cell about once in ten thousand scans of two
aircraft at the formation study's tightest spacing (one sigma apart).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from service.geo import Site
from service.tracking.base import PlotColumns


def first_in_cell(
    plots: PlotColumns, site: Site, fraction: float, altitude_sigma_m: float = 100.0
) -> NDArray[np.bool_]:
    """Which plots to keep: the first of each cell (module docstring); all of them when
    ``fraction`` is 0 or there is at most one plot.  A given altitude (Mode C, a 2-D radar's)
    is a coordinate too, in cells of ``fraction`` times ``altitude_sigma_m``."""
    n = len(plots)
    keep = np.ones(n, dtype=bool)
    if fraction <= 0.0 or n < 2:
        return keep
    # Plots in two range cells share no cell: the whole key is made only for those sharing one
    # (in a radar's batch, hardly ever any).
    ranges = np.floor(plots.range_m / (fraction * site.range_sigma_m))
    _, at, count = np.unique(ranges, return_inverse=True, return_counts=True)
    rows = np.flatnonzero(count[at.reshape(-1)] > 1)
    if rows.size == 0:
        return keep
    sub = plots.take(rows)
    has_el = np.isfinite(sub.elevation_deg)
    el = np.where(has_el, sub.elevation_deg, 0.0)
    codes = [
        np.unique(np.asarray([x or "" for x in labels], dtype=str), return_inverse=True)[1].reshape(-1)
        for labels in (sub.mode_s, sub.mode_3a)
    ]
    has_alt = np.isfinite(sub.altitude_m)
    alt = np.where(has_alt, sub.altitude_m, 0.0)
    cells = np.stack(
        [
            ranges[rows],
            np.floor(sub.azimuth_deg / (fraction * site.azimuth_sigma_deg)),
            np.floor(el / (fraction * site.elevation_sigma_deg)),
            has_el.astype(float),
            np.floor(alt / (fraction * altitude_sigma_m)),
            has_alt.astype(float),
            *(c.astype(float) for c in codes),
        ],
        axis=1,
    )
    _, first = np.unique(cells, axis=0, return_index=True)  # (the first of each, in batch order)
    keep[rows] = False
    keep[rows[first]] = True
    return keep
