"""Sensor registration: per-radar range offset and gain, azimuth and elevation offsets and
time-stamp bias, by least squares.

Model (SVD paper Eq. 2, and the AIS/CFAR paper's registration step), per radar ``s`` five terms
``b_s = (dr, dtheta, dphi, g, tau)``: the radar reports a target at true polar position
``(r, theta, phi)`` at true time ``T`` as

    r_m = r (1 + g 1e-6) + dr,   theta_m = theta + dtheta,   phi_m = phi + dphi,   t_m = T + tau

(range offset ``dr`` in m, range gain ``g`` in ppm, angle offsets in rad, time-stamp bias ``tau``
in s: the radar's clock is ``tau`` ahead of true time).  A track built from such plots, read at
*reported* time ``t``, shows the target where it truly was at ``t - tau``: with ``x(t)`` the
true ECEF position and ``v`` its velocity, ``x(t - tau) = x(t) - tau v`` to first order (exact
for straight flight, which a track's constant-velocity state assumes anyway).  Its reported
ECEF position is therefore, to first order in the biases,

    y_s(t) = x(t) + G_s b_s,      G_s = [ R_s J_s | 1e-6 (y_s - L_s) | -v ]          (*)

with ``J_s`` the polar Jacobian of Eq. 2 at the measured polar coordinates and ``R_s`` the
ENU-to-ECEF rotation of Eq. 1 (columns ``dr, dtheta, dphi``); the gain column is the line of
sight scaled by the range, ``dr/dg = r 1e-6`` along ``u = (y - L) / r`` (Eq. 1's ``L`` the
site); the time column is ``-v`` (the report lags the target by ``tau``).  A confirmed pair of
tracks of radars ``a`` and ``b`` at one common (reported) time gives

    d = y_a - y_b = G_a b_a - G_b b_b + n,      Cov(n) = P_a + P_b,

and every row's ``v`` is the mean of its two tracks' velocities (the same aircraft), so a time
bias *common* to ``a`` and ``b`` cancels exactly: ``-v tau_a + v tau_b``.  A row of a radar with
a reference takes the *reference's* velocity: a radar track's velocity error is correlated with
its own position error (the filter pulls both towards each plot, and the prediction to the
row's time adds ``dt`` times it), so a column made of it correlates with the row's noise,
``E[v^T W d] = -tau v^T W v + tr(W Cov(e_a, dv_a)) / 2``, and biases the time bias by about
``-tr(W Cov(e, dv)) / (2 v^T W v)``: -0.04 s for every radar of the three-radar study
(docs/registration.md), 4-6 sigma.  The reference's velocity (GNSS positions over a baseline)
is independent of the radar's errors.  Between two radars that term enters only as the
difference of the two radars' (each radar's own against the other's), and cancels for radars
of alike track quality.  All pairs of all
radar pairs are stacked into one weighted least-squares problem in the terms of every radar
(a bias-free reference source such as ADS-B or AIS has ``b = 0``: its rows fix the terms of
its radar absolutely), with a weak Gaussian prior ``b ~ N(0, diag(prior^2))`` (Tikhonov;
:class:`RegistrationParams` ``prior_*``): where the geometry determines a term the data
dominate, where it does not the estimate shrinks towards zero -- the minimum-norm answer --
rather than blowing up.  The posterior covariance ``H^-1`` says which is which
(:func:`solve_biases`).  The solve iterates (Gauss-Newton on the exact model,
:func:`remove_bias`), dropping pairs whose residual chi-square exceeds ``outlier_chi2``.

Observability (what the rows can tell):

* range offset vs gain: a pair at range ``r`` sees ``dr + g r 1e-6`` along the line of sight;
  rows spread in range separate the two (a gain of 1 000 ppm is 100 m at 100 km, 300 m at
  300 km);
* time bias vs angles: ``-v tau`` lies along each aircraft's track, an azimuth offset across
  the line of sight; aircraft on crossing headings and at different speeds separate them.
  Only *differences* ``tau_a - tau_b`` are seen between radars: a time bias common to every
  radar of a network without a reference moves every track alike and is not observable at
  all -- its estimate stays at the prior's zero and its sigma at the prior's.  Compensation
  therefore uses the covariance *conditioned on that common mode* (each radar's time bias
  relative to the network's mean clock, :attr:`BiasSolution.relative_covariance`), while
  ``/biases`` reports the honest marginal sigma.  A reference (ADS-B) fixes it absolutely.
* a lone radar with no reference and no partner sees nothing (it has no rows); with a
  reference it determines all five terms where the reference's aircraft span ranges,
  bearings and headings;
* a gain that the data do not show (within ``gain_significance_sigma`` of zero) is held at
  zero rather than left to trade against the range offset (a model-selection test):
  ``/biases`` then reports it as 0 with the sigma it was estimated with.

Uncertainty: the rows of one track pair at successive updates share most of their track errors
(a filtered track is an average over its recent plots), so the textbook covariance ``H^-1``,
which treats every row as independent, is optimistic by about the square root of the updates
per track-error correlation time.  And one radar track enters several track pairs -- with the
track of every other radar that sees its aircraft, and with the aircraft's reference track --
with the same errors.  The reported covariance is therefore the cluster-robust (sandwich) one
with rows correlated whenever they share a track, ``H^-1 M H^-1``,

    M = diag(prior) + G/(G-1) (sum_t S_t S_t^T - sum_p S_p S_p^T),

``S_t`` the summed score ``G^T W r`` of all rows of track ``t`` (a radar's track, or a
reference's: one ADS-B track is paired with every radar that hears it), ``S_p`` of all rows of
track pair ``p``: the double sum ``sum_i sum_j s_i s_j^T`` over the rows ``i``, ``j`` that share
a track, by inclusion and exclusion (the rows of one track pair share both its tracks, and only
they).  ``G`` is the fewer of the tracks and the track pairs; where no track is in two pairs
(two radars, no reference) ``M`` is the sandwich over track pairs alone.  Such a meat need not
be positive semi-definite (few tracks for many terms): a negative part of the covariance, on
its correlation scale, is set to zero.  Any correlation among the rows of one track is allowed,
tracks of different aircraft are independent.  With fewer than ``min_clusters`` track pairs the
model covariance ``H^-1`` is used.  Measured calibration (error against sigma over the lab
study's runs): docs/registration.md, *Sigma*.

With two radars the *differential* effect ``G_a b_a - G_b b_b`` is always well determined
(it is what the data measure), so bias-compensating both radars with the estimate removes
the relative bias even where the split between the radars is prior-driven.

Compensation (:func:`compensate`) inverts (*) exactly for the polar terms (:func:`remove_bias`:
``r = (r_m - dr) / (1 + g 1e-6)``, angles less their offsets) and then moves the position to
reported time by ``+tau v``; velocities turn back by ``-dtheta`` and shrink by ``1 + g 1e-6``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Annotated, Any

import numpy as np
from annotated_types import Ge, Gt
from numpy.typing import NDArray

from service.correlation.base import FloatArray, PredictedTracks
from service.geo import Site
from service.linalg import congruence, inv3, quad3


@dataclass(frozen=True)
class RegistrationParams:
    """Bias least squares."""

    #: Prior 1-sigma of a range bias (m); weak, only regularises unobservable components.
    prior_range_m: Annotated[float, Gt(0)] = 3_000.0
    #: Prior 1-sigma of an azimuth bias (deg).
    prior_azimuth_deg: float = 3.0
    #: Prior 1-sigma of an elevation bias (deg).
    prior_elevation_deg: float = 3.0
    #: Prior 1-sigma of a range gain (ppm).  Weak: a gain of 2 000 ppm is 600 m at 300 km, far
    #: beyond what a maintained radar shows (a few hundred ppm), so where rows spread in range
    #: the data decide and only a gain the geometry cannot see shrinks to zero.
    prior_range_gain_ppm: Annotated[float, Gt(0)] = 2_000.0
    #: Prior 1-sigma of a time-stamp bias (s).  Weak: 3 s is most of a scan; a time bias the
    #: geometry cannot see (one common to every radar of a network without a reference)
    #: stays at zero with this sigma.
    prior_time_bias_s: Annotated[float, Gt(0)] = 3.0
    #: Estimate each radar's range gain (False: fixed at zero, the three-term model of old).
    estimate_range_gain: bool = True
    #: A radar's range gain within this many of its sigma of zero is held at zero (not
    #: significant: the data do not show it; :func:`solve_biases`).  Two radars without a
    #: reference separate gain and range offset only weakly (a gain sigma of some 100 ppm after
    #: 10 min), and a gain estimated there anyway costs the range offsets a factor 3-4 of
    #: precision; a real gain of a few hundred ppm is several sigma and stays.  0: never held.
    gain_significance_sigma: float = 3.0
    #: Estimate each radar's time-stamp bias (False: fixed at zero).
    estimate_time_bias: bool = True
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
    max_rows_per_update: Annotated[int, Ge(1)] = 300
    #: ... and at most this many per scan of the slower radar once the pair is registered (its
    #: solution in use; a pair updated every few scans takes that many times more).  Every
    #: solve costs in proportion to the remembered rows (a re-solve of a busy pair with 300
    #: rows per update was 40-80 ms); the pick's phase advances each update, so successive
    #: updates take different track pairs, and the memory still holds every confirmed pair
    #: several times over (1 000 pairs, 4 s updates, 600 s: each about 4 times at 30 rows).
    #: A row costs about 1 100 bytes (its cached normal-equation pieces of the five-term
    #: model; 740 with three terms): a national network of 66 radar pairs holds some 370 MB
    #: of rows at 30 per update, 1.2 GB at 100.
    registered_rows_per_update: Annotated[int, Ge(1)] = 30
    #: Minimum confirmed pairs before a correlator uses its registration.
    min_pairs: int = 6
    #: ... or at least this many distinct track pairs among the rows its solve kept (its
    #: ``clusters``, over the whole ``memory_s``): in thin traffic, or at the far ends of an
    #: overlap, a radar pair may never hold ``min_pairs`` confirmed pairs at once, yet its
    #: memory gathers many aircraft's rows over minutes (the biases drift over hours), and from
    #: ``min_clusters`` of them on the solve's covariance is the cluster-robust one, which
    #: the compensated test (stage 2) takes into its gates.  0 (the default): ``min_pairs``
    #: alone.  At 10 it paired more in thin traffic and at the ends of overlaps, and fewer
    #: right and more false in the formation study (a formation's pairs held, its solve kept
    #: in use on rows of tracks gone astray): docs/correlation.md, "A registration over time".
    min_track_pairs: int = 0
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
    #: Fewest distinct track pairs for the cluster-robust covariance (clustered by shared
    #: track, module docstring); below it, ``H^-1``.
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


#: The terms of every radar's registration, in the order of a bias vector (module docstring):
#: range offset (m), azimuth offset (rad), elevation offset (rad), range gain (ppm), time bias (s).
TERMS = ("range_m", "azimuth_rad", "elevation_rad", "range_gain_ppm", "time_bias_s")
N_TERMS = len(TERMS)
RANGE, AZIMUTH, ELEVATION, GAIN, TIME = range(N_TERMS)
#: One part per million (the unit of the range gain).
PPM = 1e-6


@dataclass(frozen=True)
class RadarBias:
    """One radar's estimated systematic errors (``GET /biases``).

    ``pairs_used``: confirmed pairs (over all radar pairs involving this radar) of the latest
    update that entered the least squares; earlier remembered updates are used as well.  The
    ``*_sigma_*`` are the 1-sigma of each bias (:meth:`BiasSolution.term_std`, cluster-robust
    once enough track pairs entered).  ``range_gain_*`` and ``time_bias_*`` are None where the
    term was not estimated (switched off, or a solution kept from before these terms existed).
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
    range_gain_ppm: float | None = None
    range_gain_sigma_ppm: float | None = None
    time_bias_s: float | None = None
    time_bias_sigma_s: float | None = None


def _term_index(n: int, terms: Sequence[int]) -> NDArray[np.intp]:
    """Indices of ``terms`` of every one of ``n`` radars in a stacked ``N_TERMS n`` vector."""
    return (N_TERMS * np.arange(n)[:, None] + np.asarray(terms)[None, :]).ravel().astype(np.intp)


_POLAR = (RANGE, AZIMUTH, ELEVATION)


@dataclass(frozen=True)
class BiasSolution:
    """Joint solution of every radar's registration terms.

    ``terms (n_radars, 5)``: ``(dr, dtheta, dphi, g, tau)`` in (m, rad, rad, ppm, s) per radar
    (:data:`TERMS`), ``terms_covariance (5 n, 5 n)`` their covariance (cluster-robust when at
    least ``min_clusters`` track pairs entered, else the model covariance), stacked per radar.
    ``relative_covariance``: the same, conditioned on the time bias common to the radars of each
    network part without a reference (not observable, module docstring): what compensation uses;
    None: ``terms_covariance``.

    ``bias (n, 3)``, ``covariance (3 n, 3 n)`` and ``model_covariance``: the three polar
    offsets alone (``terms[:, :3]`` and their blocks; ``model_covariance`` is ``H^-1``, rows
    treated as independent), as a solution of the three-term model had them.  A solution made
    with ``terms`` None (e.g. kept by an older version) is that three-term model: gain and time
    bias zero with zero variance (not estimated).
    """

    radar_ids: tuple[str, ...]
    bias: FloatArray
    covariance: FloatArray  # (3 n, 3 n)
    pairs_used: dict[str, int]
    model_covariance: FloatArray | None = None
    clusters: int = 0
    terms: FloatArray | None = None  # (n, 5); None: bias with zero gain and time bias
    terms_covariance: FloatArray | None = None  # (5 n, 5 n)
    relative_covariance: FloatArray | None = None  # (5 n, 5 n)

    def __post_init__(self) -> None:
        n = len(self.radar_ids)
        if self.terms is None:
            terms = np.zeros((n, N_TERMS))
            terms[:, :3] = np.asarray(self.bias, dtype=float).reshape(n, 3)
            object.__setattr__(self, "terms", terms)
        if self.terms_covariance is None:
            cov = np.zeros((N_TERMS * n, N_TERMS * n))
            idx = _term_index(n, _POLAR)
            cov[np.ix_(idx, idx)] = np.asarray(self.covariance, dtype=float).reshape(3 * n, 3 * n)
            object.__setattr__(self, "terms_covariance", cov)

    @classmethod
    def of_terms(
        cls,
        radar_ids: tuple[str, ...],
        terms: FloatArray,
        covariance: FloatArray,
        pairs_used: dict[str, int],
        model_covariance: FloatArray | None = None,
        clusters: int = 0,
        relative_covariance: FloatArray | None = None,
    ) -> BiasSolution:
        """A solution from the whole model; the three-term fields are its polar part."""
        idx = np.ix_(*(2 * (_term_index(len(radar_ids), _POLAR),)))
        return cls(
            radar_ids,
            terms[:, :3].copy(),
            covariance[idx],
            pairs_used,
            None if model_covariance is None else model_covariance[idx],
            clusters,
            terms,
            covariance,
            relative_covariance,
        )

    @property
    def full(self) -> tuple[FloatArray, FloatArray]:
        """``terms`` and ``terms_covariance`` (never None after construction)."""
        assert self.terms is not None and self.terms_covariance is not None
        return self.terms, self.terms_covariance

    def std(self) -> FloatArray:
        """1-sigma of the three polar offsets ``(n, 3)``."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None)).reshape(-1, 3)

    def term_std(self) -> FloatArray:
        """1-sigma of every term ``(n, 5)`` (zero: not estimated)."""
        return np.sqrt(np.clip(np.diag(self.full[1]), 0.0, None)).reshape(-1, N_TERMS)

    def of(self, radar_id: str | None) -> tuple[FloatArray, FloatArray]:
        """One radar's terms ``(5,)`` and the ``5x5`` covariance compensation uses (the relative
        one where a common time bias is unobservable); zeros for unknown / reference sources."""
        if radar_id is None or radar_id not in self.radar_ids:
            return np.zeros(N_TERMS), np.zeros((N_TERMS, N_TERMS))
        k = self.radar_ids.index(radar_id)
        terms, cov = self.full
        if self.relative_covariance is not None:
            cov = self.relative_covariance
        s = slice(N_TERMS * k, N_TERMS * k + N_TERMS)
        return terms[k], cov[s, s]


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


def model_jacobian(site: Site, position: FloatArray, velocity: FloatArray) -> FloatArray:
    """``G`` of the whole model (module docstring, (*)) at ECEF positions and velocities
    ``(n, 3)``: ``(n, 3, 5)``, columns ``R J`` (:func:`bias_jacobian`), ``1e-6 (y - L)`` (range
    gain, per ppm) and ``-v`` (time bias, per s)."""
    g = np.empty((position.shape[0], 3, N_TERMS))
    g[:, :, :3] = bias_jacobian(site, position)
    g[:, :, GAIN] = (position - site.origin_ecef) * PPM
    g[:, :, TIME] = -velocity
    return g


def _full_terms(bias: FloatArray, bias_cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """A bias vector and covariance of the three polar terms, or of all five, as all five
    (gain and time bias zero, with zero variance, when not given)."""
    bias = np.asarray(bias, dtype=float)
    if bias.shape[-1] == N_TERMS:
        return bias, np.asarray(bias_cov, dtype=float)
    full = np.zeros(N_TERMS)
    full[:3] = bias
    cov = np.zeros((N_TERMS, N_TERMS))
    cov[:3, :3] = bias_cov
    return full, cov


_SHAPES: dict[str, tuple[int, ...]] = {
    "time": (),
    "pair": (),
    "p_a": (3,),
    "p_b": (3,),
    "v": (3,),
    "s": (3, 3),
    "w": (3, 3),
    "w_ok": (),
    "gaw": (N_TERMS, 3),
    "gbw": (N_TERMS, 3),
    "haa": (N_TERMS, N_TERMS),
    "hab": (N_TERMS, N_TERMS),
    "hbb": (N_TERMS, N_TERMS),
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
    #: (k, 3) the pair's ECEF velocity (the time-bias column: mean of its two tracks', the
    #: reference's alone in a row with a reference); None: not known (rows from a peer that
    #: does not send it), zero: its time bias not observed.
    v: np.ndarray | None = None

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
    sums the pieces of the rows it keeps (``G`` of the whole model, :func:`model_jacobian`:
    the pieces are ``5x3`` and ``5x5``, some 1 100 bytes a row).  The columns (``time``,
    ``p_a``, ``p_b`` the raw ECEF positions, ``v`` the pair's velocity, ``s``, ``w``, ...) read
    as concatenated arrays; ``d = p_a - p_b``; ``g_a``, ``g_b`` (the polar columns of ``G``, not
    kept) are made again when read.
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
    v = property(lambda self: self._column("v"))
    d = property(lambda self: self.p_a - self.p_b)
    s = property(lambda self: self._column("s"))
    w = property(lambda self: self._column("w"))
    w_ok = property(lambda self: self._column("w_ok"))
    gaw = property(lambda self: self._column("gaw"))
    gbw = property(lambda self: self._column("gbw"))
    haa = property(lambda self: self._column("haa"))
    hab = property(lambda self: self._column("hab"))
    hbb = property(lambda self: self._column("hbb"))

    @property
    def g_a(self) -> FloatArray:
        """The polar columns ``R_a J_a`` of every row's ``G_a`` ``(n, 3, 3)`` (not kept: made
        again when read; the whole ``G`` is :func:`model_jacobian` of ``p_a`` and ``v``)."""
        return bias_jacobian(self.site_a, self.p_a)

    @property
    def g_b(self) -> FloatArray:
        """The same of ``G_b`` (zeros for a reference source)."""
        if self.site_b is None:
            return np.zeros((len(self), 3, 3))
        return bias_jacobian(self.site_b, self.p_b)

    def add(
        self,
        time_s: float,
        a: PredictedTracks,
        b: PredictedTracks,
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
        if self.site_b is None:
            # A reference row: its time column is the reference's velocity alone.  A radar
            # track's velocity error is correlated with its own position error (the filter
            # pulls both towards each plot; the prediction to the row's time adds dt times
            # it), so a column made of it correlates with the row's noise and biases the time
            # bias: E[v^T W d] picks up half of tr(W Cov(e_a, dv_a)), about -0.04 s of every
            # radar's time bias in the three-radar study (docs/registration.md).  The
            # reference's velocity (GNSS positions over a baseline) is independent of the
            # radar's errors.
            v = np.array(b.velocity[ib], dtype=float)
        else:
            # Both tracks follow the same aircraft: their mean velocity is the time column of
            # both sides, so that a time bias common to the two radars cancels exactly
            # (docstring); its correlation with the tracks' errors enters only as the
            # difference of the two radars' (module docstring).
            v = 0.5 * (a.velocity[ia] + b.velocity[ib])
        return self.add_rows(
            time_s, id_a, id_b, a.position[ia], b.position[ib], a.pos_cov[ia] + b.pos_cov[ib], params, v=v
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
        v: np.ndarray | None = None,
    ) -> RegistrationRowsData:
        """Remember the rows of one update given by what defines them (the pairs' track ids,
        raw ECEF positions, the sum ``s`` of their position covariances and the pairs' velocity
        ``v``, None: zero, its time biases then not observed); every other column is derived
        here.  Returns those defining columns: another process that adds the same rows in the
        same order holds the same memory (partitioned workers)."""
        pair = np.char.add(np.char.add(track_a, "\x1f"), track_b)
        vel = np.zeros((len(p_a), 3)) if v is None else np.asarray(v, dtype=float)
        self._append({"time": np.full(len(p_a), float(time_s)), **self._rows_of(pair, p_a, p_b, s, vel)})
        self._updates.append((float(time_s), len(p_a)))
        if prune:
            self.prune(time_s, params)
        return RegistrationRowsData(float(time_s), track_a, track_b, p_a, p_b, s, vel)

    def _rows_of(
        self, pair: np.ndarray, p_a: np.ndarray, p_b: np.ndarray, s: np.ndarray, v: np.ndarray
    ) -> dict[str, np.ndarray]:
        """Every column of rows but ``time``: the defining ones and the pieces derived here."""
        ga = model_jacobian(self.site_a, p_a, v)
        if self.site_b is not None:
            gb = model_jacobian(self.site_b, p_b, v)
        else:
            gb = np.zeros((len(p_b), 3, N_TERMS))
        w, w_ok = inv3(s)
        gat_w = np.swapaxes(ga, 1, 2) @ w
        gbt_w = np.swapaxes(gb, 1, 2) @ w
        return {
            "pair": pair,
            "p_a": p_a,
            "p_b": p_b,
            "v": v,
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
        the live rows' ``time``, ``pair``, ``p_a``, ``p_b``, ``s`` and ``v``, each remembered update's
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
            "v": self.v,
            "update_time": np.array([t for t, _ in self._updates], dtype=float),
            "update_rows": np.array([k for _, k in self._updates], dtype=np.int64),
            "adds": self._adds,
        }

    @classmethod
    def restored(cls, site_a: Site, site_b: Site | None, state: Mapping[str, Any]) -> RegistrationMemory:
        """The memory :meth:`export` gave, its derived columns made again from ``site_a`` and
        ``site_b`` (the sites it was measured from).  ``ValueError`` if the columns disagree.
        A memory kept before the time bias was modelled has no ``v``: its rows take velocity
        zero (they say nothing of time biases; newer rows do)."""
        time = np.asarray(state["time"], dtype=float)
        n = time.shape[0]
        cols = {
            "pair": np.asarray(state["pair"], dtype=str),
            "p_a": np.asarray(state["p_a"], dtype=float),
            "p_b": np.asarray(state["p_b"], dtype=float),
            "s": np.asarray(state["s"], dtype=float),
            "v": np.asarray(state["v"], dtype=float) if "v" in state else np.zeros((n, 3)),
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
                {
                    "time": time,
                    **memory._rows_of(cols["pair"], cols["p_a"], cols["p_b"], cols["s"], cols["v"]),
                }
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

    Every radar's five terms (module docstring, (*)); terms switched off in ``params`` stay
    zero with zero variance, and a range gain within ``gain_significance_sigma`` of zero is
    held at zero with the sigma the whole model gives it.  ``initial``: a previous solution to
    start from (a warm start; radars it lacks start at zero; the gains it held start held).
    Its rows are then first selected by the outlier test at that estimate, so a solve whose
    rows changed little since converges in one or two Gauss-Newton steps instead of first
    converging on every row, outliers included, from zero (5-8 steps).  The fixed point is the
    same: the estimate is converged on a row set the outlier test leaves unchanged.
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
    nt = N_TERMS
    n = nt * len(ids)
    prior = np.tile(
        [
            1.0 / prm.prior_range_m**2,
            1.0 / np.radians(prm.prior_azimuth_deg) ** 2,
            1.0 / np.radians(prm.prior_elevation_deg) ** 2,
            1.0 / prm.prior_range_gain_ppm**2,
            1.0 / prm.prior_time_bias_s**2,
        ],
        len(ids),
    )
    # The terms solved for; the others stay zero with zero variance.
    active = np.tile([True, True, True, prm.estimate_range_gain, prm.estimate_time_bias], len(ids))
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
                for c in ("pair", "p_a", "p_b", "v", "w", "w_ok", "gaw", "gbw", "haa", "hab", "hbb")
            },
        )
        for m, r in rows
    ]
    _cluster_labels(data)
    bias = np.zeros(n)
    if initial is not None:
        start, _ = initial.full
        for rid, k in col.items():
            if rid in initial.radar_ids:
                bias[nt * k : nt * k + nt] = start[initial.radar_ids.index(rid)]
        bias[~active] = 0.0
    if initial is not None and np.any(bias != 0.0):
        residuals = [_residual(m, cols, bias, col) for m, _, cols in data]
        keep = [
            cols["w_ok"] & (quad3(res, cols["w"]) <= prm.outlier_chi2)
            for (_, _, cols), res in zip(data, residuals, strict=True)
        ]
    else:
        residuals = [cols["p_a"] - cols["p_b"] for _, _, cols in data]
        keep = [cols["w_ok"].copy() for _, _, cols in data]
    # A range gain the data do not show (within ``gain_significance_sigma`` of zero) is held at
    # zero: estimating it costs the range offsets most of their precision where the geometry
    # hardly separates the two (two radars, no reference: 4-6 m become 16-18 m), for nothing
    # when there is no gain.  Its sigma is the whole model's: the gain is held, not known.  The
    # gains the previous solution held start held (a warm solve then converges once), and the
    # held set is tested after each solve; at most one change of it per solve.
    gains = N_TERMS * np.arange(len(ids)) + GAIN
    held = np.zeros(n, dtype=bool)
    if initial is not None and prm.estimate_range_gain:
        start, start_cov = initial.full
        for rid, k in col.items():
            if rid in initial.radar_ids:
                j = N_TERMS * initial.radar_ids.index(rid) + GAIN
                held[nt * k + GAIN] = start[j // N_TERMS, GAIN] == 0.0 and start_cov[j, j] > 0.0
    for attempt in range(2):
        if held.any():
            bias[held] = 0.0
            residuals = [_residual(m, cols, bias, col) for m, _, cols in data]
        bias, cov, keep, fit_keep, residuals = _gauss_newton(
            data, col, prior, active & ~held, bias, keep, residuals, prm
        )
        robust, clusters = _robust_covariance(data, fit_keep, residuals, col, cov, prior, prm.min_clusters)
        gain, sigma = bias[gains], np.sqrt(np.clip(np.diag(robust)[gains], 0.0, None))
        if held.any():  # the held gains as the whole model would estimate them from here
            whole, whole_cov = _one_step(data, fit_keep, residuals, col, prior, active, bias, prm)
            gain = np.where(held[gains], whole[gains], gain)
            sigma = np.where(held[gains], np.sqrt(np.clip(np.diag(whole_cov)[gains], 0.0, None)), sigma)
        weak = np.zeros(n, dtype=bool)
        weak[gains] = active[gains] & (np.abs(gain) < prm.gain_significance_sigma * sigma)
        if attempt == 1 or np.array_equal(weak, held):
            break
        held = weak
    robust[held, held] = sigma[held[gains]] ** 2
    relative = _relative_covariance(robust, [m for m, _, _ in data], col) if prm.estimate_time_bias else None
    # pairs_used: confirmed pairs of the latest remembered update that survived the outlier
    # test (the LS itself uses every remembered update's rows).
    used: dict[str, int] = dict.fromkeys(ids, 0)
    kept: dict[str, int] = dict.fromkeys(ids, 0)
    for (m, r, _), kp in zip(data, keep, strict=True):
        t = m.time[r]
        n_latest = int((kp & (t == t.max())).sum()) if t.size else 0
        for site in (m.site_a, m.site_b):
            if site is not None:
                used[site.site_id] += n_latest
                kept[site.site_id] += int(kp.sum())
    if initial is not None and not all(kept.values()):
        # A radar with rows in the window none of which the outlier test keeps at the warm
        # start's estimate: that estimate was wrong for it (a solve on few rows, with large
        # biases), and selecting its rows by it would lock them out for good, the estimate
        # standing where no row supports it.  Solved cold instead: every row is a candidate.
        return solve_biases(memories, time_s, prm)
    return BiasSolution.of_terms(tuple(ids), bias.reshape(-1, nt), robust, used, cov, clusters, relative)


def _gauss_newton(
    data: list[tuple[RegistrationMemory, np.ndarray, dict[str, np.ndarray]]],
    col: dict[str, int],
    prior: FloatArray,
    active: NDArray[np.bool_],
    bias: FloatArray,
    keep: list[np.ndarray],
    residuals: list[FloatArray],
    prm: RegistrationParams,
) -> tuple[FloatArray, FloatArray, list[np.ndarray], list[np.ndarray], list[FloatArray]]:
    """Gauss-Newton on the exact model from ``bias`` over the rows ``keep`` (their residuals at
    ``bias``), re-selecting the rows by the outlier test once converged (:func:`solve_biases`).
    Returns the estimate, its model covariance ``H^-1`` (zero outside ``active``), the last row
    selection, the one the estimate was fitted to, and every row's residual at the estimate."""
    n = prior.shape[0]
    act = np.ix_(active, active)
    fit_keep = keep
    cov = np.diag(np.where(active, 1.0 / prior, 0.0))
    rounds = 0
    normal_of: list[np.ndarray] | None = None  # the row set ``cov`` (H^-1) was made for
    for _ in range(prm.max_iterations):
        fit_keep = keep
        if normal_of is not keep:
            # The normal matrix depends on the rows kept only: made again when they change.
            cov = np.zeros((n, n))
            cov[act] = np.linalg.inv(_normal_matrix(data, keep, col, prior)[act])
            normal_of = keep
        g = -prior * bias
        for (m, _, cols), kp, res in zip(data, keep, residuals, strict=True):
            np.add.at(g, _columns(m, col), kp.astype(float) @ _scores(m, cols, res))
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
    return bias, cov, keep, fit_keep, residuals


def _one_step(
    data: list[tuple[RegistrationMemory, np.ndarray, dict[str, np.ndarray]]],
    keep: list[np.ndarray],
    residuals: list[FloatArray],
    col: dict[str, int],
    prior: FloatArray,
    active: NDArray[np.bool_],
    bias: FloatArray,
    prm: RegistrationParams,
) -> tuple[FloatArray, FloatArray]:
    """One Gauss-Newton step of every ``active`` term from ``bias`` (a solution with some terms
    held), and the cluster-robust covariance of the result: what the whole model would estimate
    for the held terms, without solving it (``held`` gains, :func:`solve_biases`)."""
    n = prior.shape[0]
    act = np.ix_(active, active)
    cov = np.zeros((n, n))
    cov[act] = np.linalg.inv(_normal_matrix(data, keep, col, prior)[act])
    g = -prior * bias
    for (m, _, cols), kp, res in zip(data, keep, residuals, strict=True):
        np.add.at(g, _columns(m, col), kp.astype(float) @ _scores(m, cols, res))
    robust, _ = _robust_covariance(data, keep, residuals, col, cov, prior, prm.min_clusters)
    return bias + cov @ g, robust


def _normal_matrix(
    data: list[tuple[RegistrationMemory, np.ndarray, dict[str, np.ndarray]]],
    keep: list[np.ndarray],
    col: dict[str, int],
    prior: FloatArray,
) -> FloatArray:
    """``H = diag(prior) + sum G^T W G`` over the kept rows, from each row's cached pieces."""
    nt = N_TERMS
    h = np.diag(prior)
    for (m, _, cols), kp in zip(data, keep, strict=True):
        kf = kp.astype(float)
        nr = kf.shape[0]
        ka = nt * col[m.site_a.site_id]
        h[ka : ka + nt, ka : ka + nt] += (kf @ cols["haa"].reshape(nr, nt * nt)).reshape(nt, nt)
        if m.site_b is not None:
            kb = nt * col[m.site_b.site_id]
            cross = (kf @ cols["hab"].reshape(nr, nt * nt)).reshape(nt, nt)
            h[ka : ka + nt, kb : kb + nt] -= cross
            h[kb : kb + nt, ka : ka + nt] -= cross.T
            h[kb : kb + nt, kb : kb + nt] += (kf @ cols["hbb"].reshape(nr, nt * nt)).reshape(nt, nt)
    return h


def _relative_covariance(
    cov: FloatArray, memories: Sequence[RegistrationMemory], col: dict[str, int]
) -> FloatArray | None:
    """``cov`` conditioned on the time bias common to the radars of each part of the network
    (radars linked by rows) that no reference reaches: ``C - C e (e^T C e)^-1 e^T C`` with ``e``
    the sum of those radars' time-bias directions, one part after the other (module docstring).
    That common mode is not observable (every row cancels it), its estimate is the prior's zero
    and its variance the prior's; left in, it would enter every compensated position of the
    part alike yet count as independent on each side of a pair test.  None: no such part."""
    parent = list(range(len(col)))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    referenced: set[int] = set()
    for m in memories:
        ka = col[m.site_a.site_id]
        if m.site_b is None:
            referenced.add(ka)
        else:
            parent[root(ka)] = root(col[m.site_b.site_id])
    parts: dict[int, list[int]] = {}
    for k in range(len(col)):
        parts.setdefault(root(k), []).append(k)
    out = None
    for members in parts.values():
        if len(members) < 2 or referenced.intersection(members):
            continue
        e = np.zeros(cov.shape[0])
        e[N_TERMS * np.asarray(members) + TIME] = 1.0
        out = cov.copy() if out is None else out
        ce = out @ e
        var = float(e @ ce)
        if var > 0.0:
            out -= np.outer(ce, ce) / var
    return out


def remove_bias(
    site: Site, position: FloatArray, bias: FloatArray, velocity: FloatArray | None = None
) -> FloatArray:
    """The exact inverse of the model (module docstring, (*)): the ECEF positions ``(n, 3)``
    the radar at ``site`` would report without its terms ``bias``, the three polar offsets
    ``(dr, dtheta, dphi)`` in (m, rad, rad) or all five (with ``g`` ppm and ``tau`` s).

    The polar part equals ``polar_to_ecef((r - dr) / (1 + g 1e-6), theta - dtheta, phi -
    dphi)`` of the position's polar coordinates, computed without per-point trigonometry: in
    the site's ENU frame the horizontal part turns by ``dtheta`` about the vertical (azimuth
    clockwise from north), the point turns by ``-dphi`` in its vertical plane, and the range
    scales.  A time bias then moves each position by ``+tau v`` (``velocity`` ECEF ``(n, 3)``,
    required when ``tau`` is not zero): from where the target was at ``t - tau`` to ``t``.
    """
    b = np.asarray(bias, dtype=float)
    out = site.enu_to_ecef(_remove_bias_enu(site.ecef_to_enu(position), b))
    if b.shape[0] == N_TERMS and b[TIME] != 0.0:
        if velocity is None:
            raise ValueError("a time bias needs the velocities")
        out = out + b[TIME] * velocity
    return out


def _remove_bias_enu(enu: FloatArray, bias: FloatArray) -> FloatArray:
    """The polar part of :func:`remove_bias` in the site's ENU frame (points in, points out):
    offsets and, when ``bias`` has five terms, the range gain."""
    ct, st = np.cos(bias[AZIMUTH]), np.sin(bias[AZIMUTH])
    cp, sp = np.cos(bias[ELEVATION]), np.sin(bias[ELEVATION])
    gain = 1.0 + bias[GAIN] * PPM if bias.shape[0] == N_TERMS else 1.0
    e = enu[:, 0] * ct - enu[:, 1] * st
    n = enu[:, 1] * ct + enu[:, 0] * st
    u = enu[:, 2]
    h = np.hypot(e, n)
    r = np.hypot(h, u)
    h1 = h * cp + u * sp
    u1 = u * cp - h * sp
    scale = (r - bias[RANGE]) / (gain * np.where(r > 0, r, 1.0))
    ratio = np.divide(h1, h, out=np.ones_like(h), where=h > 0) * scale
    return np.stack([e * ratio, n * ratio, u1 * scale], axis=1)


def _residual(
    m: RegistrationMemory, cols: dict[str, np.ndarray], bias: FloatArray, col: dict[str, int]
) -> FloatArray:
    """Each row's exact residual: A's position minus B's, both with the estimated terms removed
    (the time terms with the row's velocity, ``(tau_a - tau_b) v``)."""
    nt = N_TERMS
    ka = nt * col[m.site_a.site_id]
    ba = bias[ka : ka + nt]
    pa = m.site_a.enu_to_ecef(_remove_bias_enu(m.site_a.ecef_to_enu(cols["p_a"]), ba))
    tau = ba[TIME]
    if m.site_b is None:
        res = pa - cols["p_b"]
    else:
        kb = nt * col[m.site_b.site_id]
        bb = bias[kb : kb + nt]
        res = pa - m.site_b.enu_to_ecef(_remove_bias_enu(m.site_b.ecef_to_enu(cols["p_b"]), bb))
        tau = tau - bb[TIME]
    if tau != 0.0:
        res += tau * cols["v"]
    return res


def _scores(m: RegistrationMemory, cols: dict[str, np.ndarray], res: FloatArray) -> FloatArray:
    """Each row's score in its own two radars' columns ``(rows, 10)``: ``G_a^T W r`` for A and
    ``-G_b^T W r`` for B (the negative half-gradient of the row's ``r^T W r`` in the terms;
    B's half is zero for a reference source)."""
    nt = N_TERMS
    sc = np.zeros((res.shape[0], 2 * nt))
    _matvec53(cols["gaw"], res, sc[:, :nt])
    if m.site_b is not None:
        _matvec53(cols["gbw"], res, sc[:, nt:])
        sc[:, nt:] *= -1.0
    return sc


def _matvec53(m: FloatArray, v: FloatArray, out: FloatArray) -> None:
    """``out = M v`` for stacks ``M (n, 5, 3)``, ``v (n, 3)`` (one ``einsum``: a batched ``@`` on
    such small matrices pays a per-matrix overhead; measured 0.9 against 1.1 ms at 39 000)."""
    np.einsum("nij,nj->ni", m, v, out=out)


def _columns(m: RegistrationMemory, col: dict[str, int]) -> NDArray[np.intp]:
    """The ten columns of the joint problem a memory's row scores fall in (B's: A's again for
    a reference source, whose half of the score is zero)."""
    nt = N_TERMS
    ka = nt * col[m.site_a.site_id]
    kb = nt * col[m.site_b.site_id] if m.site_b is not None else ka
    return np.concatenate([np.arange(ka, ka + nt), np.arange(kb, kb + nt)]).astype(np.intp)


def _cluster_labels(data: list[tuple[RegistrationMemory, np.ndarray, dict[str, np.ndarray]]]) -> None:
    """The clusters of the robust covariance, found once per solve (sorting the ids is the
    dearest step of a covariance): ``cols["cluster"]`` each row's track pair as a small integer
    of its memory, ``cols["tracks"] (pairs, 2)`` the two tracks of each of those track pairs as
    integers common to every memory.  A track is its source's: the radar's site id and the
    track id (a reference's with an empty site id: one reference track of an aircraft is paired
    with every radar that sees it, with the same errors)."""
    keys = []
    for m, _, cols in data:
        pairs, label = np.unique(cols["pair"], return_inverse=True)
        cols["cluster"] = label.ravel().astype(np.intp)
        # only the distinct pairs are split into their two track ids
        parts = np.char.partition(pairs.astype(str), "\x1f")
        site_b = "" if m.site_b is None else m.site_b.site_id
        keys.append(np.char.add(m.site_a.site_id + "\x1f", parts[:, 0]))
        keys.append(np.char.add(site_b + "\x1f", parts[:, 2]))
    if not keys:
        return
    track = np.unique(np.concatenate(keys), return_inverse=True)[1].ravel().astype(np.intp)
    start = 0
    for _, _, cols in data:
        k = int(cols["cluster"].max()) + 1 if cols["cluster"].size else 0
        cols["tracks"] = np.stack([track[start : start + k], track[start + k : start + 2 * k]], axis=1)
        start += 2 * k


def _robust_covariance(
    data: list[tuple[RegistrationMemory, np.ndarray, dict[str, np.ndarray]]],
    keep: list[np.ndarray],
    residuals: list[FloatArray],
    col: dict[str, int],
    cov: FloatArray,
    prior: FloatArray,
    min_clusters: int,
) -> tuple[FloatArray, int]:
    """Cluster-robust covariance of the terms (module docstring), and the number of track pairs
    that entered it.

    ``residuals``: every row's exact residual at the solution (:func:`_residual`), ``keep``: the
    rows that solution was fitted to.  Two rows are taken as correlated when they share a radar
    (or reference) track, in one track pair or in two: the meat is
    ``sum_i sum_j s_i s_j^T [i, j share a track]`` (``s_i`` a row's score ``G^T W r`` in every
    column), by inclusion and exclusion ``sum_t S_t S_t^T - sum_p S_p S_p^T`` with ``S_t`` the
    summed score of the rows of track ``t`` and ``S_p`` of track pair ``p`` (the rows of one
    track pair share both its tracks, and only they), times ``G/(G-1)`` with ``G`` the fewer of
    the tracks and track pairs.  The prior is one more independent term, so components the data
    do not determine keep their prior variance.  Where no track is in two track pairs this is
    the sandwich over track pairs alone.
    """
    if len(residuals) != len(data):
        return cov, 0
    n = prior.shape[0]
    n_tracks = max((int(cols["tracks"].max()) + 1 for _, _, cols in data if cols["tracks"].size), default=0)
    by_track = np.zeros((n_tracks, n))
    by_pair = np.zeros((n, n))
    used = np.zeros(n_tracks, dtype=bool)
    pairs = 0
    for (m, _, cols), kp, res in zip(data, keep, residuals, strict=True):
        idx = np.flatnonzero(kp)
        if idx.size == 0:
            continue
        sc = _scores(m, cols, res)[idx]
        label = cols["cluster"][idx]  # the track pair of each kept row
        k = cols["tracks"].shape[0]
        summed = np.stack(
            [np.bincount(label, weights=sc[:, j], minlength=k) for j in range(sc.shape[1])], axis=1
        )
        where = _columns(m, col)  # a reference's half of a score is zero (its columns A's again)
        # Track pairs never span two memories: their part is one 10x10 block per memory.
        np.add.at(by_pair, np.ix_(where, where), summed.T @ summed)
        tracks = cols["tracks"]
        np.add.at(by_track, (tracks[:, :1], where[None, :]), summed)
        np.add.at(by_track, (tracks[:, 1:], where[None, :]), summed)
        entered = np.bincount(label, minlength=k) > 0
        used[tracks[entered].ravel()] = True
        pairs += int(np.count_nonzero(entered))
    g = min(pairs, int(np.count_nonzero(used)))
    if pairs < max(min_clusters, 2) or g < 2:
        return cov, pairs
    meat = np.diag(prior) + (by_track.T @ by_track - by_pair) * (g / (g - 1))
    return _nonnegative(cov @ meat @ cov), pairs


def _nonnegative(v: FloatArray) -> FloatArray:
    """``v`` with negative eigenvalues set to zero (the inclusion and exclusion of
    :func:`_robust_covariance` need not give a positive semi-definite meat), on the correlation
    scale: the terms' units differ by many orders of magnitude.  ``v`` itself when it has none."""
    d = np.sqrt(np.clip(np.diag(v), 0.0, None))
    on = np.flatnonzero(d > 0)  # terms not estimated keep their zero rows exactly
    scale = np.outer(d[on], d[on])
    w, u = np.linalg.eigh(0.5 * (v[np.ix_(on, on)] + v[np.ix_(on, on)].T) / scale)
    if on.size == 0 or w.min() >= 0.0:
        return v
    out = np.zeros_like(v)
    out[np.ix_(on, on)] = (u * np.clip(w, 0.0, None)) @ u.T * scale
    return out


def compensate(
    snapshot: PredictedTracks, bias: FloatArray, bias_cov: FloatArray
) -> tuple[PredictedTracks, FloatArray]:
    """Remove an estimated registration from a radar snapshot; also the per-track covariance
    it adds, ``G C G^T`` (module docstring, (*)).

    ``bias``, ``bias_cov``: the five terms and their covariance (:meth:`BiasSolution.of`), or
    the three polar offsets alone.  Positions: the polar terms removed exactly
    (:func:`remove_bias`; to first order ``y - G b``), then moved by ``+tau v`` to the reported
    time.  Velocities: an azimuth offset rotates the radar's whole picture and a range gain
    scales it about the site, so ENU velocities are rotated back by ``-dtheta`` (clockwise
    azimuth convention) and divided by ``1 + g 1e-6``; a time bias leaves them as they are.
    """
    bias, bias_cov = _full_terms(bias, bias_cov)
    if snapshot.site is None or len(snapshot) == 0:
        return snapshot, np.zeros((len(snapshot), 3, 3))
    site = snapshot.site
    # The snapshot's own ENU states (those of its positions) give the Jacobian and the removal:
    # G in ENU is [J | 1e-6 enu | -v_enu] (the site's rotation applied once, below).
    n = len(snapshot)
    g = np.empty((n, 3, N_TERMS))
    g[:, :, :3] = polar_jacobian_enu(snapshot.enu)
    g[:, :, GAIN] = snapshot.enu * PPM
    g[:, :, TIME] = -snapshot.enu_velocity
    enu = _remove_bias_enu(snapshot.enu, bias)
    dth = -bias[AZIMUTH]
    c, s = np.cos(dth), np.sin(dth)
    ev = snapshot.enu_velocity / (1.0 + bias[GAIN] * PPM)
    enu_v = np.stack([ev[:, 0] * c + ev[:, 1] * s, -ev[:, 0] * s + ev[:, 1] * c, ev[:, 2]], axis=1)
    if bias[TIME] != 0.0:
        enu = enu + bias[TIME] * enu_v
    # G C G^T = R (G_enu C G_enu^T) R^T: G C as one 2-D product, R (.) R^T as a congruence.
    gc = (g.reshape(-1, N_TERMS) @ bias_cov).reshape(g.shape)
    extra = congruence(site.rotation, gc @ np.swapaxes(g, 1, 2))
    out = PredictedTracks(
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
        quality=snapshot.quality,
        track_key=snapshot.track_key,
    )
    return out, extra


def solution_state(solution: BiasSolution) -> dict[str, Any]:
    """A joint solution as plain values and arrays, every field (service.state keeps it)."""
    return {f.name: getattr(solution, f.name) for f in fields(BiasSolution)}


def _array_or_none(value: Any) -> FloatArray | None:
    return None if value is None else np.asarray(value, dtype=float)


def solution_from_state(state: Mapping[str, Any]) -> BiasSolution:
    """The solution :func:`solution_state` gave; ``ValueError`` if its arrays disagree.

    A state kept by a version of the three-term model (no ``terms``) loads as that model:
    gain and time bias zero with zero variance (not estimated), until the next solve."""
    known = {f.name for f in fields(BiasSolution)}
    sol = BiasSolution(
        **{
            **{k: v for k, v in state.items() if k in known},
            "radar_ids": tuple(str(r) for r in state["radar_ids"]),
            "bias": np.asarray(state["bias"], dtype=float),
            "covariance": np.asarray(state["covariance"], dtype=float),
            "pairs_used": {str(k): int(v) for k, v in state["pairs_used"].items()},
            "model_covariance": _array_or_none(state.get("model_covariance")),
            "terms": _array_or_none(state.get("terms")),
            "terms_covariance": _array_or_none(state.get("terms_covariance")),
            "relative_covariance": _array_or_none(state.get("relative_covariance")),
        }
    )
    n = len(sol.radar_ids)
    terms, cov = sol.full
    if (
        sol.bias.shape != (n, 3)
        or sol.covariance.shape != (3 * n, 3 * n)
        or terms.shape != (n, N_TERMS)
        or cov.shape != (N_TERMS * n, N_TERMS * n)
        or (sol.relative_covariance is not None and sol.relative_covariance.shape != cov.shape)
        or not np.array_equal(terms[:, :3], sol.bias)
        or set(sol.pairs_used) != set(sol.radar_ids)
    ):
        raise ValueError(f"bias solution of {n} radars with biases of shape {sol.bias.shape}")
    return sol


def _estimated(value: float, sigma: float) -> tuple[float | None, float | None]:
    """A term and its 1-sigma, both None when it was not estimated (zero variance)."""
    return (float(value), float(sigma)) if sigma > 0.0 else (None, None)


def to_estimates(solution: BiasSolution | None, time_s: float) -> list[RadarBias]:
    if solution is None:
        return []
    terms, _ = solution.full
    std = solution.term_std()
    out = []
    for k, rid in enumerate(solution.radar_ids):
        gain, gain_sigma = _estimated(terms[k, GAIN], std[k, GAIN])
        tau, tau_sigma = _estimated(terms[k, TIME], std[k, TIME])
        out.append(
            RadarBias(
                radar_id=rid,
                range_bias_m=float(terms[k, RANGE]),
                azimuth_bias_deg=float(np.degrees(terms[k, AZIMUTH])),
                elevation_bias_deg=float(np.degrees(terms[k, ELEVATION])),
                pairs_used=int(solution.pairs_used[rid]),
                time_s=float(time_s),
                range_bias_sigma_m=float(std[k, RANGE]),
                azimuth_bias_sigma_deg=float(np.degrees(std[k, AZIMUTH])),
                elevation_bias_sigma_deg=float(np.degrees(std[k, ELEVATION])),
                range_gain_ppm=gain,
                range_gain_sigma_ppm=gain_sigma,
                time_bias_s=tau,
                time_bias_sigma_s=tau_sigma,
            )
        )
    return out
