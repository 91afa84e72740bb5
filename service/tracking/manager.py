"""The per-radar track manager: association, filtering, M-of-N life cycle, initiation.

One :meth:`TrackManager.update` per accepted batch, all in data time:

1. plots to ENU positions with covariance (:mod:`.measurement`), each at its own time;
2. gating: KD-tree pre-gate on the tracks predicted to the batch's median plot time, then the
   exact Mahalanobis gate of each candidate with the track predicted to *that plot's* time;
3. one-to-one assignment (:mod:`.assignment`, ``linear_sum_assignment``) and the Kalman update
   of every assigned track (:mod:`.kalman`), all vectorised across tracks;
4. looks: a track is *expected* in a batch when its predicted azimuth lies inside the azimuth
   arc covered by the batch's plots (sector batches of a scanning radar), less a margin.  A hit
   or an expected miss is one look of its M-of-N history (a bit mask);
5. confirmation (M of the last N looks), deletion (a tentative track that can no longer reach M,
   a confirmed track after ``confirmed_max_misses`` expected misses in a row, any track not
   updated for ``coast_scans`` scan periods);
6. unused plots join the radar's :class:`PlotWindow`; the initiator turns window plots into
   candidate groups, a CV fit checks each (mean NIS), and accepted groups become tentative
   tracks (their plots count as hits) and leave the window.

Track ids ``{prefix}-{n}`` count from 1 and are never reused.  Every update records which
plots joined which track (:attr:`TrackManager.joined`, plots with all their columns); the
manager itself only carries them.  Per-track labels from the plots (the simulator's truth, for
evaluation) are kept outside the tracker, by :mod:`service.truth_labels`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from service.geo import FloatArray, Site
from service.tracking import kalman
from service.tracking.assignment import assign
from service.tracking.base import PlotColumns, Tracker, TrackTable
from service.tracking.groups import fit_groups
from service.tracking.initiators import get_initiator
from service.tracking.measurement import Measurements, plots_to_measurements
from service.tracking.params import TrackerParams
from service.tracking.window import PlotWindow

IntArray = NDArray[np.intp]
_POP16 = np.array([bin(i).count("1") for i in range(1 << 16)], dtype=np.int64)


def popcount(h: NDArray[np.int64]) -> NDArray[np.int64]:
    """Number of set bits of non-negative ints below 2^32."""
    return np.asarray(_POP16[h & 0xFFFF] + _POP16[(h >> 16) & 0xFFFF])


def covered_arc(azimuth_deg: FloatArray) -> tuple[float, float] | None:
    """Smallest arc ``(start, width)`` in degrees holding every azimuth; None without plots."""
    if azimuth_deg.shape[0] == 0:
        return None
    a = np.sort(np.mod(azimuth_deg, 360.0))
    gaps = np.diff(np.append(a, a[0] + 360.0))
    g = int(np.argmax(gaps))
    start = float(a[(g + 1) % a.shape[0]])
    return start, float(360.0 - gaps[g])


class TrackManager(Tracker):
    """Per-radar tracker (see module docstring)."""

    def __init__(
        self,
        site: Site,
        window_s: float,
        initiator: str = "logic",
        id_prefix: str = "T",
        params: TrackerParams | None = None,
    ) -> None:
        super().__init__(site, window_s)
        self.params = params if params is not None else TrackerParams()
        mp = self.params.manager
        if not 1 <= mp.confirm_m <= mp.confirm_n <= 30:
            raise ValueError(f"need 1 <= confirm_m <= confirm_n <= 30, got {mp.confirm_m}, {mp.confirm_n}")
        self.initiator = initiator
        self._initiate = get_initiator(initiator)
        self.id_prefix = id_prefix
        self._window = PlotWindow(window_s)
        self._next_uid = 1
        self.last_time_s = -np.inf
        self._uid = np.empty(0, dtype=np.int64)
        self._x = np.empty((0, 6))
        self._P = np.empty((0, 6, 6))
        self._t = np.empty(0)
        self._hist = np.empty(0, dtype=np.int64)
        self._looks = np.empty(0, dtype=np.int64)
        self._miss_run = np.empty(0, dtype=np.int64)
        self._confirmed = np.empty(0, dtype=bool)
        self._nplots = np.empty(0, dtype=np.int64)
        #: The plots that joined tracks in the last update, as ``(track uids, plots)`` chunks:
        #: assigned to existing tracks, and the members of newly initiated ones.
        self.joined: list[tuple[NDArray[np.int64], PlotColumns]] = []

    # -- contract ---------------------------------------------------------------------
    @property
    def window_plots(self) -> int:
        return len(self._window)

    @property
    def uids(self) -> NDArray[np.int64]:
        """Numeric ids of the live tracks, in the row order of :meth:`tracks`."""
        return self._uid.copy()

    def update(self, plots: PlotColumns, time_s: float) -> None:
        fp = self.params.filter
        self.joined = []
        self.last_time_s = max(self.last_time_s, float(time_s))
        meas = plots_to_measurements(self.site, plots, self.params.measurement)
        n_tr = self._uid.shape[0]
        used = np.zeros(len(meas), dtype=bool)
        hit = np.zeros(n_tr, dtype=bool)
        if n_tr and len(meas):
            rows, cols, d2, xp, pp = self._gate(meas)
            chosen = assign(rows, cols, d2, fp.gate_chi2)
            r, c = rows[chosen], cols[chosen]
            if r.shape[0]:
                x_new, p_new, _ = kalman.update(xp[chosen], pp[chosen], meas.enu_m[c], meas.covariance[c])
                self._x[r], self._P[r], self._t[r] = x_new, p_new, meas.time_s[c]
                self._nplots[r] += 1
                hit[r] = True
                used[c] = True
                self.joined.append((self._uid[r], plots.take(c)))
        self._life_cycle(hit, plots.azimuth_deg, float(time_s))
        self._window.extend(plots.take(~used), float(time_s))
        self._initiate_from_window()

    def tracks(self) -> TrackTable:
        n = self._uid.shape[0]
        if n == 0:
            return TrackTable.empty()
        rot = self.site.rotation
        pos = self._x[:, :3] @ rot.T + self.site.origin_ecef
        vel = self._x[:, 3:] @ rot.T
        big = np.zeros((6, 6))
        big[:3, :3] = rot
        big[3:, 3:] = rot
        cov = big @ self._P @ big.T
        ids = np.array([f"{self.id_prefix}-{u}" for u in self._uid.tolist()], dtype=str)
        return TrackTable(
            ids,
            self._confirmed.copy(),
            self._t.copy(),
            pos,
            vel,
            cov,
            self._nplots.copy(),
            np.full(n, None, dtype=object),  # plot labels per track: service.truth_labels
        )

    # -- association ------------------------------------------------------------------
    def _gate(self, meas: Measurements) -> tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray]:
        """Gated candidates ``(track, plot, d^2)`` and each candidate's predicted state."""
        fp = self.params.filter
        tb = float(np.median(meas.time_s))
        xb, pb = kalman.predict(self._x, self._P, tb - self._t, fp.process_noise_psd)
        span = float(np.max(np.abs(meas.time_s - tb)))
        sig_t = np.sqrt(np.trace(pb[:, :3, :3], axis1=1, axis2=2))
        sig_p = float(np.sqrt(np.max(np.trace(meas.covariance, axis1=1, axis2=2))))
        speed = np.linalg.norm(xb[:, 3:], axis=1)
        radius = np.sqrt(fp.gate_chi2) * (sig_t + sig_p) + speed * span
        radius = np.minimum(radius, fp.coarse_gate_max_m)
        tree_t = cKDTree(xb[:, :3])
        tree_p = cKDTree(meas.enu_m)
        sdm = tree_t.sparse_distance_matrix(tree_p, float(radius.max()), output_type="ndarray")
        rows = sdm["i"].astype(np.intp)
        cols = sdm["j"].astype(np.intp)
        keep = sdm["v"] <= radius[rows]
        rows, cols = rows[keep], cols[keep]
        dt = meas.time_s[cols] - self._t[rows]
        xp, pp = kalman.predict(self._x[rows], self._P[rows], dt, fp.process_noise_psd)
        y, S = kalman.innovation(xp, pp, meas.enu_m[cols], meas.covariance[cols])
        d2 = kalman.mahalanobis2(y, S)
        ok = d2 <= fp.gate_chi2
        return rows[ok], cols[ok], d2[ok], xp[ok], pp[ok]

    # -- life cycle -------------------------------------------------------------------
    def _expected(self, azimuth_deg: FloatArray, time_s: float) -> NDArray[np.bool_]:
        """Tracks whose predicted azimuth lies inside the batch's covered arc (less a margin)."""
        arc = covered_arc(np.asarray(azimuth_deg, dtype=float))
        n = self._uid.shape[0]
        if arc is None or n == 0:
            return np.zeros(n, dtype=bool)
        start, width = arc
        pos = self._x[:, :3] + self._x[:, 3:] * (time_s - self._t)[:, None]
        az = np.degrees(np.arctan2(pos[:, 0], pos[:, 1]))
        off = np.mod(az - start, 360.0)
        m = self.params.manager.sector_margin_deg
        return np.asarray((off >= m) & (off <= width - m))

    def _life_cycle(self, hit: NDArray[np.bool_], azimuth_deg: FloatArray, time_s: float) -> None:
        mp = self.params.manager
        n_bits = mp.confirm_n
        mask = (1 << n_bits) - 1
        expected = self._expected(azimuth_deg, time_s) & ~hit
        looked = hit | expected
        self._hist[looked] = ((self._hist[looked] << 1) | hit[looked].astype(np.int64)) & mask
        self._looks[looked] = np.minimum(self._looks[looked] + 1, n_bits)
        self._miss_run[hit] = 0
        self._miss_run[expected] += 1
        hits = popcount(self._hist)
        self._confirmed |= hits >= mp.confirm_m
        misses = self._looks - hits
        dead = (~self._confirmed & (misses > mp.confirm_n - mp.confirm_m)) | (
            self._confirmed & (self._miss_run >= mp.confirmed_max_misses)
        )
        dead |= time_s - self._t > mp.coast_scans * self.site.scan_period_s
        if dead.any():
            self._keep(~dead)

    def _keep(self, keep: NDArray[np.bool_]) -> None:
        self._uid = self._uid[keep]
        self._x, self._P, self._t = self._x[keep], self._P[keep], self._t[keep]
        self._hist, self._looks = self._hist[keep], self._looks[keep]
        self._miss_run, self._confirmed = self._miss_run[keep], self._confirmed[keep]
        self._nplots = self._nplots[keep]

    # -- initiation -------------------------------------------------------------------
    def _initiate_from_window(self) -> None:
        wplots = self._window.plots
        if len(wplots) < 3:
            return
        p = self.params
        wm = plots_to_measurements(self.site, wplots, p.measurement)
        groups = self._initiate(wm, p, self.site.scan_period_s)
        if groups.count == 0:
            return
        births = fit_groups(wm, groups, p.filter.process_noise_psd, p.manager.birth_velocity_sigma_mps)
        ok = births.mean_nis <= p.manager.birth_max_mean_nis
        if not ok.any():
            return
        k = int(ok.sum())
        uid = np.arange(self._next_uid, self._next_uid + k, dtype=np.int64)
        self._next_uid += k
        n_bits = p.manager.confirm_n
        first = np.minimum(births.plots[ok], n_bits).astype(np.int64)
        hist = (np.int64(1) << first) - 1
        self._uid = np.concatenate([self._uid, uid])
        self._x = np.concatenate([self._x, births.x[ok]])
        self._P = np.concatenate([self._P, births.P[ok]])
        self._t = np.concatenate([self._t, births.time_s[ok]])
        self._hist = np.concatenate([self._hist, hist])
        self._looks = np.concatenate([self._looks, first])
        self._miss_run = np.concatenate([self._miss_run, np.zeros(k, dtype=np.int64)])
        self._confirmed = np.concatenate([self._confirmed, popcount(hist) >= p.manager.confirm_m])
        self._nplots = np.concatenate([self._nplots, births.plots[ok]])
        # Plots of accepted groups leave the window; label -> uid of the new track.
        label_uid = np.full(groups.count, -1, dtype=np.int64)
        label_uid[ok] = uid
        in_new = label_uid[groups.group] >= 0
        member = groups.plot[in_new]
        self.joined.append((label_uid[groups.group][in_new], wplots.take(member)))
        used = np.zeros(len(wplots), dtype=bool)
        used[member] = True
        self._window.replace(wplots.take(~used))
