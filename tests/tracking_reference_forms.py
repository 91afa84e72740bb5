"""Plain reference forms (loops, dense matrices) of the tracking code, that tests compare the
vectorised forms against.  Tests only: the service never calls them."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from service.geo import FloatArray
from service.tracking.assignment import _FORBIDDEN
from service.tracking.groups import IntArray
from service.tracking.params import ClusterParams


def assign_reference(
    n_rows: int, n_cols: int, rows: IntArray, cols: IntArray, cost: FloatArray, miss_cost: float
) -> IntArray:
    """Plain reference: one dense LSA over every track and plot (for tests)."""
    if rows.shape[0] == 0:
        return np.empty(0, dtype=np.intp)
    mat = np.full((n_rows, n_cols + n_rows), _FORBIDDEN)
    index = np.full((n_rows, n_cols), -1, dtype=np.intp)
    for k in range(rows.shape[0]):
        mat[rows[k], cols[k]] = cost[k]
        index[rows[k], cols[k]] = k
    for r in range(n_rows):
        mat[r, n_cols + r] = miss_cost
    r_idx, c_idx = linear_sum_assignment(mat)
    out = [int(index[r, c]) for r, c in zip(r_idx, c_idx, strict=True) if c < n_cols]
    return np.sort(np.array(out, dtype=np.intp))


def fit_set_reference(
    t: FloatArray, xy: FloatArray, cov: FloatArray, t_ref: float
) -> tuple[FloatArray, float]:
    """Plain loop form of one set's fit (for tests): ``(theta, chi2)``."""
    A = np.zeros((4, 4))
    b = np.zeros(4)
    c = 0.0
    for k in range(t.shape[0]):
        H = np.array([[1.0, 0.0, t[k] - t_ref, 0.0], [0.0, 1.0, 0.0, t[k] - t_ref]])
        W = np.linalg.inv(cov[k])
        A += H.T @ W @ H
        b += H.T @ W @ xy[k]
        c += float(xy[k] @ W @ xy[k])
    theta = np.asarray(np.linalg.solve(A, b), dtype=float)
    return theta, c - float(b @ theta)


def velocity_cluster_reference(
    t: FloatArray, x: FloatArray, delta: FloatArray, p: ClusterParams
) -> list[IntArray]:
    """Plain loop form of Steps 1-8 with Eq. (9) evaluated explicitly (for tests)."""
    s = t.shape[0]
    if s < 3:
        return []
    order = sorted(range(s), key=lambda q: (t[q], q))
    tt, xx, dd = t[order], x[order], delta[order]

    def vel(i: int, j: int) -> np.ndarray | None:
        if abs(tt[j] - tt[i]) < p.min_dt_s:
            return None
        return np.asarray((xx[j] - xx[i]) / (tt[j] - tt[i]))

    def logd(i: int, j: int, k: int) -> float:
        vij, vik = vel(i, j), vel(i, k)
        if vij is None or vik is None:
            return -np.inf
        dij = max(float(np.linalg.norm(xx[i] - xx[j])), 1e-6)
        dik = max(float(np.linalg.norm(xx[i] - xx[k])), 1e-6)
        if j != k:
            num = float(np.sum((vij - vik) ** 2)) * (dd[i] * dd[j] * dd[k]) ** p.eta
            return -num / (dij**p.eta * dik**p.eta)
        return -p.lam * p.delta_v_mps**2 * (dd[i] * dd[k] ** 2) ** p.eta / dik ** (2 * p.eta)

    sets: list[set[int]] = []
    for i in range(s):
        rows = list(range(i + 1, s))
        for k in rows:
            col = [logd(i, j, k) for j in rows]
            if not np.isfinite(logd(i, k, k)):
                continue
            e = np.array(col) / (p.c - 1.0)
            top = np.max(e)
            u = e - (top + np.log(np.sum(np.exp(e - top))))  # log of Eq. (9), no underflow
            u_kk = u[rows.index(k)]
            js = {j for j, uj in zip(rows, u, strict=True) if j != k and uj > u_kk}
            if js:
                sets.append({i, k} | js)
    changed = True
    while changed:
        changed = False
        for a in range(len(sets)):
            for b in range(a + 1, len(sets)):
                if sets[a] and sets[b] and len(sets[a] & sets[b]) >= p.merge_overlap:
                    sets[a] |= sets[b]
                    sets[b] = set()
                    changed = True
    return [np.sort(np.array([order[q] for q in st], dtype=np.intp)) for st in sets if len(st) >= p.min_plots]


def imm_cycle_reference(
    xm: FloatArray,
    pm: FloatArray,
    mu: FloatArray,
    dt: FloatArray,
    z: FloatArray,
    R: FloatArray,
    psd: tuple[float, float],
    sojourn_s: tuple[float, float],
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Plain loop form of one IMM cycle of two constant-velocity models per track (for tests):
    the textbook's mixing, prediction, update and combination one track and one model at a
    time, the transition matrix from the chain's generator by ``scipy.linalg.expm``, and the
    likelihoods as full Gaussian densities.  Returns ``(x, P, mu, d2)``: the combined updated
    state and covariance, the models' probabilities, and ``d^2`` of the plot against the
    moment-matched prediction."""
    from scipy.linalg import expm
    from scipy.stats import multivariate_normal

    rate = np.array([1.0 / sojourn_s[0], 1.0 / sojourn_s[1]])
    gen = np.array([[-rate[0], rate[0]], [rate[1], -rate[1]]])
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    out_x, out_p, out_mu, out_d2 = [], [], [], []
    for k in range(xm.shape[0]):
        p = expm(gen * abs(dt[k]))
        c = np.array([sum(p[i, j] * mu[k, i] for i in range(2)) for j in range(2)])
        xs, ps = [], []
        for j in range(2):
            w = [p[i, j] * mu[k, i] / c[j] for i in range(2)]
            x0 = sum(w[i] * xm[k, i] for i in range(2))
            p0 = sum(w[i] * (pm[k, i] + np.outer(xm[k, i] - x0, xm[k, i] - x0)) for i in range(2))
            F = np.eye(6)
            F[:3, 3:] = dt[k] * np.eye(3)
            a = abs(dt[k])
            Q = np.zeros((6, 6))
            Q[:3, :3] = psd[j] * a**3 / 3 * np.eye(3)
            Q[:3, 3:] = Q[3:, :3] = psd[j] * dt[k] * a / 2 * np.eye(3)
            Q[3:, 3:] = psd[j] * a * np.eye(3)
            xs.append(F @ x0)
            ps.append(F @ p0 @ F.T + Q)
        xbar = sum(c[j] * xs[j] for j in range(2))
        pbar = sum(c[j] * (ps[j] + np.outer(xs[j] - xbar, xs[j] - xbar)) for j in range(2))
        ybar = z[k] - H @ xbar
        out_d2.append(float(ybar @ np.linalg.inv(H @ pbar @ H.T + R[k]) @ ybar))
        like, xu, pu = [], [], []
        for j in range(2):
            S = H @ ps[j] @ H.T + R[k]
            K = ps[j] @ H.T @ np.linalg.inv(S)
            y = z[k] - H @ xs[j]
            like.append(multivariate_normal(np.zeros(3), S).pdf(y))
            xu.append(xs[j] + K @ y)
            ikh = np.eye(6) - K @ H
            pu.append(ikh @ ps[j] @ ikh.T + K @ R[k] @ K.T)
        post = np.array([like[j] * c[j] for j in range(2)])
        m = post / post.sum()
        x = sum(m[j] * xu[j] for j in range(2))
        P = sum(m[j] * (pu[j] + np.outer(xu[j] - x, xu[j] - x)) for j in range(2))
        out_x.append(x)
        out_p.append(P)
        out_mu.append(m)
    return np.array(out_x), np.array(out_p), np.array(out_mu), np.array(out_d2)
