"""Monostatic multi-target scenario with clutter, run through the per-radar tracker.

A 3-D surveillance radar (200 m / 0.2 deg / 0.2 deg, 4 s scan, batches of 45 deg sectors)
sees ``n_targets`` straight-flying air targets and uniform clutter.  Each plot carries the time
at which the antenna swept its azimuth.  Seeded RNG only; data time only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.evaluation.truth import TruthLabelledTracker
from service.geo import FloatArray, Site, enu_to_polar
from service.tracking import make_tracker
from service.tracking.base import PlotColumns, TrackTable
from service.tracking.params import TrackerParams


@dataclass(frozen=True)
class MonostaticScenario:
    """Parameters of the simulated scenario (all documented, all data time)."""

    n_targets: int = 100
    """Number of true targets, all present from the start."""
    clutter_per_scan: int = 100
    """Mean number of clutter plots per scan (Poisson), uniform in area, azimuth, elevation."""
    scans: int = 30
    """Number of antenna revolutions simulated."""
    sectors: int = 8
    """Batches per scan (each covers 360/sectors degrees of azimuth)."""
    scan_period_s: float = 4.0
    pd: float = 0.9
    """Detection probability per look."""
    range_min_m: float = 30_000.0
    range_max_m: float = 120_000.0
    """Initial target ranges (uniform in area between them)."""
    clutter_range_max_m: float = 160_000.0
    speed_min_mps: float = 100.0
    speed_max_mps: float = 300.0
    alt_min_m: float = 1_000.0
    alt_max_m: float = 10_000.0
    clutter_max_elevation_deg: float = 10.0
    t0_s: float = 1_763_769_600.0


SITE = Site("M", 31.2, 118.5, 40.0, range_sigma_m=200.0, azimuth_sigma_deg=0.2, elevation_sigma_deg=0.2)


@dataclass(frozen=True)
class Truth:
    """Straight-line truth in the site's ENU frame: ``p(t) = p0 + v (t - t0)``."""

    names: list[str]
    p0: FloatArray  # (n, 3)
    v: FloatArray  # (n, 3)
    t0_s: float

    def at(self, t: FloatArray) -> FloatArray:
        return self.p0 + self.v * (np.asarray(t) - self.t0_s)[..., None]


def simulate(
    scn: MonostaticScenario, rng: np.random.Generator, site: Site = SITE
) -> tuple[list[tuple[PlotColumns, float]], Truth, FloatArray]:
    """Batches ``(plots, batch_time)``, the truth, and each target's first detection time."""
    n = scn.n_targets
    r0 = np.sqrt(rng.uniform(scn.range_min_m**2, scn.range_max_m**2, n))
    az0 = rng.uniform(0, 2 * np.pi, n)
    alt = rng.uniform(scn.alt_min_m, scn.alt_max_m, n)
    p0 = np.stack([r0 * np.sin(az0), r0 * np.cos(az0), alt], axis=1)
    sp = rng.uniform(scn.speed_min_mps, scn.speed_max_mps, n)
    hd = rng.uniform(0, 2 * np.pi, n)
    v = np.stack([sp * np.sin(hd), sp * np.cos(hd), np.zeros(n)], axis=1)
    truth = Truth([f"tgt-{k}" for k in range(n)], p0, v, scn.t0_s)
    T = scn.scan_period_s
    sector_deg = 360.0 / scn.sectors
    first_det = np.full(n, np.inf)
    batches: list[tuple[PlotColumns, float]] = []
    sig = np.array([site.range_sigma_m, site.azimuth_sigma_deg, site.elevation_sigma_deg])
    for s in range(scn.scans):
        ts = scn.t0_s + s * T
        # Time at which the antenna sweeps each target (two fixed-point steps).
        t = np.full(n, ts)
        for _ in range(2):
            _, az, _ = enu_to_polar(truth.at(t))
            t = ts + az / 360.0 * T
        r, az, el = enu_to_polar(truth.at(t))
        det = rng.random(n) < scn.pd
        first_det = np.where(det & ~np.isfinite(first_det), t, first_det)
        noise = rng.normal(size=(n, 3)) * sig
        tr = np.stack([r, az, el], axis=1) + noise
        tr[:, 1] = np.mod(tr[:, 1], 360.0)
        k = rng.poisson(scn.clutter_per_scan)
        cr = np.sqrt(rng.uniform(scn.range_min_m**2 / 4, scn.clutter_range_max_m**2, k))
        caz = rng.uniform(0, 360.0, k)
        cel = rng.uniform(0, scn.clutter_max_elevation_deg, k)
        all_r = np.concatenate([tr[det, 0], cr])
        all_az = np.concatenate([tr[det, 1], caz])
        all_el = np.concatenate([tr[det, 2], cel])
        all_t = ts + all_az / 360.0 * T
        names = np.array(truth.names, dtype=object)[det]
        all_truth = np.concatenate([names, np.full(k, None, dtype=object)])
        sector = np.minimum((all_az // sector_deg).astype(int), scn.sectors - 1)
        for q in range(scn.sectors):
            m = np.flatnonzero(sector == q)
            m = m[rng.permutation(m.shape[0])]  # plots inside a batch are not sorted
            cols = PlotColumns(
                all_t[m], all_r[m], all_az[m], all_el[m], np.full(m.shape[0], np.nan), all_truth[m]
            )
            batches.append((cols, ts + (q + 1) * T / scn.sectors))
    return batches, truth, first_det


@dataclass(frozen=True)
class MonostaticResult:
    completeness: float
    false_ratio: float
    duplicate_ratio: float
    rmse_m: float
    time_to_confirm_s: float
    confirmed: int
    completeness_curve: FloatArray  # per scan
    scan_times: FloatArray


def score_tracks(
    table: TrackTable, truth: Truth, site: Site, match_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per confirmed track: matched target index (-1 false), its position error, duplicate flag."""
    conf = table.take(table.confirmed)
    idx = {name: q for q, name in enumerate(truth.names)}
    target = np.array([idx.get(t, -1) if t is not None else -1 for t in conf.truth_id], dtype=np.intp)
    enu = site.ecef_to_enu(conf.position_ecef_m)
    err = np.full(len(conf), np.inf)
    ok = target >= 0
    if ok.any():
        tt = target[ok]
        true_pos = truth.p0[tt] + truth.v[tt] * (conf.time_s[ok] - truth.t0_s)[:, None]
        err[ok] = np.linalg.norm(enu[ok] - true_pos, axis=1)
    target = np.where(err <= match_m, target, -1)
    dup = np.zeros(len(conf), dtype=bool)
    good = np.flatnonzero(target >= 0)
    if good.shape[0]:
        _, first = np.unique(target[good], return_index=True)
        d = np.ones(good.shape[0], dtype=bool)
        d[first] = False
        dup[good[d]] = True
    return target, err, dup


def run_monostatic(
    scn: MonostaticScenario,
    initiator: str,
    seed: int,
    params: TrackerParams | None = None,
    match_m: float = 2_000.0,
) -> MonostaticResult:
    """Run one scenario realisation through one tracker; metrics at the end of the run."""
    rng = np.random.default_rng(seed)
    batches, truth, first_det = simulate(scn, rng)
    tracker = TruthLabelledTracker(make_tracker(SITE, initiator=initiator, id_prefix="M", params=params))
    n = scn.n_targets
    confirmed_at = np.full(n, np.inf)
    sq_err: list[np.ndarray] = []
    curve = []
    times = []
    for k, (plots, tb) in enumerate(batches):
        tracker.update(plots, tb)
        if (k + 1) % scn.sectors == 0:
            target, err, dup = score_tracks(tracker.tracks(), truth, SITE, match_m)
            good = target >= 0
            confirmed_at[target[good]] = np.minimum(confirmed_at[target[good]], tb)
            sq_err.append(err[good & ~dup] ** 2)
            curve.append(np.unique(target[good]).shape[0] / n)
            times.append(tb - scn.t0_s)
    target, err, dup = score_tracks(tracker.tracks(), truth, SITE, match_m)
    n_conf = target.shape[0]
    found = np.unique(target[target >= 0]).shape[0]
    ttc = confirmed_at - first_det
    errs = np.concatenate(sq_err) if sq_err else np.empty(0)
    return MonostaticResult(
        completeness=found / n,
        false_ratio=float(np.sum(target < 0) / max(n_conf, 1)),
        duplicate_ratio=float(np.sum(dup) / max(n_conf, 1)),
        rmse_m=float(np.sqrt(np.mean(errs))) if errs.shape[0] else float("nan"),
        time_to_confirm_s=float(np.mean(ttc[np.isfinite(ttc)])) if np.isfinite(ttc).any() else float("nan"),
        confirmed=n_conf,
        completeness_curve=np.array(curve),
        scan_times=np.array(times),
    )
