"""Plain reference forms (loops, dense matrices) of the correlation code, that tests compare
the vectorised forms against.  Tests only: the service never calls them."""

from __future__ import annotations

import itertools

import numpy as np
import scipy.stats
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from service.correlation.assignment import _FORBIDDEN
from service.correlation.base import BoolArray, FloatArray, PredictedTracks
from service.correlation.gls import N_PARAMS
from service.correlation.topology import TopologyParams
from service.correlation.umeyama import yaw_matrix
from service.geo import Site


def brute_force_neighbours(pts: np.ndarray, i: int, prm: TopologyParams) -> list[int]:
    """Point ``i``'s neighbourhood by a full distance scan: the ``max_neighbours`` nearest,
    those within ``radius_m``, or among the ``min_neighbours`` nearest within ``max_radius_m``."""
    d = np.linalg.norm(pts - pts[i], axis=1)
    d[i] = np.inf
    order = np.argsort(d)[: prm.max_neighbours]
    return [
        int(j)
        for r, j in enumerate(order)
        if d[j] <= prm.radius_m or (r < prm.min_neighbours and d[j] <= prm.max_radius_m)
    ]


def umeyama_reference(x: FloatArray, y: FloatArray) -> tuple[FloatArray, float, FloatArray, float]:
    """Plain one-pair form of Umeyama's algorithm (tests only): returns ``M, c, t, e^2``."""
    n = x.shape[0]
    mx = x.mean(axis=0)
    my = y.mean(axis=0)
    var_x = float(((x - mx) ** 2).sum() / n)
    var_y = float(((y - my) ** 2).sum() / n)
    sigma = np.zeros((3, 3))
    for i in range(n):
        sigma += np.outer(y[i] - my, x[i] - mx) / n
    u, d, vt = np.linalg.svd(sigma)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1.0
    rot = u @ s @ vt
    c = float(np.trace(np.diag(d) @ s) / var_x)
    t = my - c * rot @ mx
    e2 = var_y - float(np.trace(np.diag(d) @ s)) ** 2 / var_x
    return rot, c, t, e2


def yaw_similarity_reference(x: FloatArray, y: FloatArray) -> tuple[float, float, FloatArray]:
    """Plain one-pair yaw fit (tests only), by brute-force normal equations: yaw, c, t."""
    n = x.shape[0]
    mx = x.mean(axis=0)
    my = y.mean(axis=0)
    a = b = v = 0.0
    for i in range(n):
        dx = x[i] - mx
        dy = y[i] - my
        a += (dx[0] * dy[0] + dx[1] * dy[1]) / n
        b += (dx[0] * dy[1] - dx[1] * dy[0]) / n
        v += (dx[0] ** 2 + dx[1] ** 2) / n
    yaw = float(np.arctan2(b, a))
    c = float(np.hypot(a, b) / v)
    rot = yaw_matrix(np.array(yaw))
    return yaw, c, my - c * rot @ mx


def assign_reference(
    index_a: NDArray[np.intp], index_b: NDArray[np.intp], cost: FloatArray, accepted: BoolArray, margin: float
) -> BoolArray:
    """Plain dense form of :func:`service.correlation.assignment.assign_unambiguous`."""
    chosen = np.zeros(index_a.shape[0], dtype=bool)
    acc = [k for k in range(index_a.shape[0]) if accepted[k] and np.isfinite(cost[k])]
    if not acc:
        return chosen
    na = int(index_a.max()) + 1
    nb = int(index_b.max()) + 1
    mat = np.full((na, nb), _FORBIDDEN)
    for k in acc:
        mat[index_a[k], index_b[k]] = cost[k]
    r_idx, c_idx = linear_sum_assignment(mat)
    for r, cc in zip(r_idx, c_idx, strict=True):
        if mat[r, cc] >= _FORBIDDEN:
            continue
        k = next(k for k in acc if index_a[k] == r and index_b[k] == cc)
        rivals = [cost[j] for j in acc if j != k and (index_a[j] == r or index_b[j] == cc)]
        if all(rv - cost[k] >= margin for rv in rivals):
            chosen[k] = True
    return chosen


def sequence_chi2_reference(r: FloatArray, d: FloatArray, c0: FloatArray) -> float:
    """Plain dense form of the joint chi-square (tests only): one candidate, ``r (n, 3)``."""
    n = r.shape[0]
    cov = np.zeros((3 * n, 3 * n))
    for i in range(n):
        for j in range(n):
            cov[3 * i : 3 * i + 3, 3 * j : 3 * j + 3] = c0 + (d[i] if i == j else 0.0)
    v = r.reshape(-1)
    return float(v @ np.linalg.solve(cov, v))


def similarity_gls_reference(
    x: FloatArray, y: FloatArray, s: FloatArray, sigma_scale: float, sigma_yaw_rad: float
) -> tuple[FloatArray, FloatArray, float, float]:
    """Plain one-candidate form (tests only): stacked 3m x 5 design, dense weight matrix.

    Returns ``theta, cov, Q (residual + prior), df_model``.
    """
    m = x.shape[0]
    rows = []
    for i in range(m):
        xe, xn, xu = x[i]
        rows.append([[xe, -xn, 1, 0, 0], [xn, xe, 0, 1, 0], [xu, 0, 0, 0, 1]])
    big_a = np.array(rows, dtype=float).reshape(3 * m, N_PARAMS)
    big_w = np.zeros((3 * m, 3 * m))
    for i in range(m):
        big_w[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = np.linalg.inv(s[i])
    lam = np.diag([1.0 / sigma_scale**2, 1.0 / sigma_yaw_rad**2, 0.0, 0.0, 0.0])
    theta0 = np.array([1.0, 0.0, 0.0, 0.0, 0.0])
    yy = y.reshape(-1)
    h_data = big_a.T @ big_w @ big_a
    h = h_data + lam
    theta = np.linalg.solve(h, big_a.T @ big_w @ yy + lam @ theta0)
    r = yy - big_a @ theta
    q = float(r @ big_w @ r + (theta - theta0) @ lam @ (theta - theta0))
    cov = np.linalg.inv(h)
    return theta, cov, q, float(np.trace(cov @ h_data))


def joint_regret_reference(
    ia: np.ndarray, ib: np.ndarray, c: np.ndarray, assigned: np.ndarray, unmatched_cost: float
) -> np.ndarray:
    """The joint rule's regret of each assigned candidate by enumerating, for every rival, the
    alternative assignment it forces (the two broken pairs' tracks re-paired or unmatched)."""
    n = len(ia)
    regret = np.full(n, np.inf)
    cost = {(int(ia[k]), int(ib[k])): float(c[k]) for k in range(n)}
    chosen = [k for k in range(n) if assigned[k]]
    by_a = {int(ia[k]): k for k in chosen}
    by_b = {int(ib[k]): k for k in chosen}
    for r in range(n):
        if assigned[r]:
            continue
        x, y = int(ia[r]), int(ib[r])
        kx, ky = by_a.get(x), by_b.get(y)
        change = c[r]
        if kx is not None:
            change -= c[kx]
        if ky is not None:
            change -= c[ky]
        if kx is not None and ky is not None:
            change += min(cost.get((int(ia[ky]), int(ib[kx])), np.inf), unmatched_cost)
        for k in (kx, ky):
            if k is not None:
                regret[k] = min(regret[k], change)
    return regret


def evidence_reference(
    looks: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]],
    horizon_s: float,
    correlation_s: float,
) -> tuple[np.ndarray, float, float]:
    """One pair's accumulated residual mean, effective looks and chi-square from its looks
    ``(time, r, S, C)`` by the explicit weighted sums: weight ``exp(-(t_last - t_k) / horizon)``
    on every look, the effective count by the recursion over the gaps."""
    t_last = looks[-1][0]
    w = np.array([np.exp(-(t_last - t) / horizon_s) for t, *_ in looks])
    rbar = sum(wk * r for wk, (_, r, _, _) in zip(w, looks, strict=True)) / w.sum()
    sbar = sum(wk * s for wk, (_, _, s, _) in zip(w, looks, strict=True)) / w.sum()
    n_eff = 1.0
    for (t0, *_), (t1, *_) in itertools.pairwise(looks):
        rho = np.exp(-(t1 - t0) / correlation_s)
        n_eff = np.exp(-(t1 - t0) / horizon_s) * n_eff + (1 - rho) / (1 + rho)
    cov = sbar / n_eff + looks[-1][3]
    return rbar, n_eff, float(rbar @ np.linalg.solve(cov, rbar))


def group_offset_reference(
    d: np.ndarray,
    s: np.ndarray,
    pos_a: np.ndarray,
    ia: np.ndarray,
    radius_m: float,
    support_bandwidth: float,
    starts: int,
    iterations: int,
    gate_chi2: float,
) -> dict[int, tuple[np.ndarray, int]]:
    """The local offset of every reference row and its number of matched candidates, by plain
    loops: voters are the candidates of the other A tracks within ``radius_m``; from each of
    the ``starts`` best-supported voters, per nearby track the candidate nearest the offset
    (within the gate), the offset their mean; the start matching the most tracks wins."""
    n = len(ia)
    var_h = 0.5 * (s[:, 0, 0] + s[:, 1, 1])
    voters = {
        int(i): [c for c in range(n) if ia[c] != i and np.linalg.norm(pos_a[ia[c]] - pos_a[i]) <= radius_m]
        for i in np.unique(ia)
    }
    every = sorted({c for v in voters.values() for c in v})
    scale = float(np.sqrt(np.median(var_h[every])))
    support = np.zeros(n)
    for c in range(n):
        for c2 in range(n):
            near = np.linalg.norm(pos_a[ia[c]] - pos_a[ia[c2]]) <= radius_m
            if ia[c2] != ia[c] and near:
                dd = d[c, :2] - d[c2, :2]
                support[c] += np.exp(-0.5 * dd @ dd / (support_bandwidth * scale) ** 2)
    out = {}
    for i, v in voters.items():
        if not v:
            continue
        results = []
        for start in sorted(v, key=lambda c: -support[c])[:starts]:
            off = d[start].copy()
            matched, qsum = 0, 0.0
            for _ in range(iterations):
                picks, qs = [], []
                for k in sorted({int(ia[c]) for c in v}):
                    mine = [c for c in v if ia[c] == k]
                    res = [d[c, :2] - off[:2] for c in mine]
                    q = [float(x @ np.linalg.solve(s[c, :2, :2], x)) for c, x in zip(mine, res, strict=True)]
                    if min(q) <= gate_chi2:
                        picks.append(mine[int(np.argmin(q))])
                        qs.append(min(q))
                if picks:
                    off = d[picks].mean(axis=0)
                matched, qsum = len(picks), sum(qs)
            results.append((matched, -qsum, off))
        best = max(results, key=lambda x: (x[0], x[1]))
        out[i] = (best[2], best[0])
    return out


def system_groups_reference(n: int, source: list[int], links: list[tuple[int, int, float]]) -> list[int]:
    """Plain form of :func:`service.fusion.system_tracks.groups`: every link strongest first
    (ties by member rows), joined unless the two groups share a source; groups numbered by
    their smallest member."""
    parent = list(range(n))
    sources = [{s} for s in source]

    def root(k: int) -> int:
        while parent[k] != k:
            k = parent[k]
        return k

    for a, b, _ in sorted(links, key=lambda x: (-x[2], x[0], x[1])):
        ra, rb = root(a), root(b)
        if ra != rb and not sources[ra] & sources[rb]:
            parent[rb] = ra
            sources[ra] |= sources[rb]
    roots = [root(k) for k in range(n)]
    first: dict[int, int] = {}
    for k, r in enumerate(roots):
        first.setdefault(r, k)
    order = sorted(first, key=lambda r: first[r])
    return [order.index(r) for r in roots]


def fuse_reference(
    x: list[np.ndarray], p: list[np.ndarray], reference: list[bool]
) -> tuple[np.ndarray, np.ndarray]:
    """Plain form of one group's fusion: fast covariance intersection of the radar members,
    references added in information form."""
    radar = [k for k, r in enumerate(reference) if not r]
    weights = [1.0 / np.trace(p[k]) for k in radar]
    total = sum(weights)
    info = np.zeros((3, 3))
    vec = np.zeros(3)
    for w, k in zip(weights, radar, strict=True):
        pk = np.linalg.inv(p[k])
        info += w / total * pk
        vec += w / total * pk @ x[k]
    for k, r in enumerate(reference):
        if r:
            pk = np.linalg.inv(p[k])
            info += pk
            vec += pk @ x[k]
    cov = np.linalg.inv(info)
    return cov @ vec, cov


def diverged_reference(
    position: FloatArray, pos_cov: FloatArray, links: list[tuple[int, int]], alpha: float
) -> list[bool]:
    """Per link, one at a time: the Mahalanobis distance of the members' position difference
    under their summed covariance, above chi-square's upper ``alpha`` quantile (3 dof)?"""
    gate = float(scipy.stats.chi2.isf(alpha, 3))
    out = []
    for a, b in links:
        d = position[a] - position[b]
        out.append(bool(d @ np.linalg.solve(pos_cov[a] + pos_cov[b], d) > gate))
    return out


def cfar_consistency_reference(
    x: np.ndarray, s: np.ndarray, gate: float, inflate: bool, min_pairs: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Plain form of :func:`service.correlation.cfar.consistent_pairs`, pair by pair: robust
    start (per-component median), inliers within the gate of it, each pair against the mean of
    the other inliers (a lone inlier: chi-square 0), inflation by the inliers' median
    chi-square over ``2 ln 2``; returns bias, its covariance, chi-square, passed, inflation."""
    n = len(x)
    start = np.array([np.median(x[:, 0]), np.median(x[:, 1])])
    inlier = [float((x[k] - start) @ np.linalg.solve(s[k], x[k] - start)) <= gate for k in range(n)]
    members = [k for k in range(n) if inlier[k]]
    q = np.zeros(n)
    for k in range(n):
        others = [o for o in members if o != k]
        if not others:
            q[k] = 0.0
            continue
        mean = sum(x[o] for o in others) / len(others)
        cov = sum(s[o] for o in others) / len(others) ** 2
        d = x[k] - mean
        q[k] = float(d @ np.linalg.solve(s[k] + cov, d))
    f = 1.0
    if inflate and len(members) >= min_pairs:
        f = max(1.0, float(np.median([q[k] for k in members])) / (2.0 * np.log(2.0)))
    q = q / f
    passed = np.array([q[k] <= gate for k in range(n)])
    ok = [k for k in range(n) if passed[k]]
    bias = sum(x[k] for k in ok) / len(ok)
    bias_cov = f * sum(s[k] for k in ok) / len(ok) ** 2
    return np.asarray(bias), np.asarray(bias_cov), q, passed, f


def cfar_jump_log_bound_reference(
    s: np.ndarray, sigma_minor: np.ndarray, sigma_major: np.ndarray, jumps: list[int]
) -> list[float]:
    """Plain form of :func:`service.correlation.cfar.jump_log_bound`: for each jump ``k`` the sum
    over the entries ``q <= k`` (those with sigmas) of ``ln(erf(s_k / (sqrt2 s1_q)) erf(s_k /
    (sqrt2 s2_q)))``, a zero sigma counting as no constraint."""
    from math import erf, log, sqrt

    out = []
    for k in jumps:
        total = 0.0
        for q in range(min(k + 1, len(sigma_minor))):
            f = 1.0
            for sig in (sigma_minor[q], sigma_major[q]):
                if sig > 0:
                    f *= erf(s[k] / (sqrt(2.0) * sig))
            total += log(f) if f > 0 else -np.inf
        out.append(total)
    return out


def cfar_pair_chi2_reference(
    ref: np.ndarray, comp: np.ndarray, ref_cov: np.ndarray, radar_cov: np.ndarray, extra: np.ndarray
) -> np.ndarray:
    """Plain form of :func:`service.correlation.cfar.pair_chi2`: every reference row against
    every compensated radar row, ``r^T S^-1 r`` by ``np.linalg.solve``."""
    out = np.zeros((len(ref), len(comp)))
    for i in range(len(ref)):
        for j in range(len(comp)):
            dr = comp[j, 0] - ref[i, 0]
            da = (comp[j, 1] - ref[i, 1] + 180.0) % 360.0 - 180.0
            r = np.array([dr, da])
            out[i, j] = r @ np.linalg.solve(ref_cov[i] + radar_cov[j] + extra, r)
    return out


def clear_reference(
    index_a: list[int], index_b: list[int], cost: list[float], accepted: list[bool], margin: float
) -> list[bool]:
    """:func:`service.correlation.prompt.clear_of_rivals` by a loop over candidate pairs: an
    accepted candidate of finite cost whose every rival sharing a track (finite cost) costs at
    least ``margin`` more."""
    out = []
    for k, (i, j, c, ok) in enumerate(zip(index_a, index_b, cost, accepted, strict=True)):
        rivals = [
            cost[m]
            for m in range(len(cost))
            if m != k and (index_a[m] == i or index_b[m] == j) and np.isfinite(cost[m])
        ]
        out.append(bool(ok and np.isfinite(c) and all(r - c >= margin for r in rivals)))
    return out


def isolated_reference(
    positions: FloatArray,
    velocities: FloatArray,
    confirmed: list[bool],
    up: FloatArray,
    rows: list[int],
    radius_m: float,
    velocity_mps: float,
) -> list[bool]:
    """:func:`service.correlation.prompt.isolated` by a loop: no other track within ``radius_m``
    horizontally (the component along ``up`` removed) that is tentative, or confirmed with a
    horizontal velocity within ``velocity_mps``."""
    out = []
    for i in rows:
        near = False
        for j in range(len(positions)):
            if j == i:
                continue
            d = positions[j] - positions[i]
            d = d - float(d @ up) * up
            dv = velocities[j] - velocities[i]
            dv = dv - float(dv @ up) * up
            with_it = bool(np.sqrt(float(dv @ dv)) < velocity_mps)
            near |= bool(np.sqrt(float(d @ d)) <= radius_m) and (not confirmed[j] or with_it)
        out.append(not near)
    return out


def within_reference(
    positions: FloatArray, anchors: FloatArray, reach_m: float, busy: list[int]
) -> list[int]:
    """``service.correlation.correlator._within`` by a loop: the rows within ``reach_m`` of
    any (finite) anchor, not among ``busy``, ascending."""
    out = []
    for i, p in enumerate(positions):
        near = any(
            bool(np.all(np.isfinite(q))) and float(np.sqrt(np.sum((p - q) ** 2))) <= reach_m for q in anchors
        )
        if near and i not in busy:
            out.append(i)
    return out


def robust_covariance_reference(
    scores: FloatArray, clusters: list[tuple[str, ...]], cov: FloatArray, prior: FloatArray
) -> FloatArray:
    """``service.correlation.registration._robust_covariance`` by a double loop over rows: the
    meat ``diag(prior) + G/(G-1) sum_i sum_j s_i s_j^T`` over the rows ``i``, ``j`` whose
    cluster keys share one (``clusters[i]``: a row's radar or reference tracks), ``G`` the fewer
    of the distinct keys and the distinct key tuples, then ``cov meat cov``.  ``scores (rows,
    n)``: each row's score ``G^T W r`` in every column.  A row's only key its track pair gives
    the sandwich over track pairs."""
    n_rows = scores.shape[0]
    meat = np.zeros((scores.shape[1], scores.shape[1]))
    for i in range(n_rows):
        for j in range(n_rows):
            if set(clusters[i]) & set(clusters[j]):
                meat += np.outer(scores[i], scores[j])
    g = min(len({k for c in clusters for k in c}), len(set(clusters)))
    return np.asarray(cov @ (np.diag(prior) + meat * (g / (g - 1))) @ cov)


def registration_jacobian(site: Site, p: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Plain form of a registration row's ``G`` (service/correlation/registration.py): the five
    terms' effect on one point, through the polar coordinates (trigonometry, one point): range,
    azimuth and elevation offsets, range gain (a stretch along the line of sight, ppm) and
    time-stamp bias (``-tau v``)."""
    from service.correlation.registration import GAIN, N_TERMS, PPM, TIME
    from service.geo import polar_jacobian

    r, az, el = (float(np.ravel(x)[0]) for x in site.ecef_to_polar(p[None]))
    g = np.zeros((3, N_TERMS))
    g[:, :3] = site.rotation @ polar_jacobian(r, az, el)
    g[:, GAIN] = (p - site.origin_ecef) * PPM
    g[:, TIME] = -v
    return g


def registration_remove(site: Site, p: np.ndarray, v: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Plain form of removing the five terms ``b`` from one point: the model's exact inverse,
    a polar round trip, then ``+tau v``."""
    from service.correlation.registration import GAIN, PPM, TIME

    r, az, el = (float(np.ravel(x)[0]) for x in site.ecef_to_polar(p[None]))
    q = site.polar_to_ecef((r - b[0]) / (1.0 + b[GAIN] * PPM), az - np.degrees(b[1]), el - np.degrees(b[2]))
    return np.ravel(q) + b[TIME] * v


def track_keys_reference(tables: list[list[str]], limit: int) -> list[list[int]]:
    """Track keys by a dict per table (service.correlation.pairkeys.TrackKeys): a track keeps its
    key while it is in consecutive tables; any other id takes the next number (modulo ``limit``)."""
    last: dict[str, int] = {}
    counter = 0
    out = []
    for ids in tables:
        now = {}
        keys = []
        for track in ids:
            if track in last:
                key = last[track]
            else:
                key, counter = counter, (counter + 1) % limit
            now[track] = key
            keys.append(key)
        last = now
        out.append(keys)
    return out


def lone_reference(
    a: PredictedTracks,
    b: PredictedTracks,
    pairs: list[tuple[int, int]],
    gate_m: float,
    radius_m: float,
    max_rotation_deg: float,
    alpha: float,
) -> list[bool]:
    """The geometry of :func:`service.correlation.svd_topology.lone_candidates` by a loop:
    each track the other's only candidate within ``gate_m``, and no other track of its own
    radar within ``radius_m`` (3-D distances), counting only tracks whose velocity could be
    the track's own (each velocity in the site's ENU frame, A's turned into B's orientation:
    the speeds' difference and the heading difference beyond ``max_rotation_deg``, against the
    two velocity covariances' mean horizontal variance, chi-square with 2 dof at ``alpha``)."""
    assert a.site is not None and b.site is not None
    m0 = b.site.rotation.T @ a.site.rotation
    limit = float(scipy.stats.chi2.isf(alpha, 2))

    def same(s: PredictedTracks, i: int, t: PredictedTracks, j: int) -> bool:
        u, w = s.enu_velocity[i], t.enu_velocity[j]
        if s is not t:  # into the other radar's orientation (Eq. 3); within one radar as it is
            u = m0 @ u if s is a else m0.T @ u
        su, sw = float(np.hypot(u[0], u[1])), float(np.hypot(w[0], w[1]))
        turn = abs(np.arctan2(u[0] * w[1] - u[1] * w[0], u[0] * w[0] + u[1] * w[1]))
        excess = max(turn - np.radians(max_rotation_deg), 0.0) * 0.5 * (su + sw)
        var = (np.trace(s.vel_cov[i]) + np.trace(t.vel_cov[j])) / 3.0
        if not (np.isfinite(var) and var > 0):
            return True  # (no velocity error known: no test)
        return bool((su - sw) ** 2 + excess**2 <= limit * var)

    def rivals(s: PredictedTracks, i: int, t: PredictedTracks, r: float) -> int:
        return sum(
            float(np.sqrt(np.sum((t.position[j] - s.position[i]) ** 2))) <= r and same(s, i, t, j)
            for j in range(len(t))
        )

    return [
        same(a, i, b, j)
        and same(b, j, a, i)
        and rivals(a, i, b, gate_m) == 1
        and rivals(b, j, a, gate_m) == 1
        and rivals(a, i, a, radius_m) == 1
        and rivals(b, j, b, radius_m) == 1
        for i, j in pairs
    ]
