"""Snapshot generator for the SVD paper's Section 3 scenario (evaluation only).

Two radars 200 km apart (A at the origin of its ENU frame, B 200 km east); common targets
more than 50 km from both (and within ``max_range_m`` of both); each radar measures every
target in polar coordinates with its systematic error (bias) plus Gaussian random error,
and reports the position with the first-order covariance ``J diag(s^2) J^T``
(:meth:`service.geo.Site.measurement_covariance_enu`).  Everything is vectorised over
Monte Carlo trials (axis 0) and seeded.

``truth`` here is only used to score the methods.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.correlation.base import FloatArray
from service.geo import Site, ecef_to_geodetic, polar_to_enu

#: Latitude and longitude of radar A (arbitrary mid-latitude site).
SITE_LAT_DEG = 31.0
SITE_LON_DEG = 118.0


def make_sites(
    separation_m: float = 200_000.0, range_sigma_m: float = 200.0, angle_sigma_deg: float = 0.2
) -> tuple[Site, Site]:
    """Radars A and B, B ``separation_m`` east of A, both with the paper's random errors."""
    a = Site("A", SITE_LAT_DEG, SITE_LON_DEG, 50.0, range_sigma_m, angle_sigma_deg, angle_sigma_deg)
    lat, lon, _ = ecef_to_geodetic(a.enu_to_ecef(np.array([separation_m, 0.0, 0.0])))
    b = Site("B", float(lat), float(lon), 50.0, range_sigma_m, angle_sigma_deg, angle_sigma_deg)
    return a, b


@dataclass(frozen=True)
class Biases:
    """Systematic errors of one radar per trial: range (m), azimuth (deg), elevation (deg), each (T,)."""

    range_m: FloatArray
    azimuth_deg: FloatArray
    elevation_deg: FloatArray

    @staticmethod
    def random_sign(rng: np.random.Generator, trials: int, range_m: float, angle_deg: float) -> Biases:
        """Magnitudes fixed, signs random per trial and component (the paper gives magnitudes only)."""
        s = rng.choice([-1.0, 1.0], size=(3, trials))
        return Biases(s[0] * range_m, s[1] * angle_deg, s[2] * angle_deg)

    @staticmethod
    def fixed(trials: int, range_m: float, azimuth_deg: float, elevation_deg: float = 0.0) -> Biases:
        return Biases(np.full(trials, range_m), np.full(trials, azimuth_deg), np.full(trials, elevation_deg))


def sample_references(
    rng: np.random.Generator,
    a: Site,
    b: Site,
    trials: int,
    min_range_m: float = 50_000.0,
    max_range_m: float = 250_000.0,
    altitude_m: tuple[float, float] = (6_000.0, 12_000.0),
) -> FloatArray:
    """ECEF positions (T, 3) of reference targets ``>= min_range_m`` and ``<= max_range_m`` from both."""
    out = np.empty((0, 3))
    while out.shape[0] < trials:
        n = 4 * (trials - out.shape[0]) + 16
        e = rng.uniform(-100_000.0, 300_000.0, n)
        nn = rng.uniform(-250_000.0, 250_000.0, n)
        enu = np.column_stack([e, nn, rng.uniform(*altitude_m, n)])
        ecef = a.enu_to_ecef(enu)
        ra = np.hypot(*a.ecef_to_enu(ecef)[:, :2].T)
        rb = np.hypot(*b.ecef_to_enu(ecef)[:, :2].T)
        ok = (ra >= min_range_m) & (rb >= min_range_m) & (ra <= max_range_m) & (rb <= max_range_m)
        out = np.concatenate([out, ecef[ok]])
    return out[:trials]


def around(
    rng: np.random.Generator,
    a: Site,
    centre_ecef: FloatArray,
    count: int,
    radius_m: float = 10_000.0,
    altitude_m: tuple[float, float] = (6_000.0, 12_000.0),
    model: str = "disc",
) -> FloatArray:
    """``count`` neighbours per trial around each centre: (T, count, 3) ECEF.

    ``model="disc"``: uniform in a horizontal disc of ``radius_m`` at altitudes uniform in
    ``altitude_m`` (en-route traffic); ``"sphere"``: uniform in the ball of ``radius_m``
    around the reference -- the paper's own neighbourhood ("a sphere of radius 10 km around
    the reference", Section 1.2), where neighbours can lie nearly above or below it.
    """
    t = centre_ecef.shape[0]
    c = a.ecef_to_enu(centre_ecef)
    if model == "sphere":
        d = rng.normal(size=(t, count, 3))
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        d *= radius_m * rng.uniform(0.0, 1.0, (t, count, 1)) ** (1.0 / 3.0)
        return a.enu_to_ecef(c[:, None, :] + d)
    if model != "disc":
        raise ValueError(f"unknown neighbour model {model!r}")
    rad = radius_m * np.sqrt(rng.uniform(0.0, 1.0, (t, count)))
    ang = rng.uniform(0.0, 2 * np.pi, (t, count))
    up = rng.uniform(*altitude_m, (t, count))
    enu = np.stack([c[:, None, 0] + rad * np.sin(ang), c[:, None, 1] + rad * np.cos(ang), up], axis=-1)
    return a.enu_to_ecef(enu)


def measure(
    rng: np.random.Generator, site: Site, ecef: FloatArray, bias: Biases
) -> tuple[FloatArray, FloatArray]:
    """One radar's measured positions in its own ENU frame and their covariances.

    ``ecef``: (T, K, 3) true positions; the bias of trial ``t`` applies to all its targets.
    """
    r, az, el = site.ecef_to_polar(ecef)
    r = r + bias.range_m[:, None] + rng.normal(0.0, site.range_sigma_m, r.shape)
    az = az + bias.azimuth_deg[:, None] + rng.normal(0.0, site.azimuth_sigma_deg, az.shape)
    el = el + bias.elevation_deg[:, None] + rng.normal(0.0, site.elevation_sigma_deg, el.shape)
    return polar_to_enu(r, az, el), site.measurement_covariance_enu(r, az, el)


@dataclass(frozen=True)
class MatchBatch:
    """Inputs of the single-match functions for T candidates: points (T, K+1, 3) per radar frame."""

    pa: FloatArray
    ca: FloatArray
    ma: np.ndarray
    pb: FloatArray
    cb: FloatArray
    mb: np.ndarray
    m0: FloatArray

    def take(self, idx: np.ndarray) -> MatchBatch:
        return MatchBatch(
            self.pa[idx], self.ca[idx], self.ma[idx], self.pb[idx], self.cb[idx], self.mb[idx], self.m0
        )


def reference_first(points: FloatArray, ref: int) -> FloatArray:
    """Reorder axis 1 so that element ``ref`` comes first (the reference of a topology sequence)."""
    k = points.shape[1]
    order = np.r_[ref, np.delete(np.arange(k), ref)]
    return points[:, order]


def single_match_batch(
    rng: np.random.Generator,
    a: Site,
    b: Site,
    neighbours: int,
    trials: int,
    bias_a: Biases,
    bias_b: Biases,
    radius_m: float = 10_000.0,
    pd_neighbour: float = 1.0,
    neighbour_model: str = "disc",
) -> tuple[MatchBatch, FloatArray]:
    """Fig. 1 trials: one common reference with ``neighbours`` neighbours; returns batch, truth ECEF.

    Each neighbour is in each radar's track picture with probability ``pd_neighbour``
    (independently: missed detections, coverage, track breaks), so the two topology
    sequences can differ in length; 1.0 gives the ideal case of identical sequences.
    ``neighbour_model``: see :func:`around`.
    """
    ref = sample_references(rng, a, b, trials)
    nb = around(rng, a, ref, neighbours, radius_m, model=neighbour_model)
    truth = np.concatenate([ref[:, None, :], nb], axis=1)
    pa, ca = measure(rng, a, truth, bias_a)
    pb, cb = measure(rng, b, truth, bias_b)
    ma = rng.uniform(size=truth.shape[:2]) < pd_neighbour
    mb = rng.uniform(size=truth.shape[:2]) < pd_neighbour
    ma[:, 0] = mb[:, 0] = True
    return MatchBatch(pa, ca, ma, pb, cb, mb, b.rotation.T @ a.rotation), truth
