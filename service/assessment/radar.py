"""One radar measured against the reference aircraft paired with it (pure numpy).

Each assessment step takes the radar's plots of one step of data time and the references'
positions interpolated to each plot's time, and adds to the step's bin of the sliding window:

* **Detection** (the update-interval method of EUROCONTROL's surveillance standard, as
  COMPASS counts it): the plots that fall within ``gate_sigma`` of a reference aircraft (after
  the window's bias estimate) are its detections, one per scan at most.  Between two
  detections ``Δt`` apart the aircraft was expected ``n = round(Δt / T)`` times (``T`` the scan
  period) and detected once; of the ``n - 1`` scans in between only those whose reference
  position lies in the radar's **coverage** are expected: the range x azimuth x height cells in
  which the radar has detected a reference aircraft.  A gap longer than ``max_gap_s`` starts a
  new stretch (one expected, one detected).  ``pd = detected / expected``, 1-sigma binomial
  ``sqrt(pd (1 - pd) / expected)``.
* **Position**: per detection the ground-range error ``e_ρ`` (the plot's slant range put at the
  reference's height) and the azimuth error ``e_a``; horizontal error ``|d|² = e_ρ² + (ρ e_a)²``.
  The biases are the least-squares fit over the window of ``e_ρ ≈ k b_r`` (``k = r / ρ``, the
  slant-to-ground factor) and ``ρ e_a ≈ ρ b_a``; the compensated sum of squares is
  ``Σ e_ρ² - (Σ k e_ρ)² / Σ k²`` plus ``Σ ρ² e_a² - (Σ ρ² e_a)² / Σ ρ²``, so the bins need
  only sums and the window's figures are exact for any bias.  The range and azimuth RMS are
  about their means (the random parts); the median is over the latest ``median_plots`` plots.
* **Mode 3/A** correct: the plot's code is the reference's; **Mode C** correct: within
  ``mode_c_tolerance_fl`` of the reference's barometric level; each where both carry one.

Memory per radar: ``ceil(window_s / step_s)`` bins of :data:`FIELDS` sums, the coverage cells,
``median_plots`` rows, one time per aircraft seen within ``max_gap_s`` / ``window_s``, the
plots of the last ``lag_s + step_s`` of data time, and the report's fixed-size histograms.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.assessment.params import AssessmentParams
from service.assessment.references import ReferenceHistory
from service.geo import Site

FloatArray = NDArray[np.float64]

#: The sums each bin of the window holds.
FIELDS = (
    "expected",
    "detected",
    "plots",
    "s_erho2",  # Σ e_ρ²
    "s_kerho",  # Σ k e_ρ
    "s_k2",  # Σ k²
    "s_rea2",  # Σ ρ² e_a²
    "s_rea",  # Σ ρ² e_a
    "s_r2",  # Σ ρ²
    "s_er",  # Σ e_r (slant)
    "s_er2",
    "s_ea",  # Σ e_a (rad)
    "s_ea2",
    "m3a_checked",
    "m3a_correct",
    "mc_checked",
    "mc_correct",
)
F = {name: k for k, name in enumerate(FIELDS)}
#: 1-sigma error of a reference position (m): ADS-B with NACp 8 or better.
REFERENCE_SIGMA_M = 30.0
#: The report's fixed bins: detection per 10 km of range and 10 deg of azimuth, errors.
REPORT_RANGE_BIN_M = 10_000.0
REPORT_RANGE_BINS = 60
REPORT_AZIMUTH_BINS = 36
RANGE_ERROR_EDGES = np.linspace(-2_000.0, 2_000.0, 81)
AZIMUTH_ERROR_EDGES = np.linspace(-1.5, 1.5, 61)  # deg
HORIZONTAL_ERROR_EDGES = np.linspace(0.0, 3_000.0, 601)  # 5 m steps
MAX_AIRCRAFT_NAMES = 100_000
#: Before the window has a bias estimate, a step with at least this many candidate plots
#: estimates one (a median) and gates around it.
MIN_PLOTS_FOR_BIAS = 5


@dataclass
class PendingPlots:
    """A radar's plots waiting for their references (columns appended per batch)."""

    parts: list[tuple[FloatArray, ...] | tuple[Any, ...]]

    def take_until(self, cutoff_s: float) -> tuple[np.ndarray, ...] | None:
        if not self.parts:
            return None
        cols = [np.concatenate([p[k] for p in self.parts]) for k in range(len(self.parts[0]))]
        now = cols[0] <= cutoff_s
        later = ~now
        self.parts = [tuple(c[later] for c in cols)] if later.any() else []
        if not now.any():
            return None
        return tuple(c[now] for c in cols)


def wrap_deg(x: FloatArray) -> FloatArray:
    return (x + 180.0) % 360.0 - 180.0


#: The coarse gate's grid (m): a plot's candidates are the aircraft of its cell and the eight
#: around it, so any aircraft within this distance (in the radar's horizontal frame, the plot
#: put at its slant range) is among them: the coarse gate (5 km + 350 m/s x the time from the
#: step's middle) is inside it for plots within 26 s of that middle (a step spans 5 s).
COARSE_CELL_M = 20_000.0


def near_pairs(
    r: FloatArray, az: FloatArray, ar: FloatArray, aaz: FloatArray, cell_m: float
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """(plot, aircraft) index pairs in the same or adjacent ``cell_m`` grid cells of the radar's
    horizontal plane (positions from range and azimuth), by one sort of the aircraft."""
    ia, ja = (np.floor(x / cell_m).astype(np.int64) for x in _xy(ar, aaz))
    ip, jp = (np.floor(x / cell_m).astype(np.int64) for x in _xy(r, az))
    span = np.int64(1 << 20)
    keys = ia * span + ja
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    plots, aircraft = [], []
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            want = (ip + di) * span + (jp + dj)
            lo = np.searchsorted(sorted_keys, want, side="left")
            n = np.searchsorted(sorted_keys, want, side="right") - lo
            if not n.any():
                continue
            p = np.repeat(np.arange(r.size), n)
            first = np.repeat(lo, n)
            offset = np.arange(p.size) - np.repeat(np.cumsum(n) - n, n)
            plots.append(p)
            aircraft.append(order[first + offset])
    if not plots:
        return np.empty(0, dtype=np.intp), np.empty(0, dtype=np.intp)
    return np.concatenate(plots), np.concatenate(aircraft)


def _xy(rng: FloatArray, az_deg: FloatArray) -> tuple[FloatArray, FloatArray]:
    a = np.radians(az_deg)
    return rng * np.sin(a), rng * np.cos(a)


class RadarAssessment:
    """One radar's sliding window of sums, coverage, and the report's whole-run tallies."""

    def __init__(self, radar_id: str, params: AssessmentParams) -> None:
        p = self.params = params
        self.radar_id = radar_id
        self.bins = np.zeros((max(1, math.ceil(p.window_s / p.step_s)), len(FIELDS)))
        self.bin_step = np.full(self.bins.shape[0], -1, dtype=np.int64)
        self.total = np.zeros(len(FIELDS))
        self.pending = PendingPlots([])
        self.last_detection: dict[str, float] = {}
        self.last_seen: dict[str, float] = {}
        #: Every aircraft detected (the report's count; at most :data:`MAX_AIRCRAFT_NAMES`).
        self.all_aircraft: set[str] = set()
        shape = (
            math.ceil(p.coverage_max_range_m / p.coverage_range_m),
            math.ceil(360.0 / p.coverage_azimuth_deg),
            math.ceil(p.coverage_max_height_m / p.coverage_height_m) + 1,
        )
        self.coverage = np.zeros(shape, dtype=bool)
        m = p.median_plots
        self.recent = np.full((m, 5), np.nan)  # time, e_ρ, k, ρ, e_a
        self.recent_next = 0
        # the report's whole-run tallies (fixed sizes)
        self.det_range = np.zeros((2, REPORT_RANGE_BINS), dtype=np.int64)  # expected, detected
        self.det_azimuth = np.zeros((2, REPORT_AZIMUTH_BINS), dtype=np.int64)
        self.hist_range = np.zeros(RANGE_ERROR_EDGES.size - 1, dtype=np.int64)
        self.hist_azimuth = np.zeros(AZIMUTH_ERROR_EDGES.size - 1, dtype=np.int64)
        self.hist_horizontal = np.zeros(HORIZONTAL_ERROR_EDGES.size - 1, dtype=np.int64)
        self.hist_horizontal_over = 0
        #: (time, b_r, sigma, b_a deg, sigma) per step with plots; bounded (about 14 h at 5 s).
        self.bias_series: deque[tuple[float, float, float, float, float]] = deque(maxlen=10_000)
        self.mode_3a_codes: dict[str, list[int]] = {}  # reference code -> [checked, correct], bounded

    def histograms(self) -> dict[str, dict[str, Any]]:
        """The report's whole-run histograms (``topofusion assess``), each with its bins:
        detection against range and azimuth (expected and detected looks), and the errors
        against the references."""
        return {
            "detection_vs_range": {
                "bin_m": REPORT_RANGE_BIN_M,
                "expected": self.det_range[0].tolist(),
                "detected": self.det_range[1].tolist(),
            },
            "detection_vs_azimuth": {
                "bin_deg": 360.0 / REPORT_AZIMUTH_BINS,
                "expected": self.det_azimuth[0].tolist(),
                "detected": self.det_azimuth[1].tolist(),
            },
            "range_error_m": {"edges": RANGE_ERROR_EDGES.tolist(), "counts": self.hist_range.tolist()},
            "azimuth_error_deg": {
                "edges": AZIMUTH_ERROR_EDGES.tolist(),
                "counts": self.hist_azimuth.tolist(),
            },
            "horizontal_error_compensated_m": {
                "edges": HORIZONTAL_ERROR_EDGES.tolist(),
                "counts": self.hist_horizontal.tolist(),
                "beyond": self.hist_horizontal_over,
            },
        }

    # -- input ---------------------------------------------------------------------------
    def add_plots(self, cols: tuple[Any, ...]) -> None:
        """``(time_s, range_m, azimuth_deg, mode_3a, flight_level)`` of one batch."""
        if cols[0].size:
            self.pending.parts.append(cols)

    # -- the window ----------------------------------------------------------------------
    def window_sums(self, step: int) -> FloatArray:
        held = (self.bin_step > step - self.bins.shape[0]) & (self.bin_step <= step)
        return self.bins[held].sum(axis=0)

    def _bin(self, step: int) -> FloatArray:
        k = step % self.bins.shape[0]
        if self.bin_step[k] != step:
            self.bins[k] = 0.0
            self.bin_step[k] = step
        row: FloatArray = self.bins[k]
        return row

    def bias(self, sums: FloatArray) -> tuple[float, float, float, float]:
        """Range bias (m), its sigma, azimuth bias (rad), its sigma: the window's least squares,
        the prior where it has too few plots."""
        p = self.params
        n = sums[F["plots"]]
        if n < 10 or sums[F["s_k2"]] <= 0 or sums[F["s_r2"]] <= 0:
            return 0.0, p.prior_range_bias_m, 0.0, math.radians(p.prior_azimuth_bias_deg)
        b_r = sums[F["s_kerho"]] / sums[F["s_k2"]]
        b_a = sums[F["s_rea"]] / sums[F["s_r2"]]
        ss_r = max(sums[F["s_erho2"]] - sums[F["s_kerho"]] ** 2 / sums[F["s_k2"]], 0.0)
        ss_a = max(sums[F["s_rea2"]] - sums[F["s_rea"]] ** 2 / sums[F["s_r2"]], 0.0)
        return (
            float(b_r),
            float(math.sqrt(ss_r / (n - 1) / sums[F["s_k2"]])),
            float(b_a),
            float(math.sqrt(ss_a / (n - 1) / sums[F["s_r2"]])),
        )

    def step(
        self,
        step: int,
        cutoff_s: float,
        site: Site,
        refs: ReferenceHistory,
        aircraft: list[str],
    ) -> None:
        """Assess the plots up to ``cutoff_s`` against ``aircraft`` (reference ids) into bin
        ``step``."""
        cols = self.pending.take_until(cutoff_s)
        if cols is None or not aircraft:
            return
        codes = refs.known(aircraft)
        live = codes >= 0
        if not live.any():
            return
        ids = np.asarray(aircraft, dtype=object)[live]
        codes = codes[live]
        t, r, az, m3a, fl = cols
        match = self._match(site, refs, ids, codes, t, r, az, self.window_sums(step))
        if match is None:
            return
        self._count(step, site, refs, match, ids, codes, m3a, fl)

    def _match(
        self,
        site: Site,
        refs: ReferenceHistory,
        ids: NDArray[np.object_],
        codes: NDArray[np.int64],
        t: FloatArray,
        r: FloatArray,
        az: FloatArray,
        sums: FloatArray,
    ) -> dict[str, np.ndarray] | None:
        """Each plot that is a reference aircraft's (one per aircraft per scan): the plot's and
        the aircraft's index and the errors."""
        p = self.params
        t_mid = float(np.median(t))
        mid = refs.at(codes, np.full(codes.size, t_mid))
        if not mid.ok.any():
            return None
        ar, aaz, _ = site.ecef_to_polar(mid.ecef[mid.ok])
        a_idx = np.flatnonzero(mid.ok)
        # coarse: within a few km (and what an aircraft flies in the time between) in range and
        # cross-range of the aircraft's position at the step's middle, among the aircraft of the
        # plot's grid cell and its eight neighbours (cost in plots + candidates, not plots x aircraft)
        reach = 5_000.0 + 350.0 * np.abs(t - t_mid)
        pi, ak = near_pairs(r, az, ar, aaz, COARSE_CELL_M)
        d_range = np.abs(r[pi] - ar[ak])
        d_cross = np.abs(np.radians(wrap_deg(az[pi] - aaz[ak]))) * ar[ak]
        near = (d_range < reach[pi]) & (d_cross < reach[pi])
        pi, aj = pi[near], ak[near]
        if pi.size == 0:
            return None
        aj = a_idx[aj]
        at = refs.at(codes[aj], t[pi])
        pi, aj = pi[at.ok], aj[at.ok]
        if pi.size == 0:
            return None
        enu = site.ecef_to_enu(at.ecef[at.ok])
        rho_ref = np.hypot(enu[:, 0], enu[:, 1])
        r_ref = np.linalg.norm(enu, axis=1)
        az_ref = np.degrees(np.arctan2(enu[:, 0], enu[:, 1]))
        rho_ref = np.maximum(rho_ref, 1.0)
        rho_plot = np.sqrt(np.maximum(r[pi] ** 2 - enu[:, 2] ** 2, 0.0))
        e_rho = rho_plot - rho_ref
        e_r = r[pi] - r_ref
        e_a = np.radians(wrap_deg(az[pi] - az_ref))
        k = r_ref / rho_ref
        b_r, s_br, b_a, s_ba = self.bias(sums)
        z2 = self._z2(site, e_rho, k, rho_ref, e_a, b_r, s_br, b_a, s_ba)
        inside = z2 < p.gate_sigma**2
        if s_br >= p.prior_range_bias_m and inside.sum() >= MIN_PLOTS_FOR_BIAS:
            # No bias estimate yet: the prior's wide gate lets in neighbours' plots too.  The
            # median over this step's candidates (mostly the aircraft's own plots) is a robust
            # first estimate; gate again around it with the radar's own errors.
            b_r = float(np.median(e_rho[inside] / k[inside]))
            b_a = float(np.median(e_a[inside]))
            z2 = self._z2(site, e_rho, k, rho_ref, e_a, b_r, 0.0, b_a, 0.0)
            inside = z2 < p.gate_sigma**2
        if not inside.any():
            return None
        sel = np.flatnonzero(inside)
        # each plot to its nearest aircraft, then each aircraft one plot per scan (the nearest)
        sel = sel[np.lexsort((z2[sel], pi[sel]))]
        sel = sel[np.r_[True, pi[sel][1:] != pi[sel][:-1]]]
        sel = sel[np.lexsort((t[pi[sel]], aj[sel]))]
        keep = np.ones(sel.size, dtype=bool)
        half = 0.5 * site.scan_period_s
        start = 0
        for i in range(1, sel.size + 1):  # runs of one aircraft's plots closer than half a scan
            if i < sel.size and aj[sel[i]] == aj[sel[i - 1]] and t[pi[sel[i]]] - t[pi[sel[i - 1]]] < half:
                continue
            if i - start > 1:
                run = sel[start:i]
                keep[start:i] = False
                keep[start + int(np.argmin(z2[run]))] = True
            start = i
        sel = sel[keep]
        return {
            "plot": pi[sel],
            "aircraft": aj[sel],
            "time": t[pi[sel]],
            "e_rho": e_rho[sel],
            "k": k[sel],
            "rho": rho_ref[sel],
            "e_r": e_r[sel],
            "e_a": e_a[sel],
            "height": enu[sel, 2],
            "az_ref": az_ref[sel] % 360.0,
            "fl_ref": at.flight_level[at.ok][sel],
            "m3a_ref": at.mode_3a[at.ok][sel],
        }

    @staticmethod
    def _z2(
        site: Site,
        e_rho: FloatArray,
        k: FloatArray,
        rho: FloatArray,
        e_a: FloatArray,
        b_r: float,
        s_br: float,
        b_a: float,
        s_ba: float,
    ) -> FloatArray:
        """Squared normalised distance of plot to reference after the bias ``b_r``, ``b_a`` with
        1-sigma ``s_br``, ``s_ba``: radar random error, reference error and bias uncertainty."""
        s_r2 = site.range_sigma_m**2 + REFERENCE_SIGMA_M**2 + s_br**2
        s_x2 = (rho * math.radians(site.azimuth_sigma_deg)) ** 2 + REFERENCE_SIGMA_M**2 + (rho * s_ba) ** 2
        z2: FloatArray = (e_rho - k * b_r) ** 2 / s_r2 + (rho * (e_a - b_a)) ** 2 / s_x2
        return z2

    def _cells(self, rho: FloatArray, az: FloatArray, height: FloatArray) -> tuple[np.ndarray, ...]:
        p = self.params
        shape = self.coverage.shape
        i = np.clip((rho / p.coverage_range_m).astype(np.int64), 0, shape[0] - 1)
        j = np.clip((np.mod(az, 360.0) / p.coverage_azimuth_deg).astype(np.int64), 0, shape[1] - 1)
        h = np.clip((np.maximum(height, 0.0) / p.coverage_height_m).astype(np.int64), 0, shape[2] - 1)
        return i, j, h

    def _count(
        self,
        step: int,
        site: Site,
        refs: ReferenceHistory,
        m: dict[str, np.ndarray],
        ids: NDArray[np.object_],
        codes: NDArray[np.int64],
        m3a: NDArray[np.object_],
        fl: FloatArray,
    ) -> None:
        p = self.params
        row = np.zeros(len(FIELDS))
        n = m["plot"].size
        # Detection, per aircraft in time order (the match is sorted so).  A scan counts, detected
        # or missed, only where the coverage was known before this step: a cell learnt from the
        # detection itself would count its detections and never the misses before them.
        cells = self._cells(m["rho"], m["az_ref"], m["height"])
        known = self.coverage[cells]
        period = site.scan_period_s
        miss_code: list[int] = []
        miss_time: list[float] = []
        counted = np.zeros(n, dtype=bool)
        for i, (a, when) in enumerate(zip(m["aircraft"].tolist(), m["time"].tolist(), strict=True)):
            name = str(ids[a])
            last = self.last_detection.get(name)
            self.last_detection[name] = when
            self.last_seen[name] = when
            if len(self.all_aircraft) < MAX_AIRCRAFT_NAMES:
                self.all_aircraft.add(name)
            if last is None or when - last > p.max_gap_s:
                counted[i] = known[i]
                continue
            scans = round((when - last) / period)
            if scans < 1:
                continue  # a second plot within the same scan
            counted[i] = known[i]
            miss_code += [int(codes[a])] * (scans - 1)
            miss_time += [last + q * period for q in range(1, scans)]
        detected = expected = int(np.count_nonzero(counted))
        self._tally_detections({k: v[counted] for k, v in m.items()})
        if miss_code:
            at = refs.at(np.asarray(miss_code, dtype=np.int64), np.asarray(miss_time))
            enu = site.ecef_to_enu(at.ecef[at.ok])
            rho, az = np.hypot(enu[:, 0], enu[:, 1]), np.degrees(np.arctan2(enu[:, 0], enu[:, 1])) % 360.0
            covered = self.coverage[self._cells(rho, az, enu[:, 2])]
            expected += int(np.count_nonzero(covered))
            self._tally(self.det_range[0], self.det_azimuth[0], rho[covered], az[covered])
        self.coverage[cells] = True
        row[F["expected"]] = expected
        row[F["detected"]] = detected
        # position
        e_rho, k, rho, e_a, e_r = m["e_rho"], m["k"], m["rho"], m["e_a"], m["e_r"]
        row[F["plots"]] = n
        row[F["s_erho2"]] = np.sum(e_rho**2)
        row[F["s_kerho"]] = np.sum(k * e_rho)
        row[F["s_k2"]] = np.sum(k**2)
        row[F["s_rea2"]] = np.sum((rho * e_a) ** 2)
        row[F["s_rea"]] = np.sum(rho**2 * e_a)
        row[F["s_r2"]] = np.sum(rho**2)
        row[F["s_er"]] = np.sum(e_r)
        row[F["s_er2"]] = np.sum(e_r**2)
        row[F["s_ea"]] = np.sum(e_a)
        row[F["s_ea2"]] = np.sum(e_a**2)
        # identity: Mode 3/A, Mode C
        plot_m3a, plot_fl = m3a[m["plot"]], fl[m["plot"]]
        has_m3a = np.array(
            [a is not None and b is not None for a, b in zip(plot_m3a, m["m3a_ref"], strict=True)]
        )
        ok_m3a = np.array([a == b for a, b in zip(plot_m3a, m["m3a_ref"], strict=True)]) & has_m3a
        has_fl = np.isfinite(plot_fl) & np.isfinite(m["fl_ref"])
        ok_fl = has_fl & (
            np.abs(np.where(has_fl, plot_fl - m["fl_ref"], 0.0)) <= p.mode_c_tolerance_fl + 1e-9
        )
        row[F["m3a_checked"]], row[F["m3a_correct"]] = np.count_nonzero(has_m3a), np.count_nonzero(ok_m3a)
        row[F["mc_checked"]], row[F["mc_correct"]] = np.count_nonzero(has_fl), np.count_nonzero(ok_fl)
        self._bin(step)[:] += row
        self.total += row
        # the median's rows
        rows = np.column_stack([m["time"], e_rho, k, rho, e_a])[-p.median_plots :]
        idx = (self.recent_next + np.arange(rows.shape[0])) % p.median_plots
        self.recent[idx] = rows
        self.recent_next = int((self.recent_next + rows.shape[0]) % p.median_plots)
        # the report's whole-run tallies
        b_r, s_br, b_a, s_ba = self.bias(self.window_sums(step))
        self.hist_range += np.histogram(e_r, RANGE_ERROR_EDGES)[0]
        self.hist_azimuth += np.histogram(np.degrees(e_a), AZIMUTH_ERROR_EDGES)[0]
        horizontal = np.hypot(e_rho - k * b_r, rho * (e_a - b_a))
        self.hist_horizontal += np.histogram(horizontal, HORIZONTAL_ERROR_EDGES)[0]
        self.hist_horizontal_over += int(np.count_nonzero(horizontal >= HORIZONTAL_ERROR_EDGES[-1]))
        if n >= 10:
            self.bias_series.append(
                (float(np.max(m["time"])), b_r, s_br, math.degrees(b_a), math.degrees(s_ba))
            )
        for ref, ok in zip(m["m3a_ref"][has_m3a], ok_m3a[has_m3a], strict=True):
            if ref in self.mode_3a_codes or len(self.mode_3a_codes) < 4096:
                c = self.mode_3a_codes.setdefault(ref, [0, 0])
                c[0] += 1
                c[1] += int(ok)

    def _tally_detections(self, m: dict[str, np.ndarray]) -> None:
        """The report's detection-by-range and -azimuth tallies of the detections (each counts
        as expected and detected, as in :meth:`_count`; second plots of a scan aside)."""
        self._tally(self.det_range[0], self.det_azimuth[0], m["rho"], m["az_ref"])
        self._tally(self.det_range[1], self.det_azimuth[1], m["rho"], m["az_ref"])

    @staticmethod
    def _tally(by_range: np.ndarray, by_azimuth: np.ndarray, rho: FloatArray, az: FloatArray) -> None:
        i = np.clip((rho / REPORT_RANGE_BIN_M).astype(np.int64), 0, by_range.size - 1)
        j = np.clip((np.mod(az, 360.0) / (360.0 / by_azimuth.size)).astype(np.int64), 0, by_azimuth.size - 1)
        np.add.at(by_range, i, 1)
        np.add.at(by_azimuth, j, 1)

    def forget_before(self, time_s: float) -> None:
        """Aircraft not detected for ``max_gap_s`` nor seen in the window are forgotten."""
        p = self.params
        self.last_detection = {a: t for a, t in self.last_detection.items() if t >= time_s - p.max_gap_s}
        self.last_seen = {a: t for a, t in self.last_seen.items() if t >= time_s - p.window_s}

    def median_m(self, since_s: float, sums: FloatArray) -> float | None:
        rows = self.recent[np.isfinite(self.recent[:, 0]) & (self.recent[:, 0] >= since_s)]
        if rows.shape[0] == 0:
            return None
        b_r, _, b_a, _ = self.bias(sums)
        d = np.hypot(rows[:, 1] - rows[:, 2] * b_r, rows[:, 3] * (rows[:, 4] - b_a))
        return float(np.median(d))
