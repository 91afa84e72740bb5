"""The Hough paper's Table 1 set-up: a bistatic radar network in the plane (Section 3).

One transmitter at the origin, receivers at (-50 km, 0) and (50 km, 0); the pair with receiver
1 measures range sum / angle with 150 m / 5 mrad, the pair with receiver 2 with 200 m / 8 mrad.
Five targets fly straight for 10 s in x in [-4, 4] km, y in [30, 36] km: targets 1 and 2 on
one line, parallel to target 3 (a small-distance parallel pair), targets 4 and 5 crossing.
Each bistatic pair samples each target at random times (exponential intervals: "the sampling
interval is random"), time stamps rounded to 0.1 ms.  Clutter is uniform over the area and the
10 s, as many plots as true plots on average.

Bistatic measurement (Eq. 3): ``rho = |x - T| + |x - R|``, ``theta = atan2(y - y_R, x - x_R)``
(the paper's ``arctan`` with the quadrant kept).  A plot is located as the paper does with its
location equation: on the ray from ``R`` at angle ``theta``, the point whose range sum is
``rho``: ``x = R + s u``, ``s = (rho^2 - |R - T|^2) / (2 (rho + u . (R - T)))``.  Its location
error comes from the first-order Jacobian of that map: ``C = J diag(s_rho^2, s_theta^2) J^T``,
``delta = sqrt(trace C)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.geo import FloatArray
from service.tracking.groups import Groups


@dataclass(frozen=True)
class BistaticScenario:
    """Parameters of the Table 1 set-up (paper Section 3; choices the paper leaves open noted)."""

    transmitter_m: tuple[float, float] = (0.0, 0.0)
    receivers_m: tuple[tuple[float, float], ...] = ((-50_000.0, 0.0), (50_000.0, 0.0))
    range_sigma_m: tuple[float, ...] = (150.0, 200.0)
    angle_sigma_rad: tuple[float, ...] = (5e-3, 8e-3)
    duration_s: float = 10.0
    mean_interval_s: float = 1.0
    """Mean random sampling interval per target and bistatic pair (not given in the paper:
    "the data rate is low, the sampling interval random"; 1 s gives about 10 plots per target
    and receiver in the 10 s, 20 per target)."""
    clutter_ratio: float = 1.0
    """Mean clutter count over true plot count ("about as many")."""
    area_x_m: tuple[float, float] = (-4_000.0, 4_000.0)
    area_y_m: tuple[float, float] = (30_000.0, 36_000.0)
    time_resolution_s: float = 1e-4
    # Target start positions (m) and velocities (m/s); the paper gives only the geometry
    # (Fig. 2): 1 and 2 on the line y = 31 km, 3 parallel at 1.2 km, 4 and 5 crossing.  The
    # targets are stealth aircraft (Section 0; "near space" is where the radars are), and
    # two of them must fly 10 s one behind the other on one line inside 8 km: about 250-400
    # m/s (250 m/s for 1-3, 360 m/s for 4-5).
    starts_m: tuple[tuple[float, float], ...] = field(
        default=(
            (-3_600.0, 31_000.0),
            (200.0, 31_000.0),
            (-3_000.0, 32_200.0),
            (-2_500.0, 33_000.0),
            (1_500.0, 33_000.0),
        )
    )
    velocities_mps: tuple[tuple[float, float], ...] = field(
        default=((250.0, 0.0), (250.0, 0.0), (250.0, 0.0), (300.0, 200.0), (-300.0, 200.0))
    )


@dataclass(frozen=True)
class BistaticPlots:
    """One realisation: plot positions, covariances, times, labels (target index or -1)."""

    xy: FloatArray  # (n, 2)
    cov: FloatArray  # (n, 2, 2)
    time_s: FloatArray
    label: np.ndarray  # (n,) int; -1 clutter
    receiver: np.ndarray  # (n,) int


def bistatic_measure(xy: FloatArray, tx: FloatArray, rx: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Eq. (3): range sum and receiver angle of points ``(n, 2)``."""
    rho = np.linalg.norm(xy - tx, axis=1) + np.linalg.norm(xy - rx, axis=1)
    theta = np.arctan2(xy[:, 1] - rx[1], xy[:, 0] - rx[0])
    return rho, theta


def bistatic_locate(
    rho: FloatArray, theta: FloatArray, tx: FloatArray, rx: FloatArray, s_rho: float, s_theta: float
) -> tuple[FloatArray, FloatArray]:
    """Location equation and first-order location covariance of bistatic measurements."""
    u = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    up = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
    b = rx - tx
    num = rho**2 - float(b @ b)
    den = 2.0 * (rho + u @ b)
    s = num / den
    xy = rx + s[:, None] * u
    ds_drho = (2.0 * rho * den - 2.0 * num) / den**2
    ds_dth = -num * 2.0 * (up @ b) / den**2
    jac = np.empty((rho.shape[0], 2, 2))
    jac[:, :, 0] = u * ds_drho[:, None]
    jac[:, :, 1] = up * s[:, None] + u * ds_dth[:, None]
    cov = (jac * np.array([s_rho**2, s_theta**2])) @ np.swapaxes(jac, 1, 2)
    return xy, cov


def simulate_bistatic(scn: BistaticScenario, rng: np.random.Generator) -> BistaticPlots:
    """One Monte Carlo realisation of the Table 1 set-up."""
    tx = np.asarray(scn.transmitter_m, dtype=float)
    starts = np.asarray(scn.starts_m, dtype=float)
    vel = np.asarray(scn.velocities_mps, dtype=float)
    parts: list[tuple[FloatArray, FloatArray, FloatArray, np.ndarray, np.ndarray]] = []
    n_true = 0
    for r, rx_t in enumerate(scn.receivers_m):  # loop over the two receivers
        rx = np.asarray(rx_t, dtype=float)
        s_rho, s_th = scn.range_sigma_m[r], scn.angle_sigma_rad[r]
        # Random sampling times per target: exponential intervals from a random phase.
        n_max = int(4 * scn.duration_s / scn.mean_interval_s) + 8
        gaps = rng.exponential(scn.mean_interval_s, size=(starts.shape[0], n_max))
        times = np.cumsum(gaps, axis=1) - rng.uniform(0, scn.mean_interval_s, size=(starts.shape[0], 1))
        ok = (times >= 0) & (times <= scn.duration_s)
        tgt, _ = np.nonzero(ok)
        t = np.round(times[ok] / scn.time_resolution_s) * scn.time_resolution_s
        pos = starts[tgt] + vel[tgt] * t[:, None]
        rho, th = bistatic_measure(pos, tx, rx)
        rho = rho + rng.normal(0, s_rho, rho.shape)
        th = th + rng.normal(0, s_th, th.shape)
        xy, cov = bistatic_locate(rho, th, tx, rx, s_rho, s_th)
        parts.append((xy, cov, t, tgt.astype(np.intp), np.full(t.shape[0], r)))
        n_true += t.shape[0]
    # Clutter: uniform over area and time, split at random between the receivers.
    k = rng.poisson(scn.clutter_ratio * n_true)
    cxy = np.stack([rng.uniform(*scn.area_x_m, k), rng.uniform(*scn.area_y_m, k)], axis=1)
    ct = np.round(rng.uniform(0, scn.duration_s, k) / scn.time_resolution_s) * scn.time_resolution_s
    crx = rng.integers(0, len(scn.receivers_m), k)
    ccov = np.empty((k, 2, 2))
    for r, rx_t in enumerate(scn.receivers_m):
        m = crx == r
        rx = np.asarray(rx_t, dtype=float)
        rho, th = bistatic_measure(cxy[m], tx, rx)
        _, ccov[m] = bistatic_locate(rho, th, tx, rx, scn.range_sigma_m[r], scn.angle_sigma_rad[r])
    parts.append((cxy, ccov, ct, np.full(k, -1, dtype=np.intp), crx))
    return BistaticPlots(
        np.concatenate([p[0] for p in parts]),
        np.concatenate([p[1] for p in parts]),
        np.concatenate([p[2] for p in parts]),
        np.concatenate([p[3] for p in parts]),
        np.concatenate([p[4] for p in parts]),
    )


@dataclass(frozen=True)
class InitiationScore:
    """Per realisation: targets initiated, tracks output, false tracks."""

    initiated: int
    targets: int
    tracks: int
    false: int


def score_groups(groups: Groups, label: np.ndarray, n_targets: int) -> InitiationScore:
    """Initiation accuracy and false-track ratio of one realisation (Table 1's two columns).

    The paper does not define them; the usual definitions in its literature are used:

    * a track is *true* for target X when more than half of its plots come from X (a strict
      majority; clutter and other targets count against it) and it is the first such track for
      X in output order; every other track is *false* (clutter tracks, tracks mixing targets,
      duplicates of a target that already has a track);
    * initiation accuracy = targets with a true track / targets;
    * false-track ratio = false tracks / all tracks output.
    """
    best: set[int] = set()
    false = 0
    tracks = groups.to_lists()
    for g in tracks:  # evaluation: loop over output tracks
        vals, cnt = np.unique(label[g], return_counts=True)
        k = int(np.argmax(cnt))
        top = int(vals[k])
        if top < 0 or 2 * int(cnt[k]) <= g.shape[0] or top in best:
            false += 1
            continue
        best.add(top)
    return InitiationScore(len(best), n_targets, len(tracks), false)
