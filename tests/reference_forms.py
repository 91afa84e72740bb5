"""Plain reference forms (loops, dense matrices) of the correlation code, that tests compare
the vectorised forms against.  Tests only: the service never calls them."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from service.correlation.assignment import _FORBIDDEN
from service.correlation.base import BoolArray, FloatArray
from service.correlation.gls import N_PARAMS
from service.correlation.topology import TopologyParams
from service.correlation.umeyama import yaw_matrix


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
