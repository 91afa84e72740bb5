"""Small batched linear algebra that never raises (closed-form 2x2 / 3x3 inverses with a rank
flag), for the trackers, the correlation and the fusion alike."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: A covariance whose determinant is below this fraction of (trace/d)^d is called singular.
SINGULAR_RTOL = 1e-10
#: Stacks of fewer 3x3 matrices than this take the fewest-calls path of :func:`inv3`.
_SMALL_STACK = 256


def _invertible(det: FloatArray, a: FloatArray, e: FloatArray, i: FloatArray) -> BoolArray:
    """The non-singular flag of 3x3 matrices from their determinant and diagonal: finite, and a
    determinant above :data:`SINGULAR_RTOL` of ``(trace / 3)^3``."""
    scale = np.abs(a + e + i) / 3.0
    return np.asarray(np.isfinite(det) & (det > SINGULAR_RTOL * scale**3) & (scale > 0))


def inv3(s: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Inverse of a stack of 3x3 matrices ``(..., 3, 3)`` and a flag ``ok`` (non-singular, finite).

    Singular entries get a zero inverse and ``ok = False`` (callers turn that into "no decision").
    """
    a = s[..., 0, 0]
    b = s[..., 0, 1]
    c = s[..., 0, 2]
    d = s[..., 1, 0]
    e = s[..., 1, 1]
    f = s[..., 1, 2]
    g = s[..., 2, 0]
    h = s[..., 2, 1]
    i = s[..., 2, 2]
    co = np.empty(s.shape)
    if s.size < _SMALL_STACK * 9:
        # Few matrices: fewest numpy calls (the same arithmetic as below, so the same bits).
        co[..., 0, 0] = e * i - f * h
        co[..., 0, 1] = -(b * i - c * h)
        co[..., 0, 2] = b * f - c * e
        co[..., 1, 0] = -(d * i - f * g)
        co[..., 1, 1] = a * i - c * g
        co[..., 1, 2] = -(a * f - c * d)
        co[..., 2, 0] = d * h - e * g
        co[..., 2, 1] = -(a * h - b * g)
        co[..., 2, 2] = a * e - b * d
        det0 = a * co[..., 0, 0] + b * co[..., 1, 0] + c * co[..., 2, 0]
        ok0 = _invertible(det0, a, e, i)
        safe = np.where(ok0, det0, 1.0)
        return np.where(ok0[..., None, None], co / safe[..., None, None], 0.0), ok0
    # Many matrices: in place, one scratch buffer (fewer passes over memory).
    tmp = np.empty(s.shape[:-2])

    def cof(out: FloatArray, p: FloatArray, q: FloatArray, r: FloatArray, t: FloatArray, neg: bool) -> None:
        # out = p q - r t (negated for the odd positions), with one scratch buffer
        np.multiply(p, q, out=out)
        np.multiply(r, t, out=tmp)
        if neg:
            np.subtract(tmp, out, out=out)
        else:
            out -= tmp

    cof(co[..., 0, 0], e, i, f, h, False)
    cof(co[..., 0, 1], b, i, c, h, True)
    cof(co[..., 0, 2], b, f, c, e, False)
    cof(co[..., 1, 0], d, i, f, g, True)
    cof(co[..., 1, 1], a, i, c, g, False)
    cof(co[..., 1, 2], a, f, c, d, True)
    cof(co[..., 2, 0], d, h, e, g, False)
    cof(co[..., 2, 1], a, h, b, g, True)
    cof(co[..., 2, 2], a, e, b, d, False)
    det = np.multiply(a, co[..., 0, 0], out=np.empty(s.shape[:-2]))
    det += b * co[..., 1, 0]
    det += c * co[..., 2, 0]
    ok = _invertible(det, a, e, i)
    det[~ok] = 1.0
    co /= det[..., None, None]
    co[~ok] = 0.0
    return co, ok


def matvec3(m: FloatArray, v: FloatArray) -> FloatArray:
    """``M v`` for stacks ``m (..., 3, 3)``, ``v (..., 3)`` written out (a batched ``@`` on 3x3
    matrices pays a per-matrix overhead; this is three fused rows)."""
    shape = np.broadcast_shapes(m.shape[:-1], v.shape)
    if np.prod(shape) < _SMALL_STACK * 3:
        return np.asarray((m @ v[..., None])[..., 0])
    out = np.empty(shape)
    for i in range(3):
        np.multiply(m[..., i, 0], v[..., 0], out=out[..., i])
        out[..., i] += m[..., i, 1] * v[..., 1]
        out[..., i] += m[..., i, 2] * v[..., 2]
    return out


def quad3(r: FloatArray, s_inv: FloatArray) -> FloatArray:
    """``r^T S^-1 r`` for stacks ``r (..., 3)``, ``s_inv (..., 3, 3)`` (one ``@``: cheapest for small
    stacks, e.g. inside the basic method's grid loop; large stacks: :func:`quad3_large`)."""
    return (r * (s_inv @ r[..., None])[..., 0]).sum(-1)


def quad3_large(r: FloatArray, s_inv: FloatArray) -> FloatArray:
    """:func:`quad3` through :func:`matvec3`: fewer passes over a large stack, more calls."""
    return (r * matvec3(s_inv, r)).sum(-1)


def det3(s: FloatArray) -> FloatArray:
    """The determinant of each of a stack of 3x3 matrices ``(..., 3, 3)``, written out."""
    a, b, c = s[..., 0, 0], s[..., 0, 1], s[..., 0, 2]
    d, e, f = s[..., 1, 0], s[..., 1, 1], s[..., 1, 2]
    g, h, i = s[..., 2, 0], s[..., 2, 1], s[..., 2, 2]
    return np.asarray(a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g))


def mahalanobis3(r: FloatArray, s: FloatArray) -> tuple[FloatArray, BoolArray]:
    """``r^T S^-1 r`` for stacks ``r (..., 3)`` and *symmetric* ``s (..., 3, 3)`` (covariances),
    and the flag ``ok`` of :func:`inv3`; a singular ``S`` gives 0, as :func:`quad3` of its zero
    inverse does.

    :func:`inv3` then :func:`quad3` in one pass: the quadratic form of the six distinct
    cofactors over the determinant, without forming the inverse (a third of the arithmetic and
    of the passes over memory; the same value to rounding)."""
    a, b, c = s[..., 0, 0], s[..., 0, 1], s[..., 0, 2]
    e, f, i = s[..., 1, 1], s[..., 1, 2], s[..., 2, 2]
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    c00 = e * i - f * f
    c01 = c * f - b * i
    c02 = b * f - c * e
    det = a * c00 + b * c01 + c * c02
    q = c00 * x * x + (a * i - c * c) * y * y + (a * e - b * b) * z * z
    q += 2.0 * (c01 * x * y + c02 * x * z + (b * c - a * f) * y * z)
    ok = _invertible(det, a, e, i)
    return np.where(ok, q / np.where(ok, det, 1.0), 0.0), ok


def mahalanobis2_h(
    dx: FloatArray, dy: FloatArray, sxx: FloatArray, sxy: FloatArray, syy: FloatArray
) -> FloatArray:
    """Horizontal 2-D Mahalanobis distance squared with a closed-form 2x2 inverse (inf if singular).

    ``(syy dx^2 - 2 sxy dx dy + sxx dy^2) / det``; evaluated in place on a few buffers of the
    broadcast shape (the callers' arrays are large ``(P, K, K)`` stacks).
    """
    shape = np.broadcast_shapes(dx.shape, dy.shape, sxx.shape, sxy.shape, syy.shape)
    det = np.multiply(sxx, syy, out=np.empty(shape))
    tmp = np.multiply(sxy, sxy, out=np.empty(shape))
    det -= tmp
    np.add(sxx, syy, out=tmp)
    tmp /= 2.0
    tmp *= tmp
    tmp *= SINGULAR_RTOL
    bad = det <= tmp
    bad |= np.isnan(det)  # (det > floor) is False for NaN as well
    det[bad] = 1.0
    q = np.multiply(syy, dx, out=np.empty(shape))
    q *= dx
    np.multiply(2.0, sxy, out=tmp)
    tmp *= dx
    tmp *= dy
    q -= tmp
    np.multiply(sxx, dy, out=tmp)
    tmp *= dy
    q += tmp
    q /= det
    q[bad] = np.inf
    return q


def congruence(r: FloatArray, s: FloatArray) -> FloatArray:
    """``R S R^T`` for one fixed ``R (3, 3)`` and a stack ``S (..., 3, 3)``, as two 2-D products.

    (A broadcast ``R @ S @ R.T`` runs one tiny product per matrix; folding the stack into the
    rows of one matrix product is several times faster.)
    """
    shape = s.shape
    sr = (s.reshape(-1, 3) @ r.T).reshape(shape)  # S R^T
    return np.swapaxes((np.swapaxes(sr, -1, -2).reshape(-1, 3) @ r.T).reshape(shape), -1, -2)


def yaw_congruence(yaw: FloatArray, s: FloatArray) -> FloatArray:
    """``R S R^T`` for rotations ``R`` about the vertical by ``yaw (P,)`` and ``S (P, ..., 3, 3)``.

    Elementwise (the rotation mixes only east and north), instead of batched 3x3 products.
    """
    extra = s.ndim - 3
    cy = np.cos(yaw).reshape(-1, *([1] * extra))
    sy = np.sin(yaw).reshape(-1, *([1] * extra))
    m = np.empty_like(s)  # M = R S: rows 0 and 1 mixed
    m[..., 0, :] = cy[..., None] * s[..., 0, :] - sy[..., None] * s[..., 1, :]
    m[..., 1, :] = sy[..., None] * s[..., 0, :] + cy[..., None] * s[..., 1, :]
    m[..., 2, :] = s[..., 2, :]
    out = np.empty_like(s)  # M R^T: columns 0 and 1 mixed
    out[..., :, 0] = cy[..., None] * m[..., :, 0] - sy[..., None] * m[..., :, 1]
    out[..., :, 1] = sy[..., None] * m[..., :, 0] + cy[..., None] * m[..., :, 1]
    out[..., :, 2] = m[..., :, 2]
    return out
