"""Multi-scan streaming evaluation of the correlators (evaluation only).

A two-radar picture over time, fed through :class:`service.correlation.PairCorrelator`
exactly as the engine does: every scan each radar reports its confirmed tracks as a
:class:`~service.tracking.base.TrackTable` (each row with its own time inside the scan), and
the correlator updates at the end of the scan.  Traffic: sparse en-route aircraft
(``sparse_targets`` in a ``box_m`` square between the radars, typically 20-40 km apart)
plus a dense cluster (``cluster_targets`` within ``cluster_radius_m``).

Track errors model a tracker's output rather than raw plots: the radar's systematic errors
(range, azimuth, elevation bias) plus a random polar error of ``track_noise_factor`` times
the measurement sigmas, correlated from scan to scan (AR(1), ``noise_correlation``);
velocities are the biased picture's velocities (an azimuth bias rotates them) plus white
noise ``velocity_sigma_mps``.  The reported covariance is the matching polar covariance
mapped to ECEF.  ``truth_id`` is carried for scoring only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from service.correlation import CorrelationParams, PairCorrelator, estimate_biases
from service.correlation.registration import solve_biases
from service.correlation.svd_topology import SvdTopologyParams
from service.correlation.topology import TopologyParams
from service.geo import Site, polar_to_enu
from service.tracking.base import TrackTable
from topofusion_lab.evaluation.correlation_scenario import make_sites


@dataclass(frozen=True)
class RadarBias:
    range_m: float
    azimuth_deg: float
    elevation_deg: float


@dataclass(frozen=True)
class StreamScenario:
    """Numbers of the streaming scenario."""

    sparse_targets: int = 60
    box_m: float = 300_000.0
    cluster_targets: int = 20
    cluster_radius_m: float = 12_000.0
    scans: int = 60
    scan_period_s: float = 4.0
    max_range_m: float = 250_000.0
    bias_a: RadarBias = RadarBias(500.0, 0.5, 0.1)
    bias_b: RadarBias = RadarBias(-300.0, -0.4, -0.1)
    track_noise_factor: float = 0.6
    noise_correlation: float = 0.8
    velocity_sigma_mps: float = 6.0
    #: Scans a target must be in coverage before its track is reported confirmed.
    confirm_scans: int = 3
    extra: dict[str, float] = field(default_factory=dict)


def make_targets(rng: np.random.Generator, sc: StreamScenario, a: Site) -> tuple[np.ndarray, np.ndarray]:
    """Initial ENU (radar A frame) positions and velocities of all targets."""
    centre = np.array([100_000.0, 0.0])
    n1, n2 = sc.sparse_targets, sc.cluster_targets
    xy = centre + rng.uniform(-sc.box_m / 2, sc.box_m / 2, (n1, 2))
    cc = centre + np.array([20_000.0, 70_000.0])
    rad = sc.cluster_radius_m * np.sqrt(rng.uniform(0, 1, n2))
    ang = rng.uniform(0, 2 * np.pi, n2)
    xy2 = cc + np.column_stack([rad * np.sin(ang), rad * np.cos(ang)])
    alt = np.r_[rng.uniform(7_000, 12_000, n1), rng.uniform(2_000, 8_000, n2)]
    speed = np.r_[rng.uniform(180, 250, n1), rng.uniform(100, 200, n2)]
    hdg = rng.uniform(0, 2 * np.pi, n1 + n2)
    pos = np.column_stack([np.r_[xy[:, 0], xy2[:, 0]], np.r_[xy[:, 1], xy2[:, 1]], alt])
    vel = np.column_stack([speed * np.sin(hdg), speed * np.cos(hdg), np.zeros(n1 + n2)])
    return pos, vel


class RadarTrackSim:
    """One radar's simulated tracker output."""

    def __init__(
        self, rng: np.random.Generator, site: Site, bias: RadarBias, n: int, sc: StreamScenario
    ) -> None:
        self.rng = rng
        self.site = site
        self.bias = bias
        self.sc = sc
        self.eta = rng.normal(size=(n, 3))
        self.seen = np.zeros(n, dtype=int)
        perm = rng.permutation(n)
        self.ids = np.array([f"{site.site_id}-{k}" for k in perm])

    def table(self, a_site: Site, pos0: np.ndarray, vel: np.ndarray, scan_start: float) -> TrackTable:
        sc, site = self.sc, self.site
        rho = sc.noise_correlation
        self.eta = rho * self.eta + np.sqrt(1 - rho**2) * self.rng.normal(size=self.eta.shape)
        # Time of each target inside the scan from its azimuth at the scan start.
        ecef0 = a_site.enu_to_ecef(pos0 + vel * scan_start)
        _, az0, _ = site.ecef_to_polar(ecef0)
        t = scan_start + az0 / 360.0 * sc.scan_period_s
        true_ecef = a_site.enu_to_ecef(pos0 + vel * t[:, None])
        r, az, el = site.ecef_to_polar(true_ecef)
        inside = (np.hypot(*site.ecef_to_enu(true_ecef)[:, :2].T) <= sc.max_range_m) & (r >= 5_000.0)
        self.seen = np.where(inside, self.seen + 1, 0)
        k = sc.track_noise_factor
        rm = r + self.bias.range_m + k * site.range_sigma_m * self.eta[:, 0]
        azm = az + self.bias.azimuth_deg + k * site.azimuth_sigma_deg * self.eta[:, 1]
        elm = el + self.bias.elevation_deg + k * site.elevation_sigma_deg * self.eta[:, 2]
        pos = site.enu_to_ecef(polar_to_enu(rm, azm, elm))
        cov_enu = site.measurement_covariance_enu(rm, azm, elm) * k**2
        # Velocity as the biased radar sees it: true ENU velocity rotated by the azimuth bias.
        v_enu = (a_site.rotation @ vel.T).T @ site.rotation
        d = np.radians(self.bias.azimuth_deg)
        c, s = np.cos(d), np.sin(d)
        v_b = np.column_stack(
            [v_enu[:, 0] * c + v_enu[:, 1] * s, -v_enu[:, 0] * s + v_enu[:, 1] * c, v_enu[:, 2]]
        )
        v_b = v_b + self.rng.normal(0, sc.velocity_sigma_mps, v_b.shape) * np.array([1.0, 1.0, 0.5])
        vel_ecef = v_b @ site.rotation.T
        n = len(r)
        cov = np.zeros((n, 6, 6))
        cov[:, :3, :3] = site.rotation @ cov_enu @ site.rotation.T
        cov[:, 3:, 3:] = np.diag(np.array([1.0, 1.0, 0.25]) * sc.velocity_sigma_mps**2)
        keep = np.flatnonzero(inside)
        return TrackTable(
            track_id=self.ids[keep],
            confirmed=self.seen[keep] >= sc.confirm_scans,
            time_s=t[keep],
            position_ecef_m=pos[keep],
            velocity_ecef_mps=vel_ecef[keep],
            covariance=cov[keep],
            plots=self.seen[keep].astype(np.int64),
            truth_id=np.array([f"T{i}" for i in keep], dtype=object),
        )


@dataclass
class StreamResult:
    """Per method: final and late-average correct/false confirmed pairs, timings, biases."""

    rows: dict[str, dict[str, float]]
    biases: dict[str, dict[str, float]]


def stream_variants() -> dict[str, tuple[str, CorrelationParams]]:
    """The methods compared in the stream (label -> method, params)."""
    paper = replace(
        CorrelationParams(),
        svd=replace(
            SvdTopologyParams(),
            topology=TopologyParams(min_neighbours=0, max_radius_m=10_000.0),
            rotation_model="full",
        ),
        use_registration=False,
    )
    no_reg = replace(CorrelationParams(), use_registration=False)
    return {
        "svd-topology": ("svd-topology", CorrelationParams()),
        "svd-topology, no registration": ("svd-topology", no_reg),
        "svd-topology, paper (3-D, 10 km)": ("svd-topology", paper),
        "basic-topology": ("basic-topology", CorrelationParams()),
        "nearest": ("nearest", CorrelationParams()),
        "gmm": ("gmm", CorrelationParams()),
        "cfar (B as reference)": ("cfar", CorrelationParams()),
    }


def run_stream(
    seed: int, sc: StreamScenario | None = None, progress: Callable[[str], None] | None = None
) -> StreamResult:
    """One seeded stream, all methods on the same track tables."""
    sc = sc or StreamScenario()
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    pos0, vel = make_targets(rng, sc, a)
    n = pos0.shape[0]
    ra = RadarTrackSim(rng, a, sc.bias_a, n, sc)
    rb = RadarTrackSim(rng, b, sc.bias_b, n, sc)
    tables = []
    for k in range(sc.scans):
        t0 = k * sc.scan_period_s
        tables.append((ra.table(a, pos0, vel, t0), rb.table(a, pos0, vel, t0), t0 + sc.scan_period_s))
    rows: dict[str, dict[str, float]] = {}
    biases: dict[str, dict[str, float]] = {}
    late = max(1, sc.scans // 3)
    for label, (method, params) in stream_variants().items():
        corr = PairCorrelator(method, a, b, params)
        hist = []
        ms = []
        for ta, tb, t in tables:
            corr.update(ta, tb, t)
            ms.append(corr.last_update_ms)
            truth_a = dict(zip(ta.track_id, ta.truth_id, strict=True))
            truth_b = dict(zip(tb.track_id, tb.truth_id, strict=True))
            conf_a = {truth_a[i] for i, c in zip(ta.track_id, ta.confirmed, strict=True) if c}
            conf_b = {truth_b[i] for i, c in zip(tb.track_id, tb.confirmed, strict=True) if c}
            common = len(conf_a & conf_b)
            ok = bad = 0
            for p in corr.pairs():
                if p.status != "confirmed":
                    continue
                if truth_a.get(p.track_a) == truth_b.get(p.track_b):
                    ok += 1
                else:
                    bad += 1
            hist.append((common, ok, bad))
        h = np.array(hist[-late:], dtype=float)
        rows[label] = {
            "common": float(h[-1, 0]),
            "correct_final": h[-1, 1] / max(h[-1, 0], 1),
            "false_final": h[-1, 2] / max(h[-1, 0], 1),
            "correct_late": float(np.mean(h[:, 1] / np.maximum(h[:, 0], 1))),
            "false_late": float(np.mean(h[:, 2] / np.maximum(h[:, 0], 1))),
            "ms_mean": float(np.mean(ms)),
        }
        if label == "svd-topology":
            sol = solve_biases([corr.memory], tables[-1][2], corr.params.registration)
            std = {} if sol is None else dict(zip(sol.radar_ids, sol.std(), strict=True))
            for e in estimate_biases([corr], tables[-1][2]):
                truth = sc.bias_a if e.radar_id == "A" else sc.bias_b
                sd = std.get(e.radar_id, np.full(3, np.nan))
                biases[e.radar_id] = {
                    "std_range_m": float(sd[0]),
                    "std_azimuth_deg": float(np.degrees(sd[1])),
                    "std_elevation_deg": float(np.degrees(sd[2])),
                    "range_m": e.range_bias_m,
                    "azimuth_deg": e.azimuth_bias_deg,
                    "elevation_deg": e.elevation_bias_deg,
                    "true_range_m": truth.range_m,
                    "true_azimuth_deg": truth.azimuth_deg,
                    "true_elevation_deg": truth.elevation_deg,
                    "pairs_used": float(e.pairs_used),
                }
        if progress:
            progress(f"  stream seed {seed}: {label} done")
    return StreamResult(rows, biases)
