"""Evidence accumulated over a candidate pair's common history (the sequential test).

One snapshot cannot tell two close aircraft apart when their separation is comparable to the
radars' cross-range error; their history can: each update gives a new, partly independent
look at the difference of the two tracks, and a false pairing keeps the two aircraft's
separation while a true one averages towards zero.  This module keeps, per *candidate* pair
``(i, j)`` of one radar pair (not only the pairs of the book: a candidate the one-to-one
assignment refused as ambiguous keeps collecting evidence), the running mean of its residual
and tests that mean.

**Residual.**  Per update ``k`` a 3-vector ``r_k`` in B's ENU frame with the covariance
``S_k`` of its random part and ``C_k`` of a part common to every update (the registration's
own uncertainty: it does not average out):

* once registered, the bias-compensated difference ``x_A - x_B`` (Eq. (2) model removed, see
  :func:`.registration.compensate`) of every pair of tracks within ``registered_search_m``,
  with ``S_k = P_A + P_B`` and ``C_k`` the covariance the bias estimate adds on both sides;
* before registration, inside a group of tracks, the difference against the group's local
  offset (:mod:`.group_offset`), ``C_k`` the offset's own covariance.  (The topology match's
  translation ``t``, Eq. (4), is not used: its covariance ``S_ref`` overstated the spread of
  true pairs' ``t`` several times over, so its looks accepted every lattice neighbour.)
  Elsewhere before registration there is no look, and the update decides alone.

A re-solve of the registration moves every remembered mean residual ``rbar`` of two present
tracks by the change the new estimate makes to their compensated positions (at their present
positions, the registration's Jacobian there; ``recompensate``): the looks are a mean of
differences each compensated with the estimate of its time, and a drifting estimate would
otherwise leave its old error in the history for a horizon (a false pair that the estimate of
its time favoured kept defending itself).  A re-solve that moves a bias by more than
``reset_sigma`` of its sigmas forgets every look instead.  (Looks taken before the first
registration, against a group's offset, are moved alike; the registered looks soon outweigh
them.)

**Accumulation** (per entry, data time; ``dt`` since the entry's previous observation)::

    d = exp(-dt / horizon_s)                        forgetting of old evidence
    rho = exp(-dt / error_correlation_s)            correlation of successive track errors
    W' = d W + 1,  rbar' = (d W rbar + r_k) / W',  Sbar' = (d W Sbar + S_k) / W'
    n' = d n + (1 - rho) / (1 + rho)                 (n = 1 at the first observation)

``n`` is the effective number of independent looks: for residuals correlated by ``rho`` from
update to update (a tracker's errors are, AR(1)), the mean of ``m`` of them has the variance
of ``n = 1 + (m - 1)(1 - rho)/(1 + rho)`` independent ones (exact for ``m = 2``, within 2 %
for ``rho <= 0.5`` and asymptotically), so the same evidence is not counted twice.

**Test.**  ``q = rbar^T (Sbar / n + C)^-1 rbar`` is chi-square with 3 dof for a true pair (the
mean of zero-mean Gaussian residuals with that covariance); a false pair's ``rbar`` tends to
the two aircraft's separation ``s`` while the covariance shrinks towards ``C``, so its ``q``
grows about as ``n s^T Sbar^-1 s``.  Between two rival pairings sharing a track the
log-likelihood ratio is ``(q_2 - q_1) / 2`` (equal covariances), the quantity the one-to-one
assignment's ambiguity margin is set on (the costs are ``q_rel - 3``, ``q_rel`` the same
statistic without ``C``, common to rivals and so cancelling from their ratio): a pair
ambiguous on one snapshot is resolved once ``n`` is large enough, and stays ambiguous while
it is not.  From ``min_looks`` looks on, a pair with ``q > chi2_{3}(1 - alpha)`` is
rejected whatever its single update said.

**Probability** (the published ``score``).  The posterior of pair ``(i, j)`` among the live
hypotheses of its two tracks, each weighted by its Gaussian likelihood ``exp(-cost / 2)``
(``cost = q_rel - 3``), plus the hypothesis that the track's partner is not among them
(weight ``exp(-null_cost / 2)``)::

    p_ij = L_ij / (sum_{j'} L_ij' + sum_{i'} L_i'j - L_ij + L_0)

then mapped by a logistic calibration ``sigmoid(calibration_slope * logit(p) +
calibration_offset)`` whose two parameters are fitted on simulated formations (the dense
study in ``docs/evaluation``) and checked there by a reliability diagram and the Brier score.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.chi2 import chi2_upper
from service.correlation.base import FloatArray, IntArray, PredictedTracks
from service.correlation.candidates import candidate_pairs
from service.correlation.pairkeys import find, isin_sorted, joined, pair_keys
from service.linalg import congruence, mahalanobis3


@dataclass(frozen=True)
class EvidenceParams:
    """The sequential test over a pair's history (every threshold named)."""

    #: Accumulate evidence over the pairs' history (False: every update decides on its own).
    enabled: bool = True
    #: Correlation time (s) of a track's estimation error: successive residuals correlate by
    #: ``exp(-dt / error_correlation_s)``.  45 s is the lab's track-error model (AR(1) with 0.8
    #: from one 10 s scan to the next): a track keeps most of an error for several revisits.
    #: Too short counts the same evidence twice (false pairs, overconfident score); too long
    #: only resolves more slowly.
    error_correlation_s: float = 45.0
    #: Memory (s): evidence older than this counts ``1/e`` as much (aircraft manoeuvre, a
    #: tracker may swap two tracks: the recent past matters most).
    horizon_s: float = 300.0
    #: An entry not observed for this long is forgotten (data time).
    forget_after_s: float = 120.0
    #: False-rejection probability of the accumulated test (3 dof); a pair beyond it is rejected.
    alpha: float = 1e-3
    #: Looks (updates that observed the pair) from which its accumulated test decides it and its
    #: accumulated statistic is its cost in the one-to-one assignment (module docstring).
    min_looks: int = 2
    #: A confirmed pair is kept without a full decision only while no rival of either of its
    #: tracks has an accumulated chi-square lower by more than this (0: it must be the best).
    keep_margin: float = 0.0
    #: Whether a candidate with fewer looks than ``min_looks`` may be accepted on its single
    #: update's test (True) or must wait for its history (False).
    accept_without_history: bool = False
    #: A re-solve of the pair's registration that moves a bias by more than this many of its
    #: previous sigmas forgets every look: they were compensated with an estimate the new
    #: one refutes (the two radars' first estimate rests on a few pairs of one area).
    reset_sigma: float = 4.0
    #: Re-compensate the remembered looks whenever the registration is re-solved: each entry's
    #: mean residual moves by the change the new estimate makes to its two tracks' compensated
    #: positions (at their present positions), so the history tests every pair with the latest
    #: registration, not with the mix of the estimates its looks were taken with.
    recompensate: bool = True
    #: Once registered, every pair of tracks closer than this (m, compensated ECEF) is looked
    #: at on every update (a true pair's compensated difference is a few hundred metres).
    registered_search_m: float = 5_000.0
    #: ... and those whose compensated single-update chi-square (3 dof) exceeds this are no
    #: hypotheses at all (99.999 %): their entry is removed.
    registered_gate_chi2: float = 25.9
    #: What one lost match costs, in the costs' chi-square-excess units: the "partner not among
    #: the candidates" hypothesis of the probability, and the joint ambiguity rule's unmatched
    #: cost (:mod:`.assignment`); 8.3 = the excess of a 3-dof chi-square at its 1 % tail.
    null_cost: float = 8.3
    #: Logistic calibration of the posterior (see the module docstring): the maximum-likelihood
    #: fit over the pairs with accumulated evidence of the dense-formation study's one-run
    #: scenes with seeds 7 and 11 (the study's ``fit_calibration``, docs/evaluation/dense.md:
    #: 1.11 / 2.72 and 1.02 / 2.39 on each, the mean taken); other seeds are the held-out check
    #: (a test).  The posterior alone is too modest: a track's rivals inside the gate are
    #: mostly far less likely than the null hypothesis weighs them.
    calibration_slope: float = 1.07
    calibration_offset: float = 2.56


def registered_residuals(
    a: PredictedTracks, b: PredictedTracks, extra_a: FloatArray, extra_b: FloatArray, params: EvidenceParams
) -> tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray]:
    """The looks of one registered update: rows ``(ia, ib)`` of the bias-compensated snapshots
    within the search distance and the gate, their residual ``x_A - x_B`` and its random and
    common covariances (``P_A + P_B``; the registration's ``extra_a + extra_b``), all in B's
    ENU orientation (A's for a reference source B)."""
    ia, ib, _ = candidate_pairs(a.position, b.position, params.registered_search_m)
    site = b.site if b.site is not None else a.site
    rot = np.eye(3) if site is None else site.rotation  # ENU -> ECEF; its transpose back
    r = (a.position[ia] - b.position[ib]) @ rot
    s_noise = congruence(rot.T, a.pos_cov[ia] + b.pos_cov[ib])
    s_common = congruence(rot.T, extra_a[ia] + extra_b[ib])
    q, ok = mahalanobis3(r, s_noise + s_common)
    keep = ok & (q <= params.registered_gate_chi2)
    return ia[keep], ib[keep], r[keep], s_noise[keep], s_common[keep]


def posterior(
    track_a: NDArray[Any], track_b: NDArray[Any], cost: FloatArray, params: EvidenceParams
) -> FloatArray:
    """The calibrated posterior of each hypothesis ``(track_a[k], track_b[k])`` of cost
    ``cost[k]`` (chi-square excess, ``-2 ln`` likelihood up to a constant; inf: no hypothesis)
    among the hypotheses sharing one of its tracks and the null one (module docstring)."""
    if len(cost) == 0:
        return np.empty(0)
    # Likelihoods relative to the null hypothesis: exp(-(cost - null)/2), clipped.
    lik = np.exp(-0.5 * np.clip(cost - params.null_cost, -600.0, 600.0))
    _, inv_a = np.unique(track_a, return_inverse=True)
    _, inv_b = np.unique(track_b, return_inverse=True)
    sum_a = np.bincount(inv_a, lik)[inv_a]
    sum_b = np.bincount(inv_b, lik)[inv_b]
    p = np.clip(lik / (sum_a + sum_b - lik + 1.0), 1e-9, 1.0 - 1e-9)
    z = params.calibration_slope * np.log(p / (1.0 - p)) + params.calibration_offset
    return np.asarray(1.0 / (1.0 + np.exp(-z)))


def accumulated_chi2(rbar: FloatArray, sbar: FloatArray, n_eff: FloatArray, common: FloatArray) -> FloatArray:
    """``q = rbar^T (Sbar / n + C)^-1 rbar`` per entry (NaN where the covariance is singular)."""
    if len(rbar) == 0:
        return np.empty(0)
    q, ok = mahalanobis3(rbar, sbar / n_eff[:, None, None] + common)
    return np.where(ok, q, np.nan)


class EvidenceBook:
    """Columnar evidence of one radar pair's candidate pairs (see the module docstring)."""

    _columns = (
        *("track_a", "track_b", "keys"),
        *("weight", "n_eff", "rbar", "sbar", "common", "res_time_s", "looks", "q", "q_rel"),
    )

    def __init__(self, params: EvidenceParams | None = None) -> None:
        self.params = params or EvidenceParams()
        # The candidate pairs' tracks, by the identifiers given (track keys or ids, as a pair
        # book's, :mod:`.pairkeys`), and their pair keys.
        self.track_a: NDArray[Any] = np.empty(0, dtype=np.int64)
        self.track_b: NDArray[Any] = np.empty(0, dtype=np.int64)
        self.keys: NDArray[Any] = np.empty(0, dtype=np.int64)
        # The residual's running mean (module docstring) ...
        self.weight = np.empty(0)
        self.n_eff = np.empty(0)
        self.rbar = np.empty((0, 3))
        self.sbar = np.empty((0, 3, 3))
        self.common = np.empty((0, 3, 3))
        self.res_time_s = np.empty(0)
        self.looks = np.empty(0, dtype=np.int64)
        #: ... its accumulated chi-square (NaN before the first residual) ...
        self.q = np.empty(0)
        #: ... and the same without the common part ``C``.
        self.q_rel = np.empty(0)

    def __len__(self) -> int:
        return int(self.keys.shape[0])

    def clear(self) -> None:
        """Forget every entry."""
        self._keep(np.zeros(len(self), dtype=bool))

    def forget_tracks(self, track_a: NDArray[Any], track_b: NDArray[Any]) -> int:
        """Forget every entry whose A track is among ``track_a`` or whose B track is among
        ``track_b`` (a few ids: a swap, :mod:`.swap`); how many entries went."""
        if len(self) == 0:
            return 0
        gone = isin_sorted(self.track_a, np.unique(track_a)) | isin_sorted(self.track_b, np.unique(track_b))
        n = int(np.count_nonzero(gone))
        if n:
            self._keep(~gone)
        return n

    def _keep(self, keep: NDArray[np.bool_]) -> None:
        for name in self._columns:
            setattr(self, name, getattr(self, name)[keep])

    def _ensure(self, track_a: NDArray[Any], track_b: NDArray[Any]) -> NDArray[np.intp]:
        """The entry of each pair ``(track_a[k], track_b[k])`` (unique pairs), new ones empty."""
        keys = pair_keys(track_a, track_b)
        idx = find(self.keys, keys)
        fresh = np.flatnonzero(idx < 0)
        if fresh.size:
            m, start = fresh.size, len(self)
            add = {
                "track_a": np.asarray(track_a)[fresh],
                "track_b": np.asarray(track_b)[fresh],
                "keys": keys[fresh],
                "weight": np.zeros(m),
                "n_eff": np.zeros(m),
                "rbar": np.zeros((m, 3)),
                "sbar": np.zeros((m, 3, 3)),
                "common": np.zeros((m, 3, 3)),
                "res_time_s": np.full(m, -np.inf),
                "looks": np.zeros(m, dtype=np.int64),
                "q": np.full(m, np.nan),
                "q_rel": np.full(m, np.nan),
            }
            for name in self._columns:
                setattr(self, name, joined(getattr(self, name), add[name]))
            idx = idx.copy()
            idx[fresh] = start + np.arange(m)
        return idx

    def _weights(self, dt: FloatArray, first: NDArray[np.bool_]) -> tuple[FloatArray, FloatArray]:
        """Forgetting of the old evidence and the information of one more look (module docstring)."""
        prm = self.params
        decay = np.where(first, 0.0, np.exp(-np.where(first, 0.0, dt) / prm.horizon_s))
        rho = np.exp(-np.where(first, 0.0, dt) / prm.error_correlation_s)
        return decay, np.where(first, 1.0, (1.0 - rho) / (1.0 + rho))

    def observe(
        self,
        time_s: float,
        track_a: NDArray[Any],
        track_b: NDArray[Any],
        residual: FloatArray,
        noise_cov: FloatArray,
        common_cov: FloatArray | None = None,
    ) -> None:
        """Add one update's residuals of the pairs ``(track_a[k], track_b[k])`` (unique pairs);
        a pair already observed at ``time_s`` keeps its evidence (one look per update)."""
        n = len(track_a)
        if n == 0:
            return
        common = np.zeros((n, 3, 3)) if common_cov is None else common_cov
        idx = self._ensure(track_a, track_b)
        upd = self.res_time_s[idx] < time_s
        e = idx[upd]
        if e.size == 0:
            return
        first = self.looks[e] == 0
        decay, info = self._weights(time_s - self.res_time_s[e], first)
        w_old = decay * self.weight[e]
        w_new = w_old + 1.0
        self.rbar[e] = (w_old[:, None] * self.rbar[e] + residual[upd]) / w_new[:, None]
        self.sbar[e] = (w_old[:, None, None] * self.sbar[e] + noise_cov[upd]) / w_new[:, None, None]
        self.weight[e] = w_new
        self.n_eff[e] = decay * self.n_eff[e] + info
        self.common[e] = common[upd]
        self.res_time_s[e] = time_s
        self.looks[e] += 1
        self._test(e)

    def _test(self, e: NDArray[np.intp]) -> None:
        """The accumulated chi-squares of the entries ``e`` (observed at least once), with the
        common part and without it."""
        rbar, sbar, n_eff = self.rbar[e], self.sbar[e], self.n_eff[e]
        self.q[e] = accumulated_chi2(rbar, sbar, n_eff, self.common[e])
        self.q_rel[e] = accumulated_chi2(rbar, sbar, n_eff, np.zeros_like(sbar))

    def shift(self, entries: NDArray[np.intp], delta: FloatArray) -> None:
        """Move the mean residual of the entries ``entries`` (unique) by ``delta[k]`` and test
        them again: the registration their looks were compensated with was re-solved
        (``recompensate``)."""
        if len(entries) == 0:
            return
        self.rbar[entries] += delta
        self._test(entries)

    def prune(
        self,
        time_s: float,
        present_a: NDArray[Any],
        present_b: NDArray[Any],
        unobserved_present: bool = False,
    ) -> None:
        """Forget entries whose track left, or not looked at for ``forget_after_s``; with
        ``unobserved_present`` also those without a residual at ``time_s`` although both tracks
        are present (once registered every candidate within the gate gets one: a pair that did
        not has failed the gate, and is no hypothesis any more)."""
        if len(self) == 0:
            return
        here = isin_sorted(self.track_a, present_a) & isin_sorted(self.track_b, present_b)
        keep = here & (self.res_time_s >= time_s - self.params.forget_after_s)
        if unobserved_present:
            keep &= self.res_time_s >= time_s
        if not keep.all():
            self._keep(keep)

    def rejected(self) -> NDArray[np.bool_]:
        """Entries whose accumulated residual test fails at ``alpha`` (3 dof) after ``min_looks``."""
        return np.asarray((self.looks >= self.params.min_looks) & (self.q > chi2_upper(self.params.alpha, 3)))

    def probability(self) -> FloatArray:
        """Each entry's calibrated posterior (module docstring), NaN without a look."""
        have = np.isfinite(self.q_rel)
        p = posterior(self.track_a, self.track_b, np.where(have, self.q_rel - 3.0, np.inf), self.params)
        return np.where(have, p, np.nan)

    def rivals_better(self, entries: NDArray[np.intp], margin: float) -> NDArray[np.bool_]:
        """For entries ``entries``: is there a rival (an entry sharing one of its tracks) whose
        accumulated residual chi-square is lower by more than ``margin``?"""
        if len(entries) == 0 or len(self) == 0:
            return np.zeros(len(entries), dtype=bool)
        q = np.where(np.isfinite(self.q_rel), self.q_rel, np.inf)
        ua, inv_a = np.unique(self.track_a, return_inverse=True)
        ub, inv_b = np.unique(self.track_b, return_inverse=True)
        best_a = np.full(len(ua), np.inf)
        np.minimum.at(best_a, inv_a, q)
        best_b = np.full(len(ub), np.inf)
        np.minimum.at(best_b, inv_b, q)
        mine = q[entries]
        return np.asarray((best_a[inv_a[entries]] < mine - margin) | (best_b[inv_b[entries]] < mine - margin))
