"""Dense-formation stream bench of the ``gmm`` and ``svd-topology`` correlators (evaluation only).

A tight formation -- ``targets`` aircraft on a jittered square lattice, one heading, one speed,
one flight level -- seen by two biased radars 200 km apart, fed scan by scan through
:class:`service.correlation.PairCorrelator` exactly as the engine does.  The lattice spacing
is ``ratio`` times the larger cross-range track error of the two radars at the formation
(``track_noise_factor * azimuth sigma * range``, about 270 m here), so ``ratio`` 1 puts
neighbours one cross-range sigma apart.  Track errors come from the lab's
:class:`~topofusion_lab.evaluation.correlation_stream.RadarTrackSim` (systematic range /
azimuth / elevation bias plus an AR(1) polar track error); azimuth biases are drawn with
magnitudes uniform in 0.2-2 deg and random signs, range biases within +-500 m.  Radar A
holds a track on a target with probability ``pd_a``, radar B (the one with the lower
detection probability) with ``pd_b``, so some tracks have no counterpart.  ``truth_id`` is
read for scoring only.

Scores, per scan, of the pair book's *confirmed* pairs:

* correct rate = correct confirmed pairs / common targets (confirmed tracks in both radars);
* false rate = false confirmed pairs / confirmed pairs.

Printed: means over the seeds of the late average (last half of the scans) and of the final
scan.  ``--oracle`` adds the truth-registered bounds (:func:`oracle`); ``--diagnose`` prints
the one-snapshot diagnosis instead (:func:`diagnose`).  The results and their reading are in
``docs/evaluation/gmm_dense.md``.  Run::

    .venv/bin/python bench/eval_gmm_dense.py [--seeds 5] [--ratios 1 1.5 2 3] [--targets 30]
        [--methods ...] [--oracle] [--diagnose]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from service.correlation import CorrelationParams, PairCorrelator
from service.correlation.assignment import assign_unambiguous
from service.correlation.base import DecisionContext
from service.correlation.evidence import EvidenceBook
from service.correlation.external import GmmCorrelator
from service.correlation.gmm import GmmParams, gmm_associate
from service.correlation.prediction import predict_tracks
from service.geo import Site
from service.tracking.base import TrackTable
from topofusion_lab.evaluation.correlation_scenario import make_sites
from topofusion_lab.evaluation.correlation_stream import RadarBias, RadarTrackSim, StreamScenario


@dataclass(frozen=True)
class DenseScene:
    """Numbers of one dense-formation stream."""

    targets: int = 30
    ratio: float = 1.5
    """Lattice spacing / cross-range track error."""
    jitter: float = 0.25
    """Each aircraft is displaced uniformly within +-``jitter`` spacings per axis."""
    centre_enu_m: tuple[float, float] = (100_000.0, 80_000.0)
    """Formation centre in radar A's ENU frame (B is 200 km east: ~128 km from both)."""
    altitude_m: float = 9_000.0
    speed_mps: float = 220.0
    scans: int = 40
    pd_a: float = 0.95
    pd_b: float = 0.75
    azimuth_bias_deg: tuple[float, float] = (0.2, 2.0)
    range_bias_m: float = 500.0
    elevation_bias_deg: float = 0.1
    stream: StreamScenario = field(default_factory=StreamScenario)


def cross_range_sigma_m(scene: DenseScene, sites: tuple[Site, Site]) -> float:
    """The larger of the two radars' cross-range track sigmas at the formation centre."""
    a = sites[0]
    centre = a.enu_to_ecef(np.array([*scene.centre_enu_m, scene.altitude_m]))
    out = 0.0
    for s in sites:
        r, _, _ = s.ecef_to_polar(centre[None])
        out = max(out, float(r[0]) * np.radians(s.azimuth_sigma_deg) * scene.stream.track_noise_factor)
    return out


def _bias(rng: np.random.Generator, scene: DenseScene) -> RadarBias:
    sign = rng.choice([-1.0, 1.0], 3)
    return RadarBias(
        float(sign[0] * rng.uniform(0.0, scene.range_bias_m)),
        float(sign[1] * rng.uniform(*scene.azimuth_bias_deg)),
        float(sign[2] * rng.uniform(0.0, scene.elevation_bias_deg)),
    )


def make_formation(
    rng: np.random.Generator, scene: DenseScene, spacing_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """ENU (radar A frame) positions and velocities of the formation's aircraft."""
    n = scene.targets
    cols = int(np.ceil(np.sqrt(n)))
    k = np.arange(n)
    grid = np.column_stack([k % cols, k // cols]).astype(float)
    grid -= grid.mean(axis=0)
    grid += rng.uniform(-scene.jitter, scene.jitter, grid.shape)
    hdg = rng.uniform(0.0, 2.0 * np.pi)
    c, s = np.cos(hdg), np.sin(hdg)
    # Rows across the heading, columns along it.
    xy = spacing_m * (grid @ np.array([[c, -s], [s, c]]).T) + np.array(scene.centre_enu_m)
    pos = np.column_stack([xy, np.full(n, scene.altitude_m) + rng.uniform(-30.0, 30.0, n)])
    vel = np.tile([scene.speed_mps * np.sin(hdg), scene.speed_mps * np.cos(hdg), 0.0], (n, 1))
    return pos, vel


Tables = list[tuple[TrackTable, TrackTable, float]]


def make_tables(seed: int, scene: DenseScene) -> tuple[Tables, Site, Site]:
    """The per-scan track tables of both radars (same for every method)."""
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    spacing = scene.ratio * cross_range_sigma_m(scene, (a, b))
    pos0, vel = make_formation(rng, scene, spacing)
    n = pos0.shape[0]
    sc = scene.stream
    ra = RadarTrackSim(rng, a, _bias(rng, scene), n, sc)
    rb = RadarTrackSim(rng, b, _bias(rng, scene), n, sc)
    held_a = {f"T{i}" for i in np.flatnonzero(rng.random(n) < scene.pd_a)}
    held_b = {f"T{i}" for i in np.flatnonzero(rng.random(n) < scene.pd_b)}
    tables = []
    for k in range(scene.scans):
        t0 = k * sc.scan_period_s
        ta, tb = ra.table(a, pos0, vel, t0), rb.table(a, pos0, vel, t0)
        ta = ta.take(np.flatnonzero([t in held_a for t in ta.truth_id]))
        tb = tb.take(np.flatnonzero([t in held_b for t in tb.truth_id]))
        tables.append((ta, tb, t0 + sc.scan_period_s))
    return tables, a, b


def score(corr: PairCorrelator, ta: TrackTable, tb: TrackTable) -> tuple[int, int, int]:
    """(common targets, correct confirmed pairs, false confirmed pairs) after an update."""
    truth_a = dict(zip(ta.track_id, ta.truth_id, strict=True))
    truth_b = dict(zip(tb.track_id, tb.truth_id, strict=True))
    conf_a = {truth_a[i] for i, c in zip(ta.track_id, ta.confirmed, strict=True) if c}
    conf_b = {truth_b[i] for i, c in zip(tb.track_id, tb.confirmed, strict=True) if c}
    ok = bad = 0
    for p in corr.pairs():
        if p.status == "confirmed":
            if truth_a.get(p.track_a) == truth_b.get(p.track_b):
                ok += 1
            else:
                bad += 1
    return len(conf_a & conf_b), ok, bad


#: The variant for which the bench turns on the correlator's history evidence
#: (:mod:`service.correlation.evidence`), which the correlator keeps for ``svd-topology``
#: only: gmm's decisions with the evidence's own looks accumulated over the updates.
HISTORY = "gmm + history evidence (enabled by the bench)"


def variants(scene: DenseScene | None = None) -> dict[str, tuple[str, CorrelationParams]]:
    """Label -> (method, params) compared by the bench."""
    base = CorrelationParams()
    sc = (scene or DenseScene()).stream
    # As published: Eq. (27)'s pairs, every one accepted; sigma from EM alone; beta = 2 only.
    paper = replace(GmmParams(), sigma_floor_factor=0.0, report_rivals=False, min_kernel_width_m=0.0)
    # The history evidence with the simulated tracks' error correlation time.
    history = replace(
        base,
        evidence=replace(
            base.evidence, error_correlation_s=-sc.scan_period_s / float(np.log(sc.noise_correlation))
        ),
    )
    return {
        "gmm": ("gmm", base),
        "gmm, as published (Eq. (27) pairs, EM sigma)": ("gmm", replace(base, gmm=paper)),
        HISTORY: ("gmm", history),
        "svd-topology": ("svd-topology", base),
    }


def make_correlator(label: str, scene: DenseScene, a: Site, b: Site) -> PairCorrelator:
    method, params = variants(scene)[label]
    corr = PairCorrelator(method, a, b, params)
    if label == HISTORY:
        corr.evidence = EvidenceBook(params.evidence)
    return corr


def run(seed: int, scene: DenseScene, labels: list[str]) -> dict[str, np.ndarray]:
    """Per label: rows (correct late, false late, correct final, false final, ms/update)."""
    tables, a, b = make_tables(seed, scene)
    late = max(1, scene.scans // 2)
    out = {}
    for label in labels:
        corr = make_correlator(label, scene, a, b)
        hist, ms = [], []
        for ta, tb, t in tables:
            corr.update(ta, tb, t)
            ms.append(corr.last_update_ms)
            hist.append(score(corr, ta, tb))
        h = np.array(hist[-late:], dtype=float)
        correct = h[:, 1] / np.maximum(h[:, 0], 1.0)
        false = h[:, 2] / np.maximum(h[:, 1] + h[:, 2], 1.0)
        out[label] = np.array([correct.mean(), false.mean(), correct[-1], false[-1], np.mean(ms)])
    return out


ORACLE = (
    "oracle: one scan, best assignment",
    "oracle: one scan, ambiguity margin",
    "oracle: accumulated, best assignment",
    "oracle: accumulated, ambiguity margin",
)


def oracle(seed: int, scene: DenseScene, margin: float | None = None) -> dict[str, np.ndarray]:
    """Bounds from the truth (evaluation only), in the rows of :func:`run`.

    Every scan, B's confirmed tracks are mapped into A's plane by the affine transform fitted to
    the true pairs (the registration a perfect method would find; slightly optimistic, as it is
    fitted to the very errors it is then judged on), and every A-B pair gets the chi-square
    ``|x_A - T x_B|^2 / s^2`` (``s^2``: the scan's mean squared true-pair residual per axis).
    *One scan*: on that scan's chi-squares; *accumulated*: on each pair's mean chi-square over
    the scans so far times its effective number of looks ``1 + (m - 1)(1 - rho)/(1 + rho)``
    (``m`` scans, AR(1) correlation ``rho`` of the simulated track errors), the ideal sequential
    test.  *Best assignment*: the one-to-one assignment of least total chi-square, every track
    paired; *ambiguity margin*: :func:`~service.correlation.assignment.assign_unambiguous` with
    the correlator's margin, a pair kept only when no rival is within it.
    """
    margin = CorrelationParams().ambiguity_margin if margin is None else margin
    tables, a, _ = make_tables(seed, scene)
    n = scene.targets
    rho = scene.stream.noise_correlation
    total = np.zeros((n, n))
    looks = np.zeros((n, n))
    hist: dict[str, list[tuple[int, int, int]]] = {k: [] for k in ORACLE}
    for ta, tb, _ in tables:
        ta, tb = ta.take(ta.confirmed), tb.take(tb.confirmed)
        ida = np.array([int(t[1:]) for t in ta.truth_id], dtype=np.intp)
        idb = np.array([int(t[1:]) for t in tb.truth_id], dtype=np.intp)
        common, ra, rb = np.intersect1d(ida, idb, return_indices=True)
        if common.size < 4:
            continue
        pa = a.ecef_to_enu(ta.position_ecef_m)[:, :2]
        pb = np.column_stack([a.ecef_to_enu(tb.position_ecef_m)[:, :2], np.ones(len(idb))])
        fit, *_ = np.linalg.lstsq(pb[rb], pa[ra], rcond=None)
        d = pa[:, None, :] - (pb @ fit)[None, :, :]
        chi2 = np.einsum("ijk,ijk->ij", d, d)
        chi2 /= np.mean(chi2[ra, rb]) / 2.0
        total[np.ix_(ida, idb)] += chi2
        looks[np.ix_(ida, idb)] += 1.0
        m = looks[np.ix_(ida, idb)]
        acc = total[np.ix_(ida, idb)] / m * (1.0 + (m - 1.0) * (1.0 - rho) / (1.0 + rho))
        for k, label in enumerate(ORACLE):
            cost, forced = (chi2, acc)[k // 2], k % 2 == 0
            if forced:
                r, c = linear_sum_assignment(cost)
            else:
                ii, jj = np.indices(cost.shape)
                ii, jj = ii.ravel(), jj.ravel()
                keep, _ = assign_unambiguous(ii, jj, cost.ravel(), np.ones(ii.size, bool), margin)
                r, c = ii[keep], jj[keep]
            ok = int(np.sum(ida[r] == idb[c]))
            hist[label].append((common.size, ok, r.size - ok))
    late = max(1, scene.scans // 2)
    out = {}
    for label, rows in hist.items():
        h = np.array(rows[-late:], dtype=float)
        correct = h[:, 1] / np.maximum(h[:, 0], 1.0)
        false = h[:, 2] / np.maximum(h[:, 1] + h[:, 2], 1.0)
        out[label] = np.array([correct.mean(), false.mean(), correct[-1], false[-1], np.nan])
    return out


DIAGNOSIS = (
    "EM sigma, beta=2 (m)",
    "EM sigma, 20 km kernel (m)",
    "sigma floor (m)",
    "true-pair residual per axis (m)",
    "registration error, beta=2 (m)",
    "registration error, 20 km kernel (m)",
    "as published: correct share of P>=0.9",
    "single update, beta=2: false / decided",
    "single update: false / decided",
)


def diagnose(seed: int, scene: DenseScene) -> np.ndarray:
    """One snapshot at a time, the last half of the scans (evaluation only): the numbers of
    ``docs/evaluation/gmm_dense.md``'s diagnosis, in the order of :data:`DIAGNOSIS`.

    EM's sigma without the floor (``beta = 2`` alone, and with ``min_kernel_width_m``) against
    the floor and against the true pairs' residual after the fit; the fit's registration error
    (RMS over B's tracks of the fitted centroid minus B mapped by the affine transform fitted
    to the true pairs); the share of correct pairs among the paper's decisions with posterior
    >= 0.9; and the false share of the pairs the adapter's candidates leave to a one-to-one
    assignment with the correlator's ambiguity margin (``beta = 2`` and default).  One row per
    scan: six sizes, then (correct, decided), (false, decided), (false, decided).
    """
    tables, a, b = make_tables(seed, scene)
    margin = CorrelationParams().ambiguity_margin
    prm = GmmParams()
    em_b2 = replace(prm, sigma_floor_factor=0.0, min_kernel_width_m=0.0)
    em = replace(prm, sigma_floor_factor=0.0)
    paper = replace(em_b2, report_rivals=False)
    rows = []
    for ta, tb, t in tables[-max(1, scene.scans // 2) :]:
        sa, sb = predict_tracks(ta, a, t), predict_tracks(tb, b, t)
        truth_a = dict(zip(ta.track_id, ta.truth_id, strict=True))
        truth_b = dict(zip(tb.track_id, tb.truth_id, strict=True))
        ida = np.array([truth_a[i] for i in sa.track_id])
        idb = np.array([truth_b[i] for i in sb.track_id])
        _, ra, rb = np.intersect1d(ida, idb, return_indices=True)
        pos_a = sa.enu[:, :2]
        pos_b = a.ecef_to_enu(sb.position)[:, :2]
        rot = a.rotation
        cov_a, cov_b = sa.enu_cov()[:, :2, :2], (rot.T @ sb.pos_cov @ rot)[:, :2, :2]
        lin = np.column_stack([pos_b, np.ones(len(pos_b))])
        fit, *_ = np.linalg.lstsq(lin[rb], pos_a[ra], rcond=None)
        registered_b = lin @ fit
        row = []
        fits = {}
        for name, p in (("b2", em_b2), ("em", em), ("def", prm)):
            fits[name] = gmm_associate(pos_a, pos_b, p, cov_a, cov_b)
        row += [fits["b2"].sigma_m, fits["em"].sigma_m, fits["def"].sigma_floor_m]
        moved = pos_b + fits["def"].displacement
        row.append(float(np.sqrt(np.mean((pos_a[ra] - moved[rb]) ** 2))))
        for name in ("b2", "def"):
            err = pos_b + fits[name].displacement - registered_b
            row.append(float(np.sqrt(np.mean(np.sum(err**2, axis=1)))))
        pub = gmm_associate(pos_a, pos_b, paper)
        sure = pub.posterior >= 0.9
        good = ida[pub.index_a[sure]] == idb[pub.index_b[sure]]
        row += [float(good.sum()), float(sure.sum())]
        for p in (replace(prm, min_kernel_width_m=0.0), prm):
            dec = GmmCorrelator(p).decide(sa, sb, DecisionContext(time_s=t))
            keep, _ = assign_unambiguous(dec.index_a, dec.index_b, dec.cost, dec.accepted, margin)
            good = ida[dec.index_a[keep]] == idb[dec.index_b[keep]]
            row += [float((~good).sum()), float(keep.sum())]
        rows.append(row)
    return np.array(rows, dtype=float)


def diagnosis_table(seeds: range, scene: DenseScene) -> list[str]:
    """The column of :data:`DIAGNOSIS` for one scene: means of the sizes, pooled shares (with
    the number of pairs they are shares of)."""
    r = np.concatenate([diagnose(s, scene) for s in seeds])
    out = [f"{v:.0f}" for v in r[:, :6].mean(axis=0)]
    for k in (6, 8, 10):
        num, den = r[:, k].sum(), r[:, k + 1].sum()
        out.append(f"{num / den:.2f} of {den:.0f}" if den else "none")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--ratios", type=float, nargs="+", default=[1.0, 1.5, 2.0, 3.0])
    ap.add_argument("--targets", type=int, default=30)
    ap.add_argument("--scans", type=int, default=40)
    ap.add_argument("--methods", nargs="+", default=list(variants()), choices=list(variants()))
    ap.add_argument("--oracle", action="store_true", help="also the truth-registered bounds (oracle)")
    ap.add_argument("--diagnose", action="store_true", help="one-snapshot diagnosis instead of the stream")
    args = ap.parse_args()
    if args.diagnose:
        print("| quantity | " + " | ".join(f"ratio {r:g}" for r in args.ratios) + " |")
        print("|---|" + "---:|" * len(args.ratios))
        seeds = range(args.first_seed, args.first_seed + args.seeds)
        cols = [
            diagnosis_table(seeds, DenseScene(targets=args.targets, ratio=r, scans=args.scans))
            for r in args.ratios
        ]
        for k, name in enumerate(DIAGNOSIS):
            print(f"| {name} | " + " | ".join(c[k] for c in cols) + " |")
        return
    t0 = time.perf_counter()
    a, b = make_sites()
    print(
        f"dense formation: {args.targets} aircraft, {args.scans} scans, seeds "
        f"{args.first_seed}..{args.first_seed + args.seeds - 1}; cross-range track sigma "
        f"{cross_range_sigma_m(DenseScene(), (a, b)):.0f} m; rates in % (late = last half of the scans)"
    )
    head = ("method", "ratio", "correct late", "false late", "correct final", "false final", "ms/update")
    print(f"| {head[0]} | {' | '.join(head[1:])} |")
    print("|---|" + "---:|" * (len(head) - 1))
    for ratio in args.ratios:
        scene = DenseScene(targets=args.targets, ratio=ratio, scans=args.scans)
        seeds = range(args.first_seed, args.first_seed + args.seeds)
        rows = [run(s, scene, args.methods) | (oracle(s, scene) if args.oracle else {}) for s in seeds]
        for label in rows[0]:
            m = np.mean([r[label] for r in rows], axis=0)
            print(
                f"| {label} | {ratio:g} | {100 * m[0]:.1f} | {100 * m[1]:.1f} | {100 * m[2]:.1f} | "
                f"{100 * m[3]:.1f} | {'' if np.isnan(m[4]) else f'{m[4]:.1f}'} |",
                flush=True,
            )
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
