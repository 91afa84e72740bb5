"""Velocity fuzzy clustering with consistent merging: the Hough paper's Section 2, fixed.

Steps 1-6 are the paper's (Eq. 7-10, :mod:`.clustering`): every plot ``i`` and later plot
``k`` give a candidate set ``A_ik = {i, k} U {j : u_ijk > u_ikk}``.  Steps 7-8 as published
merge any two sets sharing two plots and output every merged set; with clutter on the line
and two targets on one line this chains sets across targets and clutter (one clutter plot
that fits both targets' velocities is enough), which is what measured badly.  What the paper
leaves open or gets wrong, and what is done here instead:

* **7a, seeds** -- a candidate set is kept only if its plots are one constant-velocity target
  (:func:`service.tracking.cvfit.consistent`: every plot within its location error of the
  set's weighted least-squares line ``x_0 + v t``, total chi-square below its quantile, speed
  inside the gate, enough time span).  This is the paper's own premise for Step 5 ("all
  plots of a true track have about the same velocity") applied to the whole set, not only to
  the three plots ``i, j, k``.
* **7, merge** -- two sets sharing ``merge_overlap`` (2) plots are merged only if their union
  passes the same test.  Candidate pairs are merged in rounds (largest union first, each set
  in at most one merge per round, :func:`service.tracking.logic.resolve_conflicts`); sets
  contained in another set are dropped as redundant.
* **Equal time stamps** -- no velocity for ``|t_i - t_j| < min_dt`` (Eq. 7), but the CV fit
  compares such plots by distance against their location errors, which is the paper's rule.
* **8, output** -- sets may still overlap (crossing targets share the plots near the
  crossing).  The largest consistent set is taken first (ties: smaller chi-square per degree
  of freedom), its plots leave every other set, optionally the preliminary track's remaining
  plots inside its prediction gate are absorbed, and it starts a track if it still has
  ``min_plots`` plots; repeat.  Each plot therefore starts at most one track.
"""

from __future__ import annotations

import numpy as np

from service.geo import FloatArray
from service.tracking.clustering import candidate_sets, log_closeness
from service.tracking.cvfit import PlotStats, consistent, fit_sets, plot_stats, residual_d2
from service.tracking.groups import IntArray
from service.tracking.params import ClusterParams

BoolMatrix = np.ndarray


def _consistent(stats: PlotStats, sets: BoolMatrix, p: ClusterParams) -> tuple[np.ndarray, np.ndarray]:
    """(ok, cost) per set: the CV test of :func:`cvfit.consistent` with this module's params,
    and the selection cost ``-sum_p (plot_llr - d_p^2 / 2)`` (a track log-likelihood ratio
    against clutter: more plots, and plots closer to the fitted line, are better)."""
    speeds = (p.min_speed_mps, p.max_speed_mps)
    ok, fits = consistent(stats, sets, p.min_span_s, p.plot_gate_chi2, p.fit_confidence, speeds)
    d2 = residual_d2(stats, fits, predicted=False)
    score = np.where(sets, p.plot_llr - 0.5 * d2, 0.0).sum(axis=1)
    return ok, -score


def drop_redundant(sets: BoolMatrix, subsets: bool = True) -> BoolMatrix:
    """Remove duplicate sets and (``subsets``) sets contained in another set (kept: the
    containing set).  Only for sets that already passed the consistency test: a consistent
    set inside an inconsistent one must not be dropped for it."""
    if sets.shape[0] <= 1:
        return sets
    packed = np.ascontiguousarray(np.packbits(sets, axis=1))
    keys = packed.view(np.dtype((np.void, packed.shape[1]))).ravel()
    _, first = np.unique(keys, return_index=True)
    sets = sets[np.sort(first)]
    if not subsets:
        return sets
    f = sets.astype(np.float32)
    inter = f @ f.T  # exact for counts below 2^24
    size = f.sum(axis=1)
    inside = inter >= size[:, None] - 0.5  # [a, b]: a is a subset of b
    np.fill_diagonal(inside, False)  # rows are unique now: a subset of b != a is proper
    return np.asarray(sets[~inside.any(axis=1)])


def converge(stats: PlotStats, sets: BoolMatrix, allowed: np.ndarray, p: ClusterParams) -> BoolMatrix:
    """Step 7 (fixed): every set becomes the ``allowed`` plots inside the prediction gate
    ``r^T (C_p + H P H^T)^-1 r <= plot_gate_chi2`` of its own CV fit, refitted and re-gated
    until it no longer changes (at most ``grow_rounds`` times), all sets at once; an update
    that would make the set inconsistent (:func:`_consistent`) is not taken.

    A set thereby absorbs the plots of every other set that fit its straight-line motion, and
    drops its own plots that do not; sets that converge to the same plots are then one set
    (:func:`drop_redundant`).  This is the paper's merge of overlapping sets restricted to
    velocity-consistent plots: a union is only ever formed of plots that fit one CV track.
    Degenerate fits keep their set unchanged (and fail the consistency test later).  Only the
    sets updated in the previous round are refitted (an unchanged set would give the same
    update again).
    """
    active = np.arange(sets.shape[0])
    for _ in range(p.grow_rounds):
        if active.shape[0] == 0:
            break
        cur = sets[active]
        fits = fit_sets(stats, cur, p.min_span_s)
        d2 = residual_d2(stats, fits, predicted=True)
        new = np.where(fits.valid[:, None], allowed[None, :] & (d2 <= p.plot_gate_chi2), cur)
        changed = (new != cur).any(axis=1)
        if not changed.any():
            break
        ok, _ = _consistent(stats, new[changed], p)
        upd = np.flatnonzero(changed)[ok]  # an update that breaks consistency is not taken
        if upd.shape[0] == 0:
            break
        sets = sets.copy()
        sets[active[upd]] = new[upd]
        active = active[upd]
    return sets


def select_tracks(stats: PlotStats, sets: BoolMatrix, p: ClusterParams) -> list[np.ndarray]:
    """Step 8 (fixed): disjoint tracks, best score first (see module docstring).

    The best consistent candidate is taken; its plots leave every other candidate, which are
    then re-tested; repeat.  With ``extend``, a taken track first absorbs the untaken plots in
    its prediction gate (:func:`converge`).  One pass per taken or discarded candidate; only
    the candidates that lost plots to a taken track are re-tested (the others are unchanged).
    """
    n = stats.tau.shape[0]
    taken = np.zeros(n, dtype=bool)
    out: list[np.ndarray] = []
    sets = sets.copy()
    ok, cost = _consistent(stats, sets, p)
    ok &= sets.sum(axis=1) >= min(p.min_plots, 3)
    for _ in range(sets.shape[0]):  # one taken or discarded candidate per pass
        if not ok.any():
            break
        best = int(np.flatnonzero(ok)[np.argmin(cost[ok])])
        member = sets[best].copy()
        sets, ok, cost = np.delete(sets, best, axis=0), np.delete(ok, best), np.delete(cost, best)
        if p.extend:
            member = converge(stats, member[None, :], ~taken, p)[0]
        final_ok, final_cost = _consistent(stats, member[None, :], p)
        if member.sum() >= p.min_plots and final_ok[0] and -final_cost[0] >= p.min_track_score:
            out.append(np.flatnonzero(member))
            taken |= member
            hit = (sets & member[None, :]).any(axis=1)  # these lose plots: re-test them
            if hit.any():
                sets[hit] &= ~taken
                ok[hit], cost[hit] = _consistent(stats, sets[hit], p)
                ok[hit] &= sets[hit].sum(axis=1) >= min(p.min_plots, 3)
    return out


def _reassign(stats: PlotStats, M: BoolMatrix, p: ClusterParams) -> BoolMatrix:
    """Give every plot to the track whose CV line it fits best (within ``plot_gate_chi2``;
    plots in no gate belong to none), refit, repeat (``refine_rounds`` times)."""
    n = stats.tau.shape[0]
    pool = np.ones(n, dtype=bool)
    for _ in range(p.refine_rounds):
        fits = fit_sets(stats, M, p.min_span_s)
        d2 = residual_d2(stats, fits, predicted=False)
        d2 = np.where(fits.valid[:, None] & (d2 <= p.plot_gate_chi2), d2, np.inf)
        best = np.argmin(d2, axis=0)
        new = np.zeros_like(M)
        owned = pool & np.isfinite(d2[best, np.arange(n)])
        new[best[owned], np.flatnonzero(owned)] = True
        if (new == M).all():
            break
        M = new
    return M


def _merge_tracks(stats: PlotStats, M: BoolMatrix, p: ClusterParams) -> BoolMatrix:
    """Merge tracks that are the same target: their CV states ``theta = [x_0, v]`` agree,
    ``(theta_a - theta_b)^T (P_a + P_b)^-1 (theta_a - theta_b) <= same_target_chi2`` (the
    fixed Step 7 applied to started tracks, e.g. two halves of one target).  Closest pair
    first, repeated over a handful of tracks."""
    for _ in range(M.shape[0]):  # at most one merge per pass, over a handful of tracks
        m = M.shape[0]
        if m < 2:
            break
        fits = fit_sets(stats, M, p.min_span_s)
        a, b = np.triu_indices(m, 1)
        dth = fits.theta[a] - fits.theta[b]
        d2 = np.einsum("ki,ki->k", dth, np.linalg.solve(fits.cov[a] + fits.cov[b], dth[..., None])[..., 0])
        d2 = np.where(fits.valid[a] & fits.valid[b], d2, np.inf)
        k = int(np.argmin(d2))
        if not d2[k] <= p.same_target_chi2:
            break
        keep = np.ones(m, dtype=bool)
        keep[[a[k], b[k]]] = False
        M = np.concatenate([M[keep], (M[a[k]] | M[b[k]])[None, :]])
    return M


def refine(stats: PlotStats, tracks: list[np.ndarray], p: ClusterParams) -> list[np.ndarray]:
    """Step 8 (fixed), last part: reassign shared and ambiguous plots to the track they fit
    best, merge tracks whose union is one consistent target, reassign again; tracks that end
    short of ``min_plots`` or ``min_track_score`` are dropped.  Greedy selection hands a plot
    to whichever track was taken first; near a crossing, or between two close parallel
    tracks, this puts it back where it fits."""
    if not tracks:
        return tracks
    n = stats.tau.shape[0]
    M = np.zeros((len(tracks), n), dtype=bool)
    for q, members in enumerate(tracks):  # loop over selected tracks (a handful)
        M[q, members] = True
    M = _reassign(stats, _merge_tracks(stats, _reassign(stats, M, p), p), p)
    ok, cost = _consistent(stats, M, p)
    keep = ok & (M.sum(axis=1) >= p.min_plots) & (-cost >= p.min_track_score)
    return [np.flatnonzero(row) for row in M[keep]]


def along_line(theta: FloatArray, fits_cov: FloatArray, normal_angle: float, p: ClusterParams) -> np.ndarray:
    """Whether fitted velocities run along the preliminary track's line (normal angle
    ``normal_angle``): ``|v . n| <= |v| sin(line_angle_deg) + 3 sigma(v . n)``.  The paper's
    premise: a track is a set of plots on a Hough line moving at one velocity, so its velocity
    is along that line; sets of clutter that happen to fit a straight motion across it are
    not tracks of that line."""
    nvec = np.array([np.cos(normal_angle), np.sin(normal_angle)])
    v = theta[:, 2:]
    vn = np.abs(v @ nvec)
    var = np.einsum("i,mij,j->m", nvec, fits_cov[:, 2:, 2:], nvec)
    tol = np.linalg.norm(v, axis=1) * np.sin(np.radians(p.line_angle_deg)) + 3.0 * np.sqrt(var)
    return np.asarray(vn <= tol)


def candidate_tracks(
    t: FloatArray, x: FloatArray, cov: FloatArray, p: ClusterParams, normal_angle: float | None = None
) -> BoolMatrix:
    """Steps 1-7 (7 fixed) on one preliminary track: consistent candidate sets, ``(m, S)``
    boolean over the given plots (any order; sorted by time internally).  With the line's
    ``normal_angle`` (rad), sets must also move along the line (:func:`along_line`)."""
    s = t.shape[0]
    if s < 3:
        return np.zeros((0, s), dtype=bool)
    order = np.argsort(t, kind="stable")  # Step 2
    tt, xx, cc = t[order], x[order], cov[order]
    xx = xx - xx.mean(axis=0)  # velocities are translation-free; keeps the LS sums small
    delta = np.sqrt(np.trace(cc, axis1=1, axis2=2))
    logd = log_closeness(tt, xx, delta, p)  # Step 3, Eq. (7)-(8)
    sets = candidate_sets(logd)  # Steps 4-6
    if sets.shape[0] == 0:
        return np.zeros((0, s), dtype=bool)
    stats = plot_stats(tt, xx, cc, float(tt[0]))
    sets = drop_redundant(sets, subsets=False)
    ok, _ = _consistent(stats, sets, p)  # 7a: seeds
    sets = converge(stats, sets[ok], np.ones(s, dtype=bool), p)  # Step 7 (fixed)
    ok, _ = _consistent(stats, sets, p)
    ok &= sets.sum(axis=1) >= p.min_plots
    if normal_angle is not None and ok.any():
        fits = fit_sets(stats, sets, p.min_span_s)
        ok &= along_line(fits.theta, fits.cov, normal_angle, p)
    sets = drop_redundant(sets[ok])
    out = np.zeros_like(sets)
    out[:, order] = sets  # back to the caller's plot order
    return out


def velocity_cluster(t: FloatArray, x: FloatArray, cov: FloatArray, p: ClusterParams) -> list[IntArray]:
    """Steps 1-8 with the fixes above on one preliminary track; index arrays into the plots.

    ``cov`` is each plot's ``(2, 2)`` location covariance; the paper's location error is
    ``delta = sqrt(trace cov)``.
    """
    sets = candidate_tracks(t, x, cov, p)
    if sets.shape[0] == 0:
        return []
    stats = plot_stats(t, x - x.mean(axis=0), cov, float(t.min()))
    tracks = refine(stats, select_tracks(stats, sets, p), p)  # Step 8 (fixed)
    return [np.asarray(m, dtype=np.intp) for m in tracks]


def global_tracks(
    t: FloatArray, x: FloatArray, cov: FloatArray, bands: list[tuple[IntArray, float]], p: ClusterParams
) -> list[IntArray]:
    """Steps 1-7 on every preliminary track (``bands``: plot indices), then Step 7 merging and
    Step 8 selection over the union of their candidate sets (``bands``: plot indices and the
    line's normal angle), so that one plot starts at most
    one track whichever line found it, and the best tracks are taken first (loop over lines).
    """
    n = t.shape[0]
    parts = []
    for band, normal_angle in bands:  # loop over preliminary tracks (Hough peaks)
        sub = candidate_tracks(t[band], x[band], cov[band], p, normal_angle)
        full = np.zeros((sub.shape[0], n), dtype=bool)
        full[:, band] = sub
        parts.append(full)
    if not parts:
        return []
    sets = np.concatenate(parts)
    if sets.shape[0] == 0:
        return []
    stats = plot_stats(t, x - x.mean(axis=0), cov, float(t.min()))
    sets = drop_redundant(sets)
    return [np.asarray(m, dtype=np.intp) for m in refine(stats, select_tracks(stats, sets, p), p)]
