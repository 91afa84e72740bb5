"""Benchmark: one radar, 1 000 targets + 200 clutter plots per scan, update time per scan.

Goal: <= 50 ms per scan on 2 cores.  Prints figures; never asserts timing.
Usage: .venv/bin/python bench/bench_tracking.py [--scans N] [--sectors K] [--initiator NAME]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from service.tracking import make_tracker
from topofusion_lab.evaluation.initiation_monostatic import SITE, MonostaticScenario, simulate


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scans", type=int, default=20)
    ap.add_argument("--sectors", type=int, default=8)
    ap.add_argument("--initiator", default="logic")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    scn = MonostaticScenario(
        n_targets=1000, clutter_per_scan=200, scans=a.scans, sectors=a.sectors, range_max_m=150_000.0
    )
    batches, _, _ = simulate(scn, np.random.default_rng(a.seed))
    tr = make_tracker(SITE, initiator=a.initiator)
    per_scan: list[float] = []
    acc = 0.0
    for k, (plots, tb) in enumerate(batches):
        t0 = time.perf_counter()
        tr.update(plots, tb)
        acc += time.perf_counter() - t0
        if (k + 1) % a.sectors == 0:
            per_scan.append(acc * 1000)
            acc = 0.0
    t0 = time.perf_counter()
    tab = tr.tracks()
    t_tab = (time.perf_counter() - t0) * 1000
    steady = np.array(per_scan[5:]) if len(per_scan) > 5 else np.array(per_scan)
    print(f"one radar, 1000 targets + 200 clutter/scan, {a.sectors} batches/scan, initiator {a.initiator}")
    print(f"scan update ms: first 5 {np.round(per_scan[:5], 1).tolist()}")
    print(
        f"steady state (scans 6..{len(per_scan)}): median {np.median(steady):.1f} ms, "
        f"p95 {np.percentile(steady, 95):.1f} ms, max {steady.max():.1f} ms per scan"
    )
    print(
        f"tracks(): {t_tab:.1f} ms; live {len(tab)}, confirmed {int(tab.confirmed.sum())}, "
        f"window plots {tr.window_plots}"
    )


if __name__ == "__main__":
    main()
