"""Time of one association by the ``gmm`` and ``cfar`` correlators at 20 / 50 / 100 tracks.

Run: ``.venv/bin/python bench/bench_gmm_cfar.py [--repeats N]``.  Prints the median wall time of
one call (and the share of correct pairs, as a sanity check) per method and scene size.  Scenes
are seeded; timing is the only thing here that depends on the machine.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from service.correlation.cfar import cfar_associate
from service.correlation.gmm import gmm_associate


def gmm_scene(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` targets at 0.02 per km^2 (about the density of the paper's scene after 100 periods)
    around (73, 73) km; radar A sees 90 %, B 70 %; B is rotated 1.5 deg about radar A, shifted
    by (1.2, -0.8) km, and both carry 100 m random errors per axis."""
    half = 0.5e3 * np.sqrt(n / 0.02)  # half side (m) of the square holding n targets
    truth = rng.uniform(73e3 - half, 73e3 + half, (n, 2))
    ids_a = np.flatnonzero(rng.random(n) < 0.9)
    ids_b = np.flatnonzero(rng.random(n) < 0.7)
    ang = np.radians(1.5)
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    pos_a = truth[ids_a] + rng.normal(0.0, 100.0, (ids_a.size, 2))
    pos_b = truth[ids_b] @ rot.T + np.array([1200.0, -800.0]) + rng.normal(0.0, 100.0, (ids_b.size, 2))
    return pos_a, pos_b, ids_a, ids_b


def sea_scene(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` vessels over 100 x 100 km, 80 % with AIS, 90 % tracked by the radar, bias 500 m /
    0.5 deg, track errors 30 m / 0.1 deg (as tests/correlation/test_correlation_cfar.py)."""
    xy = np.column_stack([rng.uniform(-50e3, 50e3, n), rng.uniform(10e3, 110e3, n)])
    r = np.hypot(xy[:, 0], xy[:, 1])
    az = np.mod(np.degrees(np.arctan2(xy[:, 0], xy[:, 1])), 360.0)
    ais = np.flatnonzero(rng.random(n) < 0.8)
    rad = np.flatnonzero(rng.random(n) < 0.9)
    ref = np.column_stack([r[ais], az[ais]])
    meas = np.column_stack(
        [
            r[rad] + 500.0 + 30.0 * rng.standard_normal(rad.size),
            np.mod(az[rad] + 0.5 + 0.1 * rng.standard_normal(rad.size), 360.0),
        ]
    )
    return ref, meas, ais, rad


def bench(
    name: str,
    scene: Callable[[np.random.Generator, int], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    run: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
    repeats: int,
) -> None:
    for n in (20, 50, 100):
        rng = np.random.default_rng(n)
        times, correct, common = [], 0, 0
        for _ in range(repeats):
            a, b, ids_a, ids_b = scene(rng, n)
            t0 = time.perf_counter()
            ia, ib = run(a, b)
            times.append(time.perf_counter() - t0)
            correct += int(np.sum(ids_a[ia] == ids_b[ib]))
            common += len(np.intersect1d(ids_a, ids_b))
        print(
            f"{name:5s} n={n:3d}  tracks {len(a):3d} x {len(b):3d}  median {1e3 * np.median(times):8.2f} ms"
            f"  max {1e3 * np.max(times):8.2f} ms  correct {correct / max(common, 1):.3f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()

    def run_gmm(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        res = gmm_associate(a, b)
        return res.index_a, res.index_b

    def run_cfar(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        res = cfar_associate(a, b)
        return res.index_ref, res.index_radar

    bench("gmm", gmm_scene, run_gmm, args.repeats)
    bench("cfar", sea_scene, run_cfar, args.repeats)
    dense_start(max(args.repeats, 20))


def dense_start(scenes: int) -> None:
    """The GMM paper's scene at period 0 (20 targets in 3 x 3 km) and later periods: correct rate."""
    from dataclasses import replace

    from service.correlation.gmm import GmmParams
    from topofusion_lab.evaluation.correlation_gmm_scene import paper_scene

    for label, params in (
        ("gmm", GmmParams()),
        ("gmm, no omega floor", replace(GmmParams(), omega_floor_from_counts=False)),
    ):
        rates = []
        for period in (0, 10, 25, 99):
            rng = np.random.default_rng(11)
            ok = common = 0
            for _ in range(scenes):
                pa, pb, ia, ib = paper_scene(rng, at_period=period)
                r = gmm_associate(pa, pb, params)
                ok += int(np.sum(ia[r.index_a] == ib[r.index_b]))
                common += len(np.intersect1d(ia, ib))
            rates.append(f"period {period}: {ok / max(common, 1):.3f}")
        print(f"paper scene, {label:20s} " + ", ".join(rates))


if __name__ == "__main__":
    main()
