"""Sensor registration: per-radar range, azimuth and elevation bias by least squares.

Model (SVD paper Eq. 2, and the AIS/CFAR paper's registration step): radar ``s`` measures
polar ``(r, theta, phi) + b_s + noise`` with the systematic error ``b_s = (dr, dtheta,
dphi)``; to first order its reported ECEF position is ``y_s = x + G_s b_s`` with
``G_s = R_s J_s`` (``J_s`` the polar Jacobian of Eq. 2 at the measured polar coordinates,
``R_s`` the ENU-to-ECEF rotation of Eq. 1).  A confirmed pair of tracks of radars ``a`` and
``b`` gives ``d = y_a - y_b = G_a b_a - G_b b_b + n``, ``Cov(n) = P_a + P_b``.  All pairs of
all radar pairs are stacked into one weighted least-squares problem in the biases of every
radar (a bias-free reference source such as AIS has ``b = 0``), with a weak Gaussian prior
``b ~ N(0, diag(prior^2))`` (Tikhonov): where the geometry determines a bias component the
data dominate, where it does not (e.g. elevation biases, seen only through nearly equal
vertical offsets ``r_a dphi_a - r_b dphi_b``; or anything when all pairs lie along one line)
the estimate shrinks towards zero -- the minimum-norm answer -- rather than blowing up.  The
posterior covariance ``H^-1`` says which is which (:func:`solve_biases`).  The solve iterates
(Gauss-Newton on the exact model, :func:`remove_bias`), dropping pairs whose residual
chi-square exceeds ``outlier_chi2``.

Uncertainty: the rows of one track pair at successive updates share most of their track errors
(a filtered track is an average over its recent plots), so the textbook covariance ``H^-1``,
which treats every row as independent, is optimistic by about the square root of the updates
per track-error correlation time.  The reported covariance is therefore the cluster-robust
(sandwich) one, ``H^-1 (sum_c s_c s_c^T) H^-1 C/(C-1)``, with ``s_c`` the summed score
``G^T W r`` of all rows of track pair ``c`` (Liang & Zeger 1986; any correlation within a
track pair is allowed, pairs are independent).  With fewer than ``min_clusters`` track pairs
the model covariance ``H^-1`` is used.

With two radars the *differential* effect ``G_a b_a - G_b b_b`` is always well determined
(it is what the data measure), so bias-compensating both radars with the estimate removes
the relative bias even where the split between the radars is prior-driven.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.correlation.base import FloatArray, TrackSnapshot
from service.correlation.linalg import congruence, inv3, matvec3, quad3
from service.geo import Site


@dataclass(frozen=True)
class RegistrationParams:
    """Bias least squares."""

    #: Prior 1-sigma of a range bias (m); weak, only regularises unobservable components.
    prior_range_m: float = 3_000.0
    #: Prior 1-sigma of an azimuth bias (deg).
    prior_azimuth_deg: float = 3.0
    #: Prior 1-sigma of an elevation bias (deg).
    prior_elevation_deg: float = 3.0
    #: Pairs whose residual chi-square (3 dof) exceeds this are dropped as outliers (99.9 %).
    outlier_chi2: float = 16.3
    #: Data time (s) confirmed pairs are remembered for.  Radar biases drift over hours; the
    #: estimate's error falls as the square root of the independent track errors it averages,
    #: so 10 min (measured on the two-radar scenario: range-bias error RMS 6 % at 600 s vs 7 %
    #: at 300 s, elevation 4 % vs 12 %) rather than 5.
    memory_s: float = 600.0
    #: Rows are kept this long beyond ``memory_s`` (s), so that a solve for a moment up to
    #: this long before the newest row still finds every row of its window (the joint solve
    #: runs ``CadenceParams.bias_lag_s`` behind the data clock).
    keep_extra_s: float = 30.0
    #: Cap on remembered pair rows per radar pair (oldest updates dropped first).  Solving only
    #: sums cached per-row pieces, so the whole ``memory_s`` of a busy pair fits (40 pairs every
    #: second for 600 s is 24 000 rows).
    max_rows: int = 40_000
    #: At most this many confirmed pairs (evenly spread) are remembered per update: rows of
    #: one update share the biases, more add little information but cost time.
    max_rows_per_update: int = 300
    #: ... and at most this many per scan of the slower radar once the pair is registered (its
    #: solution in use; a pair updated every few scans takes that many times more).  Every
    #: solve costs in proportion to the remembered rows (a re-solve of a busy pair with 300
    #: rows per update was 40-80 ms); the pick's phase advances each update, so successive
    #: updates take different track pairs, and the memory still holds every confirmed pair
    #: several times over (1 000 pairs, 4 s updates, 600 s: each about 4 times at 30 rows).
    #: A row costs about 700 bytes (its cached normal-equation pieces): a national network of
    #: 66 radar pairs holds some 250 MB of rows at 30 per update, 800 MB at 100.
    registered_rows_per_update: int = 30
    #: Minimum confirmed pairs before a correlator uses its registration.
    min_pairs: int = 6
    #: A :class:`~service.correlation.PairCorrelator` re-solves its own two-radar registration
    #: at most once per this much *data* time once it is registered (before that, on every
    #: update).  Radar biases drift over hours; the memory holds ``memory_s`` of rows, so a
    #: re-solve every minute adds a sixth of the memory's information each time, and a network
    #: of 66 radar pairs spends about 5 ms per data second on it (measured on the national
    #: scenario: 30 ms at 10 s).  The schedule depends on data time only (deterministic).
    solve_interval_s: float = 60.0
    #: ... and sooner, once the pair's confirmed pairs have grown this many times since its
    #: last solve (a first registration rests on the few pairs confirmed by then).
    resolve_growth: float = 4.0
    #: Fewest distinct track pairs for the cluster-robust covariance; below it, ``H^-1``.
    min_clusters: int = 10
    #: Most Gauss-Newton iterations of a solve: the estimate converges on the current rows
    #: (2-3 steps), then the outlier test re-selects the rows, and again until nothing changes
    #: or ``outlier_rounds`` re-selections were made.
    max_iterations: int = 12
    #: Re-selections of the rows by the outlier test at most (a set that keeps changing is
    #: left as it is after this many).
    outlier_rounds: int = 3
    #: Converged: no bias moved by more than this fraction of its (model) 1-sigma in a step.
    converged_sigma: float = 0.01


@dataclass(frozen=True)
class RadarBias:
    """One radar's estimated systematic errors (``GET /biases``).

    ``pairs_used``: confirmed pairs (over all radar pairs involving this radar) of the latest
    update that entered the least squares; earlier remembered updates are used as well.  The
    ``*_sigma_*`` are the 1-sigma of each bias (:meth:`BiasSolution.std`, cluster-robust once
    enough track pairs entered).
    """

    radar_id: str
    range_bias_m: float
    azimuth_bias_deg: float
    elevation_bias_deg: float
    pairs_used: int
    time_s: float
    range_bias_sigma_m: float
    azimuth_bias_sigma_deg: float
    elevation_bias_sigma_deg: float


@dataclass(frozen=True)
class BiasSolution:
    """Joint solution: biases ``(n_radars, 3)`` in (m, rad, rad), their covariance, rows used.

    ``covariance``: cluster-robust when at least ``min_clusters`` track pairs entered (else the
    model covariance); ``model_covariance``: ``H^-1`` (rows treated as independent).
    """

    radar_ids: tuple[str, ...]
    bias: FloatArray
    covariance: FloatArray  # (3 n, 3 n)
    pairs_used: dict[str, int]
    model_covariance: FloatArray | None = None
    clusters: int = 0

    def std(self) -> FloatArray:
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None)).reshape(-1, 3)

    def of(self, radar_id: str | None) -> tuple[FloatArray, FloatArray]:
        """Bias vector and its 3x3 covariance for one radar (zeros for unknown / reference)."""
        if radar_id is None or radar_id not in self.radar_ids:
            return np.zeros(3), np.zeros((3, 3))
        k = self.radar_ids.index(radar_id)
        return self.bias[k], self.covariance[3 * k : 3 * k + 3, 3 * k : 3 * k + 3]


def bias_jacobian(site: Site, position: FloatArray) -> FloatArray:
    """``G = R J`` of each ECEF position (n, 3) for that site's polar biases, ``(n, 3, 3)``."""
    j = polar_jacobian_enu(site.ecef_to_enu(position))
    # R J_k for every k as one 2-D product: (J_k^T R^T)^T.
    return np.swapaxes((np.swapaxes(j, 1, 2).reshape(-1, 3) @ site.rotation.T).reshape(j.shape), 1, 2)


def polar_jacobian_enu(enu: FloatArray) -> FloatArray:
    """:func:`service.geo.polar_jacobian` (the ``J`` of Eq. 2) from ENU points ``(n, 3)``, without
    trigonometry: with ``h`` the horizontal and ``r`` the slant range, ``sin(az) = e / h``,
    ``cos(az) = n / h``, ``cos(el) = h / r``, ``sin(el) = u / r``, so
    ``J = [[e/r, n, -u e/h], [n/r, -e, -u n/h], [u/r, 0, h]]`` (straight above the site,
    ``h = 0``, the azimuth is taken as 0 as ``arctan2(0, 0)`` does)."""
    e, n, u = enu[:, 0], enu[:, 1], enu[:, 2]
    h = np.hypot(e, n)
    r = np.hypot(h, u)
    above = h <= 0
    sa = np.divide(e, h, out=np.zeros_like(h), where=~above)
    ca = np.divide(n, h, out=np.ones_like(h), where=~above)
    rs = np.where(r > 0, r, 1.0)
    jac = np.empty((enu.shape[0], 3, 3))
    jac[:, 0, 0] = h / rs * sa
    jac[:, 0, 1] = h * ca
    jac[:, 0, 2] = -u * sa
    jac[:, 1, 0] = h / rs * ca
    jac[:, 1, 1] = -h * sa
    jac[:, 1, 2] = -u * ca
    jac[:, 2, 0] = u / rs
    jac[:, 2, 1] = 0.0
    jac[:, 2, 2] = h
    return jac


_SHAPES: dict[str, tuple[int, ...]] = {
    "time": (),
    "pair": (),
    "p_a": (3,),
    "p_b": (3,),
    "g_a": (3, 3),
    "g_b": (3, 3),
    "s": (3, 3),
    "w": (3, 3),
    "w_ok": (),
    "gaw": (3, 3),
    "gbw": (3, 3),
    "haa": (3, 3),
    "hab": (3, 3),
    "hbb": (3, 3),
}


_DTYPES: dict[str, type] = {"w_ok": bool, "pair": str}


@dataclass(frozen=True)
class RegistrationRowsData:
    """The defining columns of the rows one update added to a :class:`RegistrationMemory`."""

    time_s: float
    track_a: np.ndarray
    track_b: np.ndarray
    p_a: np.ndarray  # (k, 3) raw ECEF of the A side
    p_b: np.ndarray  # (k, 3)
    s: np.ndarray  # (k, 3, 3) sum of the two position covariances

    def __len__(self) -> int:
        return int(self.p_a.shape[0])


class RegistrationMemory:
    """Recent confirmed-pair rows of one radar pair (raw, uncompensated positions).

    Rows are kept in one buffer per column, the rows of each update appended at its end and
    whole updates leaving from its front (older than ``memory_s`` or beyond ``max_rows``);
    a column reads as a view of its live rows, so a solve copies nothing (the buffer is
    compacted, at amortised constant cost per row, only when its end is reached).  Each row carries
    its normal-equation pieces, computed once when it is added: the weight ``W = S^-1`` and
    its rank flag ``w_ok``, ``gaw = G_a^T W``, ``gbw = G_b^T W`` (a row's score is ``gaw r``,
    ``-gbw r``), ``haa = G_a^T W G_a``, ``hab = G_a^T W G_b``, ``hbb = G_b^T W G_b``; a solve
    sums the pieces of the rows it keeps.  The columns
    (``time``, ``p_a``, ``p_b`` the raw ECEF positions, ``g_a``, ``g_b``, ``s``, ``w``, ...) read as
    concatenated arrays; ``d = p_a - p_b``.
    """

    def __init__(self, site_a: Site, site_b: Site | None) -> None:
        self.site_a = site_a
        self.site_b = site_b
        self._buf: dict[str, np.ndarray] = {}
        self._start = 0  # live rows are [_start, _end) of every column buffer
        self._end = 0
        self._updates: list[tuple[float, int]] = []  # (time, rows) of each remembered update
        self._adds = 0

    def _column(self, name: str) -> np.ndarray:
        """One column's live rows (a view: valid until the next :meth:`add`)."""
        if not self._buf:
            return np.empty((0, *_SHAPES[name]), dtype=_DTYPES.get(name, float))
        return self._buf[name][self._start : self._end]

    def __len__(self) -> int:
        return self._end - self._start

    def _append(self, rows: dict[str, np.ndarray]) -> None:
        k = rows["time"].shape[0]
        live = self._end - self._start
        cap = self._buf["time"].shape[0] if self._buf else 0
        wider = bool(self._buf) and rows["pair"].dtype.itemsize > self._buf["pair"].dtype.itemsize
        if self._end + k > cap or wider:
            # Compact the live rows to the front of fresh buffers (twice what is needed, so
            # this happens once per as many appended rows as are live).
            new_cap = max(cap, 2 * (live + k), 1024)
            buf = {}
            for name, col in rows.items():
                dtype = col.dtype
                if name in self._buf and self._buf[name].dtype.itemsize > dtype.itemsize:
                    dtype = self._buf[name].dtype
                out = np.empty((new_cap, *col.shape[1:]), dtype=dtype)
                if live:
                    out[:live] = self._buf[name][self._start : self._end]
                buf[name] = out
            self._buf, self._start, self._end = buf, 0, live
        for name, col in rows.items():
            self._buf[name][self._end : self._end + k] = col
        self._end += k

    time = property(lambda self: self._column("time"))
    pair = property(lambda self: self._column("pair"))
    p_a = property(lambda self: self._column("p_a"))
    p_b = property(lambda self: self._column("p_b"))
    g_a = property(lambda self: self._column("g_a"))
    g_b = property(lambda self: self._column("g_b"))
    d = property(lambda self: self.p_a - self.p_b)
    s = property(lambda self: self._column("s"))
    w = property(lambda self: self._column("w"))
    w_ok = property(lambda self: self._column("w_ok"))
    gaw = property(lambda self: self._column("gaw"))
    gbw = property(lambda self: self._column("gbw"))
    haa = property(lambda self: self._column("haa"))
    hab = property(lambda self: self._column("hab"))
    hbb = property(lambda self: self._column("hbb"))

    def add(
        self,
        time_s: float,
        a: TrackSnapshot,
        b: TrackSnapshot,
        ia: np.ndarray,
        ib: np.ndarray,
        params: RegistrationParams,
        max_rows: int | None = None,
    ) -> RegistrationRowsData:
        """Remember the pairs ``(ia[k], ib[k])`` of one update; at most ``max_rows`` of them
        (default ``params.max_rows_per_update``), evenly spread over the given order.  Returns
        the rows' defining columns (:meth:`add_rows`)."""
        cap = params.max_rows_per_update if max_rows is None else max_rows
        if len(ia) > cap:
            # One pick per stride of len/cap pairs, at a phase that advances by the golden
            # ratio of a stride each update: over successive updates every pair is taken in
            # turn rather than the same ``cap`` ones (more independent track errors per row).
            stride = len(ia) / cap
            phase = (self._adds * 0.6180339887498949) % 1.0
            pick = np.minimum(((np.arange(cap) + phase) * stride).astype(np.intp), len(ia) - 1)
            ia, ib = ia[pick], ib[pick]
        self._adds += 1
        id_a, id_b = np.asarray(a.track_id[ia], dtype=str), np.asarray(b.track_id[ib], dtype=str)
        return self.add_rows(
            time_s, id_a, id_b, a.position[ia], b.position[ib], a.pos_cov[ia] + b.pos_cov[ib], params
        )

    def add_rows(
        self,
        time_s: float,
        track_a: np.ndarray,
        track_b: np.ndarray,
        p_a: np.ndarray,
        p_b: np.ndarray,
        s: np.ndarray,
        params: RegistrationParams,
        prune: bool = True,
    ) -> RegistrationRowsData:
        """Remember the rows of one update given by what defines them (the pairs' track ids,
        raw ECEF positions and the sum ``s`` of their position covariances); every other
        column is derived here.  Returns those defining columns: another process that adds
        the same rows in the same order holds the same memory (partitioned workers)."""
        pair = np.char.add(np.char.add(track_a, "\x1f"), track_b)
        self._append({"time": np.full(len(p_a), float(time_s)), **self._rows_of(pair, p_a, p_b, s)})
        self._updates.append((float(time_s), len(p_a)))
        if prune:
            self.prune(time_s, params)
        return RegistrationRowsData(float(time_s), track_a, track_b, p_a, p_b, s)

    def _rows_of(
        self, pair: np.ndarray, p_a: np.ndarray, p_b: np.ndarray, s: np.ndarray
    ) -> dict[str, np.ndarray]:
        """Every column of rows but ``time``: the defining ones and the pieces derived here."""
        ga = bias_jacobian(self.site_a, p_a)
        gb = bias_jacobian(self.site_b, p_b) if self.site_b is not None else np.zeros((len(p_b), 3, 3))
        w, w_ok = inv3(s)
        gat_w = np.swapaxes(ga, 1, 2) @ w
        gbt_w = np.swapaxes(gb, 1, 2) @ w
        return {
            "pair": pair,
            "p_a": p_a,
            "p_b": p_b,
            "g_a": ga,
            "g_b": gb,
            "s": s,
            "w": w,
            "w_ok": w_ok,
            "gaw": gat_w,
            "gbw": gbt_w,
            "haa": gat_w @ ga,
            "hab": gat_w @ gb,
            "hbb": gbt_w @ gb,
        }

    # -- kept across a restart (service.state) ------------------------------------------------
    def export(self) -> dict[str, Any]:
        """What defines the memory (the other columns are derived again by :meth:`restored`):
        the live rows' ``time``, ``pair``, ``p_a``, ``p_b`` and ``s``, each remembered update's
        time and row count, and the updates taken (the phase of the rows' pick).

        Bounded as the memory is: at most ``max_rows`` rows plus one update's (``max_rows`` +
        ``max_rows_per_update``), about 130 bytes a row plus 4 bytes per character of the two
        track ids.  The columns are views, not copies: the live rows of a buffer are never
        written again (rows are appended past them, pruning moves the start, compaction makes
        new buffers), so the export stays as it was while the memory goes on."""
        return {
            "time": self.time,
            "pair": self.pair,
            "p_a": self.p_a,
            "p_b": self.p_b,
            "s": self.s,
            "update_time": np.array([t for t, _ in self._updates], dtype=float),
            "update_rows": np.array([k for _, k in self._updates], dtype=np.int64),
            "adds": self._adds,
        }

    @classmethod
    def restored(cls, site_a: Site, site_b: Site | None, state: Mapping[str, Any]) -> RegistrationMemory:
        """The memory :meth:`export` gave, its derived columns made again from ``site_a`` and
        ``site_b`` (the sites it was measured from).  ``ValueError`` if the columns disagree."""
        time = np.asarray(state["time"], dtype=float)
        n = time.shape[0]
        cols = {
            "pair": np.asarray(state["pair"], dtype=str),
            "p_a": np.asarray(state["p_a"], dtype=float),
            "p_b": np.asarray(state["p_b"], dtype=float),
            "s": np.asarray(state["s"], dtype=float),
        }
        update_time = np.asarray(state["update_time"], dtype=float)
        update_rows = np.asarray(state["update_rows"], dtype=np.int64)
        for name, col in cols.items():
            if col.shape != (n, *_SHAPES[name]):
                raise ValueError(f"registration memory column {name} of shape {col.shape}, {n} rows")
        if update_time.shape != update_rows.shape or int(update_rows.sum()) != n or (update_rows < 0).any():
            raise ValueError(f"registration memory updates of {update_rows.sum()} rows, {n} rows")
        memory = cls(site_a, site_b)
        if n:
            memory._append(
                {"time": time, **memory._rows_of(cols["pair"], cols["p_a"], cols["p_b"], cols["s"])}
            )
        memory._updates = list(zip(update_time.tolist(), update_rows.tolist(), strict=True))
        memory._adds = int(state["adds"])
        return memory

    def prune(self, time_s: float, params: RegistrationParams) -> None:
        """Forget whole updates from the front: older than the memory before ``time_s`` (and
        ``keep_extra_s``), or beyond the row cap.  (A solve also leaves out rows outside its
        own window, should data time step back.)  A mirror of another worker's pair prunes
        for the time it solves at, not for its newest rows, which may be far ahead of it."""
        while self._updates and (
            self._updates[0][0] < time_s - params.memory_s - params.keep_extra_s
            or (len(self._updates) > 1 and len(self) > params.max_rows)
        ):
            self._start += self._updates.pop(0)[1]

    def current(self, time_s: float) -> np.ndarray:
        """Mask of rows within memory (data time) of ``time_s``."""
        return np.asarray(self.time <= time_s)


def _rows(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``x[mask]`` without a copy when every row is selected (the usual case)."""
    return x if mask.all() else x[mask]


def solve_biases(
    memories: Sequence[RegistrationMemory],
    time_s: float,
    params: RegistrationParams | None = None,
    initial: BiasSolution | None = None,
) -> BiasSolution | None:
    """Joint robust weighted least squares over all memories; None when there are no rows.

    ``initial``: a previous solution to start from (a warm start; radars it lacks start at
    zero).  Its rows are then first selected by the outlier test at that estimate, so a solve
    whose rows changed little since converges in one or two Gauss-Newton steps instead of
    first converging on every row, outliers included, from zero (5-8 steps).  The fixed point
    is the same: the estimate is converged on a row set the outlier test leaves unchanged.
    """
    prm = params or RegistrationParams()
    # Only memories with rows in the window take part: the radars solved for are those the
    # window's rows observe, whatever else a memory holds (older, or newer than ``time_s``).
    rows = [(m, m.current(time_s) & (m.time >= time_s - prm.memory_s)) for m in memories]
    rows = [(m, r) for m, r in rows if r.any()]
    if not rows:
        return None
    ids = sorted({m.site_a.site_id for m, _ in rows} | {m.site_b.site_id for m, _ in rows if m.site_b})
    col = {rid: k for k, rid in enumerate(ids)}
    n = 3 * len(ids)
    prior = np.tile(
        [
            1.0 / prm.prior_range_m**2,
            1.0 / np.radians(prm.prior_azimuth_deg) ** 2,
            1.0 / np.radians(prm.prior_elevation_deg) ** 2,
        ],
        len(ids),
    )
    # Each memory's rows in force, read once.  Gauss-Newton on the exact model: the residual
    # of a row at the current estimate is the difference of the two positions with their biases
    # removed exactly (:func:`remove_bias`); the normal matrix is the cached one at the
    # measured positions.  The linear model alone is off by ``r dtheta^2 / 2`` radially (4 m at
    # 100 km and 0.5 deg, 60 m at 2 deg), which leaks into the weakly observable common range
    # bias; the fixed point of this iteration is the exact model's solution.
    data = [
        (
            m,
            r,
            {
                c: _rows(getattr(m, c), r)
                for c in ("pair", "p_a", "p_b", "w", "w_ok", "gaw", "gbw", "haa", "hab", "hbb")
            },
        )
        for m, r in rows
    ]
    bias = np.zeros(n)
    if initial is not None:
        for rid, k in col.items():
            if rid in initial.radar_ids:
                bias[3 * k : 3 * k + 3] = initial.bias[initial.radar_ids.index(rid)]
    if initial is not None and np.any(bias != 0.0):
        residuals = [_residual(m, cols, bias, col) for m, _, cols in data]
        keep = [
            cols["w_ok"] & (quad3(res, cols["w"]) <= prm.outlier_chi2)
            for (_, _, cols), res in zip(data, residuals, strict=True)
        ]
    else:
        residuals = [cols["p_a"] - cols["p_b"] for _, _, cols in data]
        keep = [cols["w_ok"].copy() for _, _, cols in data]
    fit_keep = keep
    cov = np.diag(1.0 / prior)
    rounds = 0
    for _ in range(prm.max_iterations):
        fit_keep = keep
        h = np.diag(prior)
        g = -prior * bias
        for (m, _, cols), kp, res in zip(data, keep, residuals, strict=True):
            kf = kp.astype(float)
            nr = kf.shape[0]
            ka = 3 * col[m.site_a.site_id]
            h[ka : ka + 3, ka : ka + 3] += (kf @ cols["haa"].reshape(nr, 9)).reshape(3, 3)
            if m.site_b is not None:
                kb = 3 * col[m.site_b.site_id]
                cross = (kf @ cols["hab"].reshape(nr, 9)).reshape(3, 3)
                h[ka : ka + 3, kb : kb + 3] -= cross
                h[kb : kb + 3, ka : ka + 3] -= cross.T
                h[kb : kb + 3, kb : kb + 3] += (kf @ cols["hbb"].reshape(nr, 9)).reshape(3, 3)
            np.add.at(g, _columns(m, col), kf @ _scores(m, cols, res))
        cov = np.linalg.inv(h)
        step = cov @ g
        bias = bias + step
        residuals = [_residual(m, cols, bias, col) for m, _, cols in data]
        if np.any(np.abs(step) > prm.converged_sigma * np.sqrt(np.diag(cov))):
            continue  # converge on this set of rows first: a far-off estimate flags good rows
        if rounds == prm.outlier_rounds:
            break
        rounds += 1
        new_keep = [
            cols["w_ok"] & (quad3(res, cols["w"]) <= prm.outlier_chi2)
            for (_, _, cols), res in zip(data, residuals, strict=True)
        ]
        if all(np.array_equal(a, b) for a, b in zip(new_keep, keep, strict=True)):
            break
        keep = new_keep
    robust, clusters = _robust_covariance(data, fit_keep, residuals, col, cov, prior, prm.min_clusters)
    # pairs_used: confirmed pairs of the latest remembered update that survived the outlier
    # test (the LS itself uses every remembered update's rows).
    used: dict[str, int] = dict.fromkeys(ids, 0)
    for (m, r, _), kp in zip(data, keep, strict=True):
        t = m.time[r]
        n_latest = int((kp & (t == t.max())).sum()) if t.size else 0
        used[m.site_a.site_id] += n_latest
        if m.site_b is not None:
            used[m.site_b.site_id] += n_latest
    return BiasSolution(tuple(ids), bias.reshape(-1, 3), robust, used, cov, clusters)


def remove_bias(site: Site, position: FloatArray, bias: FloatArray) -> FloatArray:
    """The exact inverse of the bias model (Eq. 2): the ECEF positions ``(n, 3)`` the radar at
    ``site`` would report without its bias ``(dr, dtheta, dphi)`` in (m, rad, rad).

    Equal to ``polar_to_ecef(r - dr, theta - dtheta, phi - dphi)`` of the position's polar
    coordinates, computed without per-point trigonometry: in the site's ENU frame the
    horizontal part turns by ``dtheta`` about the vertical (azimuth clockwise from north), the
    point turns by ``-dphi`` in its vertical plane, and the range scales by ``(r - dr) / r``.
    """
    return site.enu_to_ecef(_remove_bias_enu(site.ecef_to_enu(position), bias))


def _remove_bias_enu(enu: FloatArray, bias: FloatArray) -> FloatArray:
    """:func:`remove_bias` in the site's ENU frame (points in, points out)."""
    ct, st = np.cos(bias[1]), np.sin(bias[1])
    cp, sp = np.cos(bias[2]), np.sin(bias[2])
    e = enu[:, 0] * ct - enu[:, 1] * st
    n = enu[:, 1] * ct + enu[:, 0] * st
    u = enu[:, 2]
    h = np.hypot(e, n)
    r = np.hypot(h, u)
    h1 = h * cp + u * sp
    u1 = u * cp - h * sp
    scale = (r - bias[0]) / np.where(r > 0, r, 1.0)
    ratio = np.divide(h1, h, out=np.ones_like(h), where=h > 0) * scale
    return np.stack([e * ratio, n * ratio, u1 * scale], axis=1)


def _residual(
    m: RegistrationMemory, cols: dict[str, np.ndarray], bias: FloatArray, col: dict[str, int]
) -> FloatArray:
    """Each row's exact residual: A's position minus B's, both with the estimated bias removed."""
    ka = 3 * col[m.site_a.site_id]
    pa = remove_bias(m.site_a, cols["p_a"], bias[ka : ka + 3])
    if m.site_b is None:
        return pa - cols["p_b"]
    kb = 3 * col[m.site_b.site_id]
    return pa - remove_bias(m.site_b, cols["p_b"], bias[kb : kb + 3])


def _scores(m: RegistrationMemory, cols: dict[str, np.ndarray], res: FloatArray) -> FloatArray:
    """Each row's score in its own two radars' columns ``(rows, 6)``: ``G_a^T W r`` for A and
    ``-G_b^T W r`` for B (the negative half-gradient of the row's ``r^T W r`` in the biases;
    B's half is zero for a reference source)."""
    sc = np.zeros((res.shape[0], 6))
    sc[:, :3] = matvec3(cols["gaw"], res)
    if m.site_b is not None:
        sc[:, 3:] = -matvec3(cols["gbw"], res)
    return sc


def _columns(m: RegistrationMemory, col: dict[str, int]) -> NDArray[np.intp]:
    """The six columns of the joint problem a memory's row scores fall in (B's: A's again for
    a reference source, whose half of the score is zero)."""
    ka = 3 * col[m.site_a.site_id]
    kb = 3 * col[m.site_b.site_id] if m.site_b is not None else ka
    return np.r_[ka : ka + 3, kb : kb + 3].astype(np.intp)


def _robust_covariance(
    data: list[tuple[RegistrationMemory, np.ndarray, dict[str, np.ndarray]]],
    keep: list[np.ndarray],
    residuals: list[FloatArray],
    col: dict[str, int],
    cov: FloatArray,
    prior: FloatArray,
    min_clusters: int,
) -> tuple[FloatArray, int]:
    """Cluster-robust covariance of the biases (module docstring), and the number of clusters.

    ``residuals``: every row's exact residual at the solution (:func:`_residual`), ``keep``: the
    rows that solution was fitted to.  The prior is one more independent term, so components the
    data do not determine keep their prior variance.
    """
    if len(residuals) != len(data):
        return cov, 0
    # Clusters (track pairs) never span two memories, so the meat is a sum of one 6x6 block per
    # memory: the outer products of its clusters' summed scores, in its two radars' columns.
    meat = np.diag(prior)
    c = 0
    blocks = []
    for (m, _, cols), kp, res in zip(data, keep, residuals, strict=True):
        idx = np.flatnonzero(kp)
        if idx.size == 0:
            continue
        sc = _scores(m, cols, res)[idx]
        _, inv = np.unique(cols["pair"][idx], return_inverse=True)  # track pairs of this memory
        k = int(inv.max()) + 1
        summed = np.stack([np.bincount(inv.ravel(), weights=sc[:, j], minlength=k) for j in range(6)], axis=1)
        blocks.append((_columns(m, col), summed.T @ summed))
        c += k
    if c < max(min_clusters, 2):
        return cov, c
    for where, block in blocks:
        np.add.at(meat, np.ix_(where, where), block * (c / (c - 1)))
    return cov @ meat @ cov, c


def compensate(
    snapshot: TrackSnapshot, bias: FloatArray, bias_cov: FloatArray
) -> tuple[TrackSnapshot, FloatArray]:
    """Remove an estimated bias from a radar snapshot; also the per-track covariance it adds.

    Positions: the bias removed exactly (:func:`remove_bias`; to first order ``y - G b``).
    Velocities: an azimuth bias rotates the radar's whole picture,
    so ENU velocities are rotated back by ``-dtheta`` (clockwise azimuth convention).
    """
    if snapshot.site is None or len(snapshot) == 0:
        return snapshot, np.zeros((len(snapshot), 3, 3))
    site = snapshot.site
    # The snapshot's own ENU states (those of its positions) give the Jacobian and the removal.
    j = polar_jacobian_enu(snapshot.enu)
    enu = _remove_bias_enu(snapshot.enu, bias)
    dth = -bias[1]
    c, s = np.cos(dth), np.sin(dth)
    ev = snapshot.enu_velocity
    enu_v = np.stack([ev[:, 0] * c + ev[:, 1] * s, -ev[:, 0] * s + ev[:, 1] * c, ev[:, 2]], axis=1)
    # G C G^T = R (J C J^T) R^T: J C as one 2-D product, R (.) R^T as a congruence.
    jc = (j.reshape(-1, 3) @ bias_cov).reshape(j.shape)
    extra = congruence(site.rotation, jc @ np.swapaxes(j, 1, 2))
    out = TrackSnapshot(
        track_id=snapshot.track_id,
        position=site.enu_to_ecef(enu),
        velocity=enu_v @ site.rotation.T,
        pos_cov=snapshot.pos_cov,
        vel_cov=snapshot.vel_cov,
        site=site,
        enu=enu,
        enu_velocity=enu_v,
        compensated=True,
        mode_s=snapshot.mode_s,
    )
    return out, extra


def solution_state(solution: BiasSolution) -> dict[str, Any]:
    """A joint solution as plain values and arrays, every field (service.state keeps it)."""
    return {f.name: getattr(solution, f.name) for f in fields(BiasSolution)}


def solution_from_state(state: Mapping[str, Any]) -> BiasSolution:
    """The solution :func:`solution_state` gave; ``ValueError`` if its arrays disagree."""
    sol = BiasSolution(
        **{
            **state,
            "radar_ids": tuple(str(r) for r in state["radar_ids"]),
            "bias": np.asarray(state["bias"], dtype=float),
            "covariance": np.asarray(state["covariance"], dtype=float),
            "pairs_used": {str(k): int(v) for k, v in state["pairs_used"].items()},
            "model_covariance": (
                None
                if state.get("model_covariance") is None
                else np.asarray(state["model_covariance"], float)
            ),
        }
    )
    n = len(sol.radar_ids)
    if (
        sol.bias.shape != (n, 3)
        or sol.covariance.shape != (3 * n, 3 * n)
        or set(sol.pairs_used) != set(sol.radar_ids)
    ):
        raise ValueError(f"bias solution of {n} radars with biases of shape {sol.bias.shape}")
    return sol


def to_estimates(solution: BiasSolution | None, time_s: float) -> list[RadarBias]:
    if solution is None:
        return []
    std = solution.std()
    return [
        RadarBias(
            radar_id=rid,
            range_bias_m=float(solution.bias[k, 0]),
            azimuth_bias_deg=float(np.degrees(solution.bias[k, 1])),
            elevation_bias_deg=float(np.degrees(solution.bias[k, 2])),
            pairs_used=int(solution.pairs_used[rid]),
            time_s=float(time_s),
            range_bias_sigma_m=float(std[k, 0]),
            azimuth_bias_sigma_deg=float(np.degrees(std[k, 1])),
            elevation_bias_sigma_deg=float(np.degrees(std[k, 2])),
        )
        for k, rid in enumerate(solution.radar_ids)
    ]
