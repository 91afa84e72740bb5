"""Plots of one batch in one resolution cell are one detection (``service.tracking.coincident``):
kept once, the others dropped and counted in ``/status``; distinct plots are all kept."""

from __future__ import annotations

import json

import numpy as np

from service.config import EngineConfig
from service.engine import Engine
from service.geo import Site
from service.tracking.base import PlotColumns
from service.tracking.coincident import first_in_cell

SITE = Site("P", 32.0, 119.0, 30.0, range_sigma_m=200.0, azimuth_sigma_deg=0.2, elevation_sigma_deg=0.2)


def _plots(
    rng: list[float], az: list[float], el: list[float], mode_s: list[str | None] | None = None
) -> PlotColumns:
    n = len(rng)
    f = np.asarray
    return PlotColumns(
        f(np.zeros(n)),
        f(rng, dtype=float),
        f(az, dtype=float),
        f(el, dtype=float),
        np.full(n, np.nan),
        np.full(n, None, dtype=object),
        mode_s=np.array(mode_s if mode_s else [None] * n, dtype=object),
    )


def test_the_first_of_each_cell_is_kept() -> None:
    """Repeats (the same cell: 0.05 of a sigma is 10 m and 0.01 deg here) are dropped after the
    first; a plot a cell away, one without elevation beside one with it, and one of another
    Mode S address are other detections."""
    r, a, e = 1e5 + 5.0, 10.005, 1.005  # (the middle of a cell)
    plots = _plots(
        [r, r, r + 3.0, r + 40.0, r, r, r],
        [a, a, a + 0.002, a, a, a, a],
        [e, e, e, e, np.nan, e, e],
        [None, None, None, None, None, "abc123", None],
    )
    keep = first_in_cell(plots, SITE, 0.05)
    assert keep.tolist() == [True, False, False, True, True, True, False]
    assert first_in_cell(plots, SITE, 0.0).all()  # (the rule off)
    # a 2-D radar's plots of one cell: another Mode 3/A code, or another Mode C altitude
    # (a holding stack), is another aircraft
    f = np.asarray
    flat = PlotColumns(
        f(np.zeros(4)),
        f([r] * 4),
        f([a] * 4),
        np.full(4, np.nan),
        f([3050.0, 3050.0, 3050.0, 3650.0]),
        np.full(4, None, dtype=object),
        mode_3a=np.array(["1234", "1234", "4321", "1234"], dtype=object),
    )
    assert first_in_cell(flat, SITE, 0.05).tolist() == [True, False, True, True]


def test_a_batch_of_one_point_repeated_makes_one_track_and_counts_the_repeats() -> None:
    """A radar sending the same plot 200 times a batch, a batch every half second (a broken
    bridge, or a hostile feed; every plot valid): one track, 199 plots a batch counted in
    ``/status`` ``plots_coincident``.  Before the rule it built 201 confirmed tracks on the
    point, and the initiator's triples of 200 plots a scan held the service's outputs back."""
    engine = Engine(EngineConfig(prefix="fusion"))
    site = {
        "radar_id": "P",
        "latitude_deg": 32.0,
        "longitude_deg": 119.0,
        "altitude_m": 30.0,
        "scan_period_s": 4.0,
    }
    engine.ingest("fusion/radar/P/site", json.dumps(site).encode())
    t0, n, batches = 1_800_000_000.0, 200, 40
    for k in range(batches):
        t = t0 + 0.5 * k
        plots = {
            "time_s": [t - 0.05] * n,
            "range_m": [1e5] * n,
            "azimuth_deg": [10.0] * n,
            "elevation_deg": [1.0] * n,
        }
        body = {"radar_id": "P", "seq": k + 1, "time_s": t, "plots": plots}
        engine.ingest("fusion/radar/P/plots", json.dumps(body).encode())
    engine.flush()
    status = engine.snapshot().status_core()["radars"][0]
    engine.close()
    assert status["plots_coincident"] == batches * (n - 1)
    assert status["tracks_confirmed"] + status["tracks_tentative"] <= 1
