"""The per-radar track manager: association, filtering, M-of-N life cycle, initiation.

One :meth:`TrackManager.update` per accepted batch, all in data time:

1. plots to ENU positions with covariance (:mod:`.measurement`), each at its own time;
2. gating: KD-tree pre-gate on the tracks predicted to the batch's median plot time, then the
   exact Mahalanobis gate of each candidate with the track predicted to *that plot's* time;
3. one-to-one assignment (:mod:`.assignment`, ``linear_sum_assignment``) and the filter update
   of every assigned track (the two-model IMM of :mod:`.imm` over the constant-velocity Kalman
   filter of :mod:`.kalman`), all vectorised across tracks;
4. looks: a track is *expected* in a batch when its predicted azimuth lies inside the azimuth
   arc covered by the batch's plots (sector batches of a scanning radar), less a margin.  A hit
   or an expected miss is one look of its M-of-N history (a bit mask);
5. confirmation (M of the last N looks), deletion (a tentative track that can no longer reach M,
   a confirmed track after ``confirmed_max_misses`` expected misses in a row, an established one
   after more on a radar of lower detection probability (:mod:`.detection`), any track not
   updated for ``coast_scans`` scan periods, an established one for its misses and a half);
6. unused plots join the radar's :class:`PlotWindow` (at most ``bounds.max_window_plots``, the
   oldest evicted beyond); the initiator turns window plots into candidate groups, a CV fit
   checks each (mean NIS), and accepted groups become tentative tracks (their plots count as
   hits) and leave the window.

An update is all or nothing: it builds the new tracks and window aside (the window's chunks
are never written in place; the rows of the assigned tracks' states that are written in place
are saved first and restored on failure) and keeps them only once every step has succeeded,
so a batch that fails part-way leaves the tracker exactly as it was.

Track ids ``{prefix}-{n}`` count from ``first_number`` (1 unless a restart's epoch says
otherwise, :func:`~service.tracking.base.first_number`) and are never reused.  Every update
records which plots joined which track (:attr:`TrackManager.joined`, plots with all their
columns); from them it keeps each track's latest identity codes (Mode 3/A, Mode S:
:mod:`.identity`), which association never reads.  Labels for evaluation are kept outside
the tracker (:mod:`service.evaluation`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from service.geo import FloatArray, Site
from service.tracking import imm, kalman
from service.tracking.aid import PartnerReferences, aided_d2, horizontal_spread
from service.tracking.assignment import assign, clarity, weighted_covariance
from service.tracking.base import PlotColumns, Tracker, TrackTable
from service.tracking.coincident import first_in_cell
from service.tracking.detection import DetectionMeter
from service.tracking.duplicates import duplicate_losers, shared_plot_pairs
from service.tracking.formation import (
    common_velocity,
    formation_groups,
    manoeuvring,
    velocity_gate,
    velocity_update,
)
from service.tracking.groups import fit_groups
from service.tracking.identity import TrackCodes
from service.tracking.initiators import get_initiator
from service.tracking.measurement import Measurements, plots_to_measurements
from service.tracking.noise import NoiseMeter
from service.tracking.pairs import cell_counts
from service.tracking.params import TrackerParams
from service.tracking.revisit import RevisitMeter
from service.tracking.window import PlotWindow, window_for

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


@dataclass(frozen=True)
class _Tracks:
    """The live tracks, one row each.  An update builds new arrays, except for the rows of the
    fields in ``_WRITTEN`` (states, times, plot counts) that its filter update writes (and
    restores on failure, :meth:`TrackManager.update`)."""

    uid: NDArray[np.int64]
    x: FloatArray  # (n, 6) ENU state
    P: FloatArray  # (n, 6, 6)
    t: FloatArray  # time of the state
    hist: NDArray[np.int64]  # look history, 1 = a plot, newest look in bit 0 (``_LOOK_BITS`` looks)
    looks: NDArray[np.int64]  # looks in the history (at most ``_LOOK_BITS``; M-of-N reads confirm_n)
    miss_run: NDArray[np.int64]  # expected misses in a row
    confirmed: NDArray[np.bool_]
    nplots: NDArray[np.int64]
    ids: NDArray[np.str_]  # "{prefix}-{uid}", made once at birth
    cov_ecef: FloatArray  # (n, 6, 6) ``P`` in ECEF, made when ``P`` is (see ``TrackManager.tracks``)
    quality: FloatArray  # ``Track.quality``: average clarity of its associations, NaN before one
    xm: FloatArray  # (n, M, 6) each filter model's state (:mod:`.imm`); ``x`` is their mixture
    Pm: FloatArray  # (n, M, 6, 6)
    mu: FloatArray  # (n, M) the models' probabilities
    formation: IntArray  # its formation at the last search (:mod:`.formation`; -1: none)
    free_until: FloatArray  # until this data time the filter's own models: its formation manoeuvred

    def __len__(self) -> int:
        return int(self.uid.shape[0])

    @staticmethod
    def empty(models: int) -> _Tracks:
        i = np.empty(0, dtype=np.int64)
        f = np.empty(0)
        m = np.empty((0, 6, 6))
        b, u = np.empty(0, dtype=bool), np.empty(0, dtype=str)
        k = models
        return _Tracks(
            i,
            np.empty((0, 6)),
            m,
            f,
            i,
            i,
            i,
            b,
            i,
            u,
            m,
            f,
            np.empty((0, k, 6)),
            np.empty((0, k, 6, 6)),
            np.empty((0, k)),
            np.empty(0, dtype=np.intp),
            f,
        )

    def take(self, keep: NDArray[np.bool_]) -> _Tracks:
        return _Tracks(*(getattr(self, f.name)[keep] for f in fields(self)))

    def append(self, new: _Tracks) -> _Tracks:
        return _Tracks(*(np.concatenate([getattr(self, f.name), getattr(new, f.name)]) for f in fields(self)))


#: Looks kept in ``_Tracks.hist`` (bits of an int64 below the sign bit): the M-of-N reads the
#: last ``confirm_n`` of them, the duplicate rule the last ``FormationParams.duplicate_looks``.
_LOOK_BITS = 62
_LOOK_MASK = (1 << _LOOK_BITS) - 1


Joined = list[tuple[NDArray[np.int64], PlotColumns]]
#: The fields of ``_Tracks`` an update writes in place, row by row (``TrackManager.update``).
_WRITTEN = ("x", "P", "t", "nplots", "cov_ecef", "xm", "Pm", "mu")
#: The tracks an update wrote in, the rows it wrote, and their previous values by field.
_Saved = tuple[_Tracks, IntArray, dict[str, NDArray]]

#: Association memory: a (track, plot) pair of the KD-tree pre-gate search costs about 90 bytes
#: (its output and masks), a gate prediction about 1.3 kB, so the search runs on chunks of
#: tracks with up to this many times ``gate_block`` pairs: about the memory of one block of
#: predictions.
_SEARCH_PAIRS_PER_PREDICTION = 16


def _track_chunks(tracks_enu: FloatArray, plots_enu: FloatArray, reach: float, block: int) -> list[IntArray]:
    """Tracks in consecutive chunks whose candidate plots (those in the 3x3 grid cells of
    side ``reach`` around each track, a bound on the plots within ``reach``) add up to at most
    ``block``, plus one track's own; all tracks in one chunk when they fit."""
    n_t = tracks_enu.shape[0]
    every = np.arange(n_t, dtype=np.intp)
    if n_t * plots_enu.shape[0] <= block:
        return [every]
    bound = cell_counts(plots_enu[:, :2], tracks_enu[:, :2], reach)
    if int(bound.sum()) <= block:
        return [every]
    start = np.cumsum(bound) - bound
    return np.split(every, np.flatnonzero(np.diff(start // block)) + 1)


#: Association: the tracks near a batch's plots are found on a dense grid of flags over the
#: box of the plots (cells of side ``coarse_gate_max_m``) when it has at most this many cells
#: (64 kB).  A wider box (plots spread over far more than the coarse gate) sends every track to
#: the pre-gate search, the form used before the selection.
_NEAR_GRID_CELLS = 65_536

#: Rounding pad of the selection grid's side, in units in the last place of the largest
#: coordinate: a track and a plot within ``coarse_gate_max_m`` of each other then always lie
#: in neighbouring cells, whatever the rounding of the positions and of the cell indices.
_NEAR_GRID_PAD_ULPS = 16.0


def _near_tracks(tracks: _Tracks, plots_enu: FloatArray, tb: float, reach: float) -> IntArray | None:
    """Rows of the tracks that may have a plot within ``reach`` at ``tb``: those whose predicted
    (east, north) lies in one of the 3x3 cells around a plot's cell of a square grid of side
    ``reach`` (a pair within ``reach`` in 3-D is within it in 2-D, so in neighbouring cells).
    None, meaning every track, when some number is not finite (the search over all tracks
    then meets it as before) or the grid would pass ``_NEAR_GRID_CELLS``."""
    x, t = tracks.x, tracks.t
    pos = x[:, :2] + (tb - t)[:, None] * x[:, 3:5]
    if not np.isfinite(x.sum() + tracks.P.sum() + t.sum() + pos.sum() + plots_enu.sum() + tb):
        return None  # a sum is finite only if every term is
    en = plots_enu[:, :2]
    lo, hi = en.min(axis=0), en.max(axis=0)
    reach = max(reach, 0.0)
    side = reach + _NEAR_GRID_PAD_ULPS * float(np.spacing(float(np.abs([lo, hi]).max()) + reach))
    extent = np.floor((hi - lo) / side)
    if (extent[0] + 5.0) * (extent[1] + 5.0) > _NEAR_GRID_CELLS:
        return None
    # The plots' cells, two empty cells on each side: the ring next to them is their
    # neighbourhood, the outer ring stays empty and takes every track beyond.
    shape = (int(extent[0]) + 5, int(extent[1]) + 5)
    cell = np.floor((en - lo) / side).astype(np.intp) + 2
    occupied = np.zeros(shape, dtype=bool)
    occupied[cell[:, 0], cell[:, 1]] = True
    band = np.zeros(shape, dtype=bool)  # the 3x3 neighbourhood, one axis at a time
    band[1:-1] = occupied[:-2] | occupied[1:-1] | occupied[2:]
    near = np.zeros(shape, dtype=bool)
    near[:, 1:-1] = band[:, :-2] | band[:, 1:-1] | band[:, 2:]
    at = np.clip(np.floor((pos - lo) / side) + 2.0, 0.0, np.array(shape, dtype=float) - 1.0).astype(np.intp)
    return np.flatnonzero(near[at[:, 0], at[:, 1]])


def _ecef_block(rotation: FloatArray) -> FloatArray:
    """The 6x6 map of an ENU ``[position, velocity]`` covariance to ECEF (the site's rotation on
    both diagonal blocks): ``big @ P @ big.T``."""
    big = np.zeros((6, 6))
    big[:3, :3] = rotation
    big[3:, 3:] = rotation
    return big


class TrackManager(Tracker):
    """Per-radar tracker (see module docstring)."""

    def __init__(
        self,
        site: Site,
        window_s: float,
        initiator: str = "logic",
        id_prefix: str = "T",
        params: TrackerParams | None = None,
        first_number: int = 1,
        window_follows_site: bool = False,
    ) -> None:
        """``first_number``: the number of the first track's id (``f"{id_prefix}-{n}"``); the
        track uids inside stay 1, 2, ... (service.evaluation packs them into 32 bits).
        ``window_follows_site``: the window is the one of the site's scan period
        (:func:`~service.tracking.window.window_for`) and follows it when the site is updated."""
        super().__init__(site, window_s)
        self._window_follows_site = window_follows_site
        self.params = params if params is not None else TrackerParams()
        mp = self.params.manager
        if not 1 <= mp.confirm_m <= mp.confirm_n <= 30:
            raise ValueError(f"need 1 <= confirm_m <= confirm_n <= 30, got {mp.confirm_m}, {mp.confirm_n}")
        self.initiator = initiator
        self._initiate = get_initiator(initiator)
        self.id_prefix = id_prefix
        #: A track's id number is its uid plus this (:func:`~service.tracking.base.first_number`).
        self._id_offset = first_number - 1
        self._window = PlotWindow(window_s, self.params.bounds.max_window_plots)
        self._coincident = 0
        self._next_uid = 1
        self.last_time_s = -np.inf
        #: Data time of the last search of the window by the initiators (``update``).
        self._initiated_s = -np.inf
        #: The filter's models (:mod:`.imm`; one: the plain constant-velocity filter).
        self._models = imm.models_of(self.params.filter)
        #: The models of a track flying in formation (None: the rule is off), and the data
        #: time of the last search for formations (``update``).
        self._formation_models = imm.formation_models_of(self.params.filter, self.params.formation)
        self._formations_s = -np.inf
        #: The references of the next batch (:meth:`take_aid`; None: no aid), the associations
        #: they decided so far (:attr:`aided_associations`) and in the batch being updated.
        self._aid: PartnerReferences | None = None
        self._aided = 0
        self._aided_batch = 0
        self._tracks = _Tracks.empty(self._models.count)
        #: The site rotation that ``_tracks.cov_ecef`` was made with, and the site that the
        #: window's measurements were made with (a site can be replaced, see ``update``).
        self._ecef_rotation = np.array(self.site.rotation, dtype=float, copy=True)
        self._window_site = self.site
        #: The plots that joined tracks in the last update, as ``(track uids, plots)`` chunks:
        #: assigned to existing tracks, and the members of newly initiated ones.
        self.joined: Joined = []
        #: Each track's latest Mode 3/A and Mode S codes (the columns of :meth:`tracks`).
        self.identity = TrackCodes()
        #: The revisit period the plots show, against the site's (:mod:`.revisit`).
        self.revisit = RevisitMeter(self.params.revisit, id_prefix)
        #: The measurement errors the innovations show, against the site's (:mod:`.noise`).
        self.noise = NoiseMeter(self.params.noise, id_prefix)
        #: The detection probability its established tracks show, for deletion (:mod:`.detection`).
        self.detection = DetectionMeter(self.params.manager)

    @property
    def scan_period_s(self) -> float:
        """The scan period every life-cycle time scale is counted in: the site's, unless the
        plots show another (:mod:`.revisit`)."""
        return self.revisit.period(self.site.scan_period_s)

    # -- contract ---------------------------------------------------------------------
    def drop_tracks(self) -> None:
        self._tracks = _Tracks.empty(self._models.count)
        self._window.clear()
        self.revisit.clear()
        self.noise.clear()
        self.detection = DetectionMeter(self.params.manager)
        self.joined = []
        self.identity.keep(self._tracks.uid)

    @property
    def window_plots(self) -> int:
        return len(self._window)

    @property
    def window_evicted(self) -> int:
        """Plots evicted so far because the window held ``bounds.max_window_plots``."""
        return self._window.evicted

    @property
    def plots_coincident(self) -> int:
        """Plots dropped so far as repeats of another plot of their batch
        (``measurement.coincident_sigma``)."""
        return self._coincident

    @property
    def aided_associations(self) -> int:
        """Associations so far whose plot was chosen by its distance from a confirmed partner
        (:mod:`.aid`)."""
        return self._aided

    @property
    def scan_period_observed_s(self) -> float | None:
        return self.revisit.observed_s

    @property
    def measurement_sigma_scale(self) -> float:
        return self.noise.scale

    @property
    def pd_measured(self) -> float | None:
        return self.detection.pd

    @property
    def misses_to_delete(self) -> int | None:
        return self.detection.misses_to_delete()

    @property
    def uids(self) -> NDArray[np.int64]:
        """Numeric ids of the live tracks, in the row order of :meth:`tracks`."""
        return self._tracks.uid.copy()

    def follow(self, site: Site) -> None:
        """A site updated with a new scan period changes a window sized by it: a window made
        for a 4 s radar holds one look of a 10 s one, and no track could start."""
        super().follow(site)
        if self._window_follows_site:
            self.window_s = self._window.window_s = window_for(site)

    def update(self, plots: PlotColumns, time_s: float) -> None:
        """One batch, all or nothing (module docstring): the steps build new track arrays and
        change a copy of the window, and the tracker takes them only at the end.  The one
        exception is the Kalman update of the assigned tracks, written into their rows in
        place (a fresh copy of every state and covariance per batch costs more than the rest
        of the bookkeeping); those rows are saved first and put back if a later step fails.

        Two caches ride along, both made from the site: each track's ECEF covariance (made
        when its covariance changes, for :meth:`tracks`) and the measurements of the window's
        plots (made when their batch arrives).  When the engine has replaced the site since,
        both are made anew here, so results are those of converting everything every time."""
        mp = self.params.measurement
        keep = first_in_cell(plots, self.site, mp.coincident_sigma, mp.altitude_sigma_m)
        coincident = len(plots) - int(np.count_nonzero(keep))
        if coincident:
            plots = plots.take(keep)
        site = self.noise.site(self.site)  # (the site's sigmas, grown if the innovations say so)
        scan_s = self.scan_period_s
        joined: Joined = []
        tracks = self._tracks
        window = self._window.copy()
        self._aided_batch = 0
        rotation = np.array(site.rotation, dtype=float, copy=True)
        big = _ecef_block(rotation)
        saved: _Saved | None = None
        try:
            if not np.array_equal(rotation, self._ecef_rotation):
                tracks = replace(tracks, cov_ecef=big @ tracks.P @ big.T)
            if site != self._window_site:
                wplots = window.plots
                window.replace(wplots, plots_to_measurements(site, wplots, self.params.measurement))
            meas = plots_to_measurements(site, plots, self.params.measurement)
            used = np.zeros(len(meas), dtype=bool)
            hit = np.zeros(len(tracks), dtype=bool)
            twins = np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
            nis = np.empty(0)
            formations_s = self._formations_s
            fm = self.params.formation
            if self._formation_models is not None and (
                time_s - formations_s >= fm.formation_interval_scans * scan_s
            ):
                tracks = replace(tracks, formation=self._formations(tracks, float(time_s)))
                formations_s = float(time_s)
            if len(tracks) and len(meas):
                rows, cols, d2, xp, pp, cw = self._gate(tracks, meas)
                chosen = self._assign(tracks, meas, rows, cols, d2)
                r, c = rows[chosen], cols[chosen]
                clear = clarity(rows, cols, d2, chosen)
                nis = d2[chosen][clear >= 1.0]  # (unambiguous ones: clutter in a gate would inflate it)
                tracks = replace(tracks, quality=self._quality(tracks.quality, r, clear))
                if self.params.formation.merge_duplicates:
                    a, b = shared_plot_pairs(rows, cols)
                    twins = tracks.uid[a], tracks.uid[b]
                if r.shape[0]:
                    z, cov_z = meas.enu_m[c], meas.covariance[c]
                    x_new, p_new, xm_new, pm_new, mu_new = imm.update(
                        xp[chosen],
                        pp[chosen],
                        cw[chosen],
                        z,
                        self._update_covariance(tracks, r, clear, cov_z),
                    )
                    saved = (tracks, r, {name: getattr(tracks, name)[r] for name in _WRITTEN})
                    tracks.x[r], tracks.P[r], tracks.t[r] = x_new, p_new, meas.time_s[c]
                    tracks.xm[r], tracks.Pm[r], tracks.mu[r] = xm_new, pm_new, mu_new
                    tracks.nplots[r] += 1
                    self._hold_velocity(tracks, r)
                    tracks.cov_ecef[r] = big @ tracks.P[r] @ big.T
                    hit[r] = True
                    used[c] = True
                    joined.append((tracks.uid[r], plots.take(c)))
                    tracks = self._release_manoeuvring(
                        tracks, r, xp[chosen], pp[chosen], cw[chosen], z, cov_z, float(time_s)
                    )
            tracks, detection = self._life_cycle(tracks, hit, plots.azimuth_deg, float(time_s), scan_s)
            tracks = self._drop_duplicates(tracks, twins, float(time_s))
            window.extend(plots.take(~used), float(time_s), meas.take(~used))
            initiated_s = self._initiated_s
            next_uid = self._next_uid
            if time_s - initiated_s >= self.params.manager.initiation_interval_scans * scan_s:
                tracks, next_uid = self._initiate_from_window(tracks, window, joined, big, site, scan_s)
                initiated_s = float(time_s)
        except BaseException:
            if saved is not None:  # back into the very arrays written
                written, rs, before = saved
                for name, values in before.items():
                    getattr(written, name)[rs] = values
            raise
        # Commit: plain assignments only, after every step that can fail.
        self._tracks, self._window, self.joined, self._next_uid = tracks, window, joined, next_uid
        self._initiated_s = initiated_s
        self._formations_s = formations_s
        self.detection = detection
        self._coincident += coincident
        self._aided += self._aided_batch
        self._ecef_rotation, self._window_site = rotation, site
        self.last_time_s = max(self.last_time_s, float(time_s))
        self.identity.add(joined)
        self.identity.keep(tracks.uid)
        self.revisit.add(meas.enu_m[:, :2], meas.time_s, float(time_s), self.site.scan_period_s)
        self.noise.add(nis, float(time_s))

    def tracks(self) -> TrackTable:
        """The live tracks in ECEF.  Covariances and ids come from the per-track caches (made
        when a track's covariance changes, and at its birth), so a call costs copies of the
        arrays, not a 6x6 product and a string per track."""
        tr = self._tracks
        n = len(tr)
        if n == 0:
            return TrackTable.empty()
        rot = self.site.rotation
        pos = tr.x[:, :3] @ rot.T + self.site.origin_ecef
        vel = tr.x[:, 3:] @ rot.T
        if np.array_equal(rot, self._ecef_rotation):
            cov = tr.cov_ecef.copy()
        else:  # the site was replaced since the last update
            big = _ecef_block(rot)
            cov = big @ tr.P @ big.T
        # The width of the longest id (the highest uid), as a table built from the strings has.
        width = len(self.id_prefix) + 1 + len(str(int(tr.uid.max()) + self._id_offset))
        return TrackTable(
            tr.ids.astype(f"<U{width}"),
            tr.confirmed.copy(),
            tr.t.copy(),
            pos,
            vel,
            cov,
            tr.nplots.copy(),
            **self.identity.of(tr.uid),
            quality=tr.quality.copy(),
        )

    # -- association ------------------------------------------------------------------
    def _gate(
        self, tracks: _Tracks, meas: Measurements
    ) -> tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """Gated candidates ``(track, plot, d^2)`` and each candidate's predicted state by
        filter model, with the models' prior weights (:func:`.imm.predict`); ``d^2`` is taken
        against the models' mixture (:func:`.imm.combine`).

        Only the tracks near the batch's plots (:func:`_near_tracks`: a sector batch of a
        scanning radar covers an eighth of its tracks) are predicted and searched; the others
        cannot have a plot within their pre-gate radius, which is at most
        ``coarse_gate_max_m``.  Every step below works row by row, so the candidates and
        their values are those of the search over all tracks (their order may differ; the
        assignment does not depend on it).

        Memory stays bounded however many plots crowd around the tracks: the tracks go in
        chunks whose candidates within the pre-gate radius are at most
        ``_SEARCH_PAIRS_PER_PREDICTION * gate_block`` (counted on a grid first,
        :func:`.pairs.cell_counts`; plus one track's own), and the per-candidate predictions are
        made ``gate_block`` per model at a time.  Normal batches are one chunk and one block,
        the form used before these bounds.  The pre-gate radius takes the largest of the
        models' process noise, so it holds every model's prediction."""
        fp = self.params.filter
        models = self._models
        tb = float(np.median(meas.time_s))
        near = _near_tracks(tracks, meas.enu_m, tb, fp.coarse_gate_max_m)
        if near is None:
            x, P, t, xm, pm, mu = tracks.x, tracks.P, tracks.t, tracks.xm, tracks.Pm, tracks.mu
        else:
            x, P, t = tracks.x[near], tracks.P[near], tracks.t[near]
            xm, pm, mu = tracks.xm[near], tracks.Pm[near], tracks.mu[near]
        out: list[tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray, FloatArray]] = []
        if x.shape[0]:
            xb, pb = kalman.predict(x, P, tb - t, max(models.psd))
            span = float(np.max(np.abs(meas.time_s - tb)))
            sig_t = np.sqrt(np.trace(pb[:, :3, :3], axis1=1, axis2=2))
            sig_p = float(np.sqrt(np.max(np.trace(meas.covariance, axis1=1, axis2=2))))
            speed = np.linalg.norm(xb[:, 3:], axis=1)
            radius = np.sqrt(fp.gate_chi2) * (sig_t + sig_p) + speed * span
            radius = np.minimum(radius, fp.coarse_gate_max_m)
            gb = max(self.params.bounds.gate_block // models.count, 1)
            grouped = None
            if self._formation_models is not None and bool(np.any(tracks.formation >= 0)):
                formation, free = (
                    (tracks.formation, tracks.free_until)
                    if near is None
                    else (tracks.formation[near], tracks.free_until[near])
                )
                grouped = (formation >= 0) & (free < tb)
            tree_p = cKDTree(meas.enu_m)
            chunks = _track_chunks(
                xb[:, :3], meas.enu_m, float(radius.max()), _SEARCH_PAIRS_PER_PREDICTION * gb
            )
            for chunk in chunks:  # a few
                sdm = cKDTree(xb[chunk, :3]).sparse_distance_matrix(
                    tree_p, float(radius[chunk].max()), output_type="ndarray"
                )
                rows = chunk[sdm["i"].astype(np.intp)]
                cols = sdm["j"].astype(np.intp)
                keep = sdm["v"] <= radius[rows]
                rows, cols = rows[keep], cols[keep]
                for b0 in range(0, rows.shape[0], gb):  # the exact gate, ``gate_block`` at a time
                    r, c = rows[b0 : b0 + gb], cols[b0 : b0 + gb]
                    xp, pp, cw = imm.predict(
                        xm[r],
                        pm[r],
                        mu[r],
                        meas.time_s[c] - t[r],
                        models,
                        self._formation_models,
                        None if grouped is None else grouped[r],
                    )
                    y, S = kalman.innovation(*imm.combine(cw, xp, pp), meas.enu_m[c], meas.covariance[c])
                    d2 = kalman.mahalanobis2(y, S)
                    ok = d2 <= fp.gate_chi2
                    rows_ok = r[ok] if near is None else near[r[ok]]
                    out.append((rows_ok, c[ok], d2[ok], xp[ok], pp[ok], cw[ok]))
        if len(out) == 1:
            return out[0]
        if not out:
            e, m = np.empty(0, dtype=np.intp), models.count
            return e, e, np.empty(0), np.empty((0, m, 6)), np.empty((0, m, 6, 6)), np.empty((0, m))
        r_, c_, d_, x_, p_, w_ = zip(*out, strict=True)
        return (
            np.concatenate(r_),
            np.concatenate(c_),
            np.concatenate(d_),
            np.concatenate(x_),
            np.concatenate(p_),
            np.concatenate(w_),
        )

    def take_aid(self, partners: PartnerReferences | None) -> None:
        self._aid = partners

    def wants_aid(self, time_s: float) -> bool:
        """Only the candidates of a track in a formation are aided (:meth:`_assign`): a batch
        asks if a track is in one, or if the search for formations is due at it (:meth:`update`
        searches before it assigns)."""
        if self._formation_models is None or not len(self._tracks):
            return False
        interval_s = self.params.formation.formation_interval_scans * self.scan_period_s
        return time_s - self._formations_s >= interval_s or bool(np.any(self._tracks.formation >= 0))

    def _assign(
        self, tracks: _Tracks, meas: Measurements, rows: IntArray, cols: IntArray, d2: FloatArray
    ) -> IntArray:
        """The chosen candidates among the gated ones (:func:`.assignment.assign`, a miss
        costing the gate).  A candidate of a track in a formation with a reference
        (:mod:`.aid`) costs its distance from the reference instead, and is none if that is
        beyond the gate.  One method, so that an evaluation can change the costs it solves and
        nothing else (the lab's bounds on association in formations, docs/results.md)."""
        gate = self.params.filter.gate_chi2
        aid = self._aid
        near = np.flatnonzero(tracks.formation[rows] >= 0) if aid is not None else rows[:0]
        if aid is None or not near.shape[0]:
            return assign(rows, cols, d2, gate)
        r, c = rows[near], cols[near]
        ref, ref_cov = aid(tracks.ids[r], meas.time_s[c], horizontal_spread(tracks.P[r]))
        aided = aided_d2(meas.enu_m[c], meas.covariance[c], ref, ref_cov)
        cost = d2.copy()
        cost[near] = np.where(np.isnan(aided), d2[near], aided)
        chosen = assign(rows, cols, cost, gate)
        by_aid = np.zeros(rows.shape[0], dtype=bool)
        by_aid[near] = ~np.isnan(aided)
        self._aided_batch = int(np.count_nonzero(by_aid[chosen]))
        return chosen

    # -- formations --------------------------------------------------------------------
    def _hold_velocity(self, tracks: _Tracks, rows: IntArray) -> None:
        """The tracks ``rows`` (just updated) that fly in a formation: their quiet model takes
        the formation's velocity without them (:func:`.formation.common_velocity`) as a
        measurement of its own, of that mean's variance plus
        ``formation_velocity_sigma_mps^2`` per axis, when within ``formation_velocity_chi2``
        of it.  The manoeuvre model keeps the track's own, so a member that flies otherwise
        shows in its plots' likelihoods and the filter follows that model.  Written in place
        (the caller saved the rows)."""
        fm = self.params.formation
        if self._formation_models is None or fm.formation_velocity_sigma_mps <= 0.0:
            return
        if not bool(np.any(tracks.formation[rows] >= 0)):
            return  # (a batch with no formation member: no mean to take over all the tracks)
        # (a formation that manoeuvres too: its members turn as one, and the release from
        # the formation's quiet model fires by chance in straight flight as well)
        members = np.flatnonzero(tracks.formation >= 0)
        if members.shape[0] < 2:
            return
        # (a member its plots put on the manoeuvre model flies otherwise: it counts little)
        quiet = np.maximum(tracks.mu[members, 0], np.finfo(float).tiny)
        var = 0.5 * (tracks.P[members, 3, 3] + tracks.P[members, 4, 4]) / quiet
        mean, mean_var = common_velocity(tracks.formation[members], tracks.x[members, 3:5], var)
        local = np.full(len(tracks), -1, dtype=np.intp)
        local[members] = np.arange(members.shape[0])
        at = local[rows]
        rows, at = rows[at >= 0], at[at >= 0]
        v, r = mean[at], mean_var[at] + fm.formation_velocity_sigma_mps**2
        quiet_x, quiet_p = tracks.xm[rows, 0], tracks.Pm[rows, 0]
        ok = velocity_gate(quiet_x, quiet_p, v, r) <= fm.formation_velocity_chi2
        rows, v, r = rows[ok], v[ok], r[ok]
        if rows.shape[0] == 0:
            return
        tracks.xm[rows, 0], tracks.Pm[rows, 0] = velocity_update(quiet_x[ok], quiet_p[ok], v, r)
        tracks.x[rows], tracks.P[rows] = imm.combine(tracks.mu[rows], tracks.xm[rows], tracks.Pm[rows])

    def _formations(self, tracks: _Tracks, time_s: float) -> IntArray:
        """Each track's formation at ``time_s`` (:func:`.formation.formation_groups` on the
        states brought to it; -1 for a track with a state not finite)."""
        x = tracks.x
        pos = x[:, :3] + x[:, 3:] * (time_s - tracks.t)[:, None]
        ok = np.flatnonzero(np.isfinite(pos).all(axis=1) & np.isfinite(x[:, 3:]).all(axis=1))
        out = np.full(len(tracks), -1, dtype=np.intp)
        fm = self.params.formation
        out[ok] = formation_groups(
            pos[ok], x[ok, 3:], fm.formation_radius_m, fm.formation_speed_mps, fm.formation_neighbours
        )
        return out

    def _release_manoeuvring(
        self,
        tracks: _Tracks,
        r: IntArray,
        xp: FloatArray,
        pp: FloatArray,
        cw: FloatArray,
        z: FloatArray,
        cov_z: FloatArray,
        time_s: float,
    ) -> _Tracks:
        """The tracks of the formations that manoeuvred in this batch (:func:`.formation.manoeuvring`
        on the innovations of their associated members ``r``: predictions ``xp``, ``pp``, ``cw``,
        plots ``z``, ``cov_z``) on the filter's own models for ``formation_release_s``, their
        model probabilities back to the filter's long-run shares."""
        lab = tracks.formation[r]
        grouped = lab >= 0
        if not grouped.any():
            return tracks
        fm = self.params.formation
        g = np.flatnonzero(grouped)
        y, S = kalman.innovation(*imm.combine(cw[g], xp[g], pp[g]), z[g], cov_z[g])
        moved = manoeuvring(lab[g], y, S, fm.formation_manoeuvre_chi2, fm.formation_manoeuvre_members)
        if moved.size == 0:
            return tracks
        rows = np.flatnonzero(np.isin(tracks.formation, moved))
        free_until, mu = tracks.free_until.copy(), tracks.mu.copy()
        free_until[rows] = time_s + fm.formation_release_s
        mu[rows] = self._models.stationary
        return replace(tracks, free_until=free_until, mu=mu)

    def _update_covariance(
        self, tracks: _Tracks, r: IntArray, clear: FloatArray, cov_z: FloatArray
    ) -> FloatArray:
        """The covariances the assigned plots ``cov_z`` update their tracks ``r`` with: a member
        of a formation's weighed by its association's clarity ``clear``
        (:func:`.assignment.weighted_covariance`, ``update_clarity_floor``), every other's as
        measured.  The gate, the assignment and the formation's manoeuvre test keep the plots'
        own."""
        floor = self.params.formation.update_clarity_floor
        if floor >= 1.0 or self._formation_models is None:
            return cov_z
        grouped = np.flatnonzero((tracks.formation[r] >= 0) & (clear < 1.0))
        if grouped.shape[0] == 0:
            return cov_z
        out = cov_z.copy()
        out[grouped] = weighted_covariance(cov_z[grouped], clear[grouped], floor)
        return out

    def _quality(self, quality: FloatArray, rows: IntArray, clear: FloatArray) -> FloatArray:
        """``Track.quality`` after this batch: each associated track's moves by
        ``1 / quality_memory_looks`` of the way to its association's clarity
        (:func:`.assignment.clarity`); a track's first association sets it."""
        out = quality.copy()
        q = out[rows]
        out[rows] = np.where(np.isnan(q), clear, q + (clear - q) / self.params.formation.quality_memory_looks)
        return out

    def _drop_duplicates(
        self, tracks: _Tracks, twins: tuple[NDArray[np.int64], NDArray[np.int64]], time_s: float
    ) -> _Tracks:
        """``tracks`` without the weaker track of each duplicate pair among ``twins`` (uids of
        tracks whose gates held the same plot in this batch; :mod:`.duplicates`)."""
        if twins[0].shape[0] == 0 or len(tracks) < 2:
            return tracks
        fm = self.params.formation
        n = len(tracks)  # uids ascend with the rows (births append), so a search finds a row
        ia = np.minimum(np.searchsorted(tracks.uid, twins[0]), n - 1)
        ib = np.minimum(np.searchsorted(tracks.uid, twins[1]), n - 1)
        alive = (tracks.uid[ia] == twins[0]) & (tracks.uid[ib] == twins[1])  # not deleted this batch
        lose = duplicate_losers(
            ia[alive],
            ib[alive],
            tracks.x,
            tracks.P,
            tracks.t,
            tracks.hist,
            tracks.looks,
            tracks.nplots,
            time_s,
            self.params.filter.process_noise_psd,
            fm.duplicate_chi2,
            fm.duplicate_looks,
        )
        if lose.shape[0] == 0:
            return tracks
        keep = np.ones(n, dtype=bool)
        keep[lose] = False
        return tracks.take(keep)

    # -- life cycle -------------------------------------------------------------------
    def _expected(self, tracks: _Tracks, azimuth_deg: FloatArray, time_s: float) -> NDArray[np.bool_]:
        """Tracks whose predicted azimuth lies inside the batch's covered arc (less a margin)."""
        arc = covered_arc(np.asarray(azimuth_deg, dtype=float))
        n = len(tracks)
        if arc is None or n == 0:
            return np.zeros(n, dtype=bool)
        start, width = arc
        pos = tracks.x[:, :3] + tracks.x[:, 3:] * (time_s - tracks.t)[:, None]
        az = np.degrees(np.arctan2(pos[:, 0], pos[:, 1]))
        off = np.mod(az - start, 360.0)
        m = self.params.manager.sector_margin_deg
        return np.asarray((off >= m) & (off <= width - m))

    def _life_cycle(
        self,
        tracks: _Tracks,
        hit: NDArray[np.bool_],
        azimuth_deg: FloatArray,
        time_s: float,
        scan_s: float,
    ) -> tuple[_Tracks, DetectionMeter]:
        """Looks, confirmation and deletion (module docstring, step 5), and the detection meter
        after the batch (kept by the caller once the whole batch has succeeded): an established
        confirmed track is deleted after the meter's ``misses_to_delete`` expected misses in a
        row (:mod:`.detection`), any other confirmed track after ``confirmed_max_misses``."""
        mp = self.params.manager
        # (established before this batch: its plot is already in ``nplots``)
        was = tracks.confirmed & (tracks.nplots - hit >= mp.established_plots)
        hits_established = int(np.count_nonzero(hit & was))
        detection = self.detection.added(hits_established, int(np.count_nonzero(was)), time_s, scan_s)
        misses_to_delete = detection.misses_to_delete()
        n_bits = mp.confirm_n
        mask = (1 << n_bits) - 1
        expected = self._expected(tracks, azimuth_deg, time_s) & ~hit
        looked = hit | expected
        hist = np.where(looked, ((tracks.hist << 1) | hit.astype(np.int64)) & _LOOK_MASK, tracks.hist)
        looks = np.where(looked, np.minimum(tracks.looks + 1, _LOOK_BITS), tracks.looks)
        miss_run = np.where(hit, 0, tracks.miss_run + expected)
        hits = popcount(hist & mask)  # the M-of-N's last ``confirm_n`` looks
        confirmed = tracks.confirmed | (hits >= mp.confirm_m)
        tracks = replace(tracks, hist=hist, looks=looks, miss_run=miss_run, confirmed=confirmed)
        misses = np.minimum(looks, n_bits) - hits
        established = confirmed & (tracks.nplots >= mp.established_plots)
        limit = np.where(established, misses_to_delete, mp.confirmed_max_misses)
        dead = (~confirmed & (misses > mp.confirm_n - mp.confirm_m)) | (confirmed & (miss_run >= limit))
        coast = np.where(established, max(mp.coast_scans, misses_to_delete + 0.5), mp.coast_scans)
        dead |= time_s - tracks.t > coast * scan_s
        return (tracks.take(~dead) if dead.any() else tracks), detection

    # -- initiation -------------------------------------------------------------------
    def _initiate_from_window(
        self, tracks: _Tracks, window: PlotWindow, joined: Joined, big: FloatArray, site: Site, scan_s: float
    ) -> tuple[_Tracks, int]:
        """New tentative tracks from ``window`` (whose used plots it removes), their plots
        appended to ``joined``; returns the tracks and the next free uid.  ``big``: the map of
        a covariance to ECEF (:func:`_ecef_block`); ``site`` and ``scan_s``: the site (sigmas)
        and scan period the update measures with."""
        next_uid = self._next_uid
        wplots = window.plots
        if len(wplots) < 3:
            return tracks, next_uid
        p = self.params
        wm = window.measurements
        if wm is None:  # the window's plots all came with theirs (``update``); kept for safety
            wm = plots_to_measurements(site, wplots, p.measurement)
        groups = self._initiate(wm, p, scan_s)
        if groups.count == 0:
            return tracks, next_uid
        births = fit_groups(wm, groups, p.filter.process_noise_psd, p.manager.birth_velocity_sigma_mps)
        ok = births.mean_nis <= p.manager.birth_max_mean_nis
        if not ok.any():
            return tracks, next_uid
        k = int(ok.sum())
        uid = np.arange(next_uid, next_uid + k, dtype=np.int64)
        n_bits = p.manager.confirm_n
        first = np.minimum(births.plots[ok], n_bits).astype(np.int64)
        hist = (np.int64(1) << first) - 1
        xm, pm, mu = imm.born(births.x[ok], births.P[ok], self._models)
        born = _Tracks(
            uid,
            births.x[ok],
            births.P[ok],
            births.time_s[ok],
            hist,
            first,
            np.zeros(k, dtype=np.int64),
            popcount(hist) >= p.manager.confirm_m,
            births.plots[ok],
            np.char.add(f"{self.id_prefix}-", (uid + self._id_offset).astype(str)),
            big @ births.P[ok] @ big.T,
            np.full(k, np.nan),
            xm,
            pm,
            mu,
            np.full(k, -1, dtype=np.intp),
            np.full(k, -np.inf),
        )
        # Plots of accepted groups leave the window; label -> uid of the new track.
        label_uid = np.full(groups.count, -1, dtype=np.int64)
        label_uid[ok] = uid
        in_new = label_uid[groups.group] >= 0
        member = groups.plot[in_new]
        joined.append((label_uid[groups.group][in_new], wplots.take(member)))
        used = np.zeros(len(wplots), dtype=bool)
        used[member] = True
        window.replace(wplots.take(~used), wm.take(~used))
        return tracks.append(born), next_uid + k
