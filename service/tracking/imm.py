"""Interacting multiple model (IMM) filter of constant-velocity models, vectorised over tracks.

Each track holds one state per model, ``xm`` ``(n, M, 6)`` and ``Pm`` ``(n, M, 6, 6)``, and the
models' probabilities ``mu`` ``(n, M)``.  The models are the constant-velocity filter of
:mod:`.kalman` with different process noise: with the default two, a *quiet* model (small
``q``: straight flight, whose velocity then settles to a fraction of the plot error's worth)
and a *manoeuvre* model (a larger ``q``; :class:`~service.tracking.params.FilterParams`).  One
cycle, at each plot a track takes (Bar-Shalom, Li, Kirubarajan, *Estimation with Applications
to Tracking and Navigation*, 2001, Section 11.6.6; Blackman & Popoli 1999, Section 4.5):

1. mixing: with the transition probabilities ``p_ij`` over the time since the track's last
   update, ``c_j = sum_i p_ij mu_i`` and ``mu_{i|j} = p_ij mu_i / c_j``;
   ``x0_j = sum_i mu_{i|j} x_i``, ``P0_j = sum_i mu_{i|j} (P_i + (x_i - x0_j)(x_i - x0_j)^T)``
   (Eqs. 11.6.6-6 to -9);
2. each model's prediction from its mixed state with its own ``q`` (:func:`.kalman.predict`);
3. the track's predicted state for association is the mixture of the models' predictions with
   the weights ``c_j``, moment-matched (:func:`combine`): gating and the one-to-one assignment
   see one Gaussian per track, as with one model;
4. each model's Kalman update with the assigned plot, its likelihood
   ``L_j = N(y_j; 0, S_j)`` (Eq. 11.6.6-12), ``mu_j = L_j c_j / sum_k L_k c_k`` (Eq. 11.6.6-15);
5. the output state and covariance are the moment-matched mixture of the updated models with
   the weights ``mu_j`` (Eqs. 11.6.6-16, -17).

A track without a plot keeps its states: the next cycle mixes over the whole time since its
last update, as the transition probabilities of a continuous-time chain allow.  The models'
switching is that chain: the process leaves model ``j`` at the rate ``1 / sojourn_j`` (its mean
time in it) for the other (one or two models).  With one model every step is the plain Kalman
filter's, number for number.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.geo import FloatArray
from service.linalg import det3
from service.tracking import kalman
from service.tracking.params import FilterParams, FormationParams


@dataclass(frozen=True)
class Models:
    """The IMM's models: each one's process noise ``q`` (m^2/s^3) and mean sojourn (s)."""

    psd: tuple[float, ...]
    sojourn_s: tuple[float, ...]

    def __post_init__(self) -> None:
        if not self.psd or len(self.psd) != len(self.sojourn_s):
            raise ValueError("need one sojourn per model and at least one model")
        if len(self.psd) > 2:
            raise ValueError(f"one or two models, got {len(self.psd)}")
        if min(self.sojourn_s) <= 0.0 or min(self.psd) < 0.0:
            raise ValueError(f"sojourns must be > 0 and q >= 0, got {self.sojourn_s}, {self.psd}")

    @property
    def count(self) -> int:
        return len(self.psd)

    @property
    def stationary(self) -> FloatArray:
        """The chain's long-run share of time in each model (each ``sojourn / sum``): a new
        track's model probabilities."""
        s = np.asarray(self.sojourn_s, dtype=float)
        return np.asarray(s / s.sum())

    def transition(self, dt: FloatArray) -> FloatArray:
        """``p_ij`` over each ``|dt|`` ``(k,)``: shape ``(k, M, M)``, rows summing to 1.

        The two-state chain that leaves ``i`` at the rate ``r_i = 1 / sojourn_i``:
        ``P(dt) = 1 pi^T + e^{-(r_1 + r_2) |dt|} (I - 1 pi^T)``, ``pi`` the stationary shares
        (every row of ``1 pi^T`` is ``pi``), the exponential of the chain's generator."""
        a = np.abs(np.asarray(dt, dtype=float))
        m = self.count
        if m == 1:
            return np.ones((a.shape[0], 1, 1))
        pi = self.stationary
        rate = float(np.sum(1.0 / np.asarray(self.sojourn_s)))
        decay = np.exp(-rate * a)[:, None, None]
        steady = np.broadcast_to(pi, (m, m))
        return np.asarray(steady + decay * (np.eye(m) - steady))


def models_of(fp: FilterParams) -> Models:
    """The filter's models: the quiet and the manoeuvre model (``fp.imm``), or the one
    constant-velocity model of ``process_noise_psd``."""
    if not fp.imm:
        return Models((fp.process_noise_psd,), (1.0,))
    return Models((fp.quiet_psd, fp.manoeuvre_psd), (fp.quiet_sojourn_s, fp.manoeuvre_sojourn_s))


def formation_models_of(fp: FilterParams, formation: FormationParams) -> Models | None:
    """The models of a track in formation (:mod:`.formation`): the formation's quiet model and
    the filter's manoeuvre model; None when the rule is off or the filter has one model."""
    if not (fp.imm and formation.hold_formations):
        return None
    return Models(
        (formation.formation_quiet_psd, fp.manoeuvre_psd),
        (formation.formation_quiet_sojourn_s, fp.manoeuvre_sojourn_s),
    )


def born(x: FloatArray, P: FloatArray, models: Models) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per-model states of new tracks (every model starts at the track's state) and their
    probabilities (the stationary shares)."""
    m = models.count
    xm = np.repeat(x[:, None, :], m, axis=1)
    pm = np.repeat(P[:, None, :, :], m, axis=1)
    return xm, pm, np.tile(models.stationary, (x.shape[0], 1))


def combine(w: FloatArray, x: FloatArray, P: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The moment-matched Gaussian of a mixture: weights ``w`` ``(k, M)`` over states ``x``
    ``(k, M, 6)`` and covariances ``P`` ``(k, M, 6, 6)``: ``x = sum w_j x_j``,
    ``P = sum w_j (P_j + (x_j - x)(x_j - x)^T)``."""
    if x.shape[1] == 1:  # one model: its own state, unchanged (no rounding through sums)
        return x[:, 0], P[:, 0]
    # two models: x_j - x = (+w_2, -w_1) (x_1 - x_2), so the spread is w_1 w_2 (x_1 - x_2)(..)^T
    xc = np.einsum("kj,kjd->kd", w, x)
    pc = np.einsum("kj,kjab->kab", w, P) + (w[:, 0] * w[:, 1])[:, None, None] * _spread(x)
    return xc, pc


def _spread(x: FloatArray) -> FloatArray:
    """``(x_1 - x_2)(x_1 - x_2)^T`` of two models' states ``x`` ``(k, 2, 6)``."""
    d = x[:, 0] - x[:, 1]
    return np.asarray(d[:, :, None] * d[:, None, :])


def predict(
    xm: FloatArray,
    pm: FloatArray,
    mu: FloatArray,
    dt: FloatArray,
    models: Models,
    other: Models | None = None,
    use_other: NDArray[np.bool_] | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Mixing and each model's prediction over ``dt`` ``(k,)`` (steps 1-2 of the module
    docstring): the models' predicted states ``(k, M, 6)``, covariances ``(k, M, 6, 6)`` and
    their prior weights ``c`` ``(k, M)``.  ``other``: models of the same count used instead
    where ``use_other`` ``(k,)`` is true (their ``q`` and their chain's transitions)."""
    k, m = mu.shape
    if m == 1:
        xp, pp = kalman.predict(xm[:, 0], pm[:, 0], dt, models.psd[0])
        return xp[:, None], pp[:, None], np.ones((k, 1))
    p = models.transition(dt)  # (k, i, j)
    q = np.tile(np.asarray(models.psd, dtype=float), k)
    if other is not None and use_other is not None and use_other.any():
        p = np.where(use_other[:, None, None], other.transition(dt), p)
        q = np.where(np.repeat(use_other, m), np.tile(np.asarray(other.psd, dtype=float), k), q)
    joint = p * mu[:, :, None]
    c = joint.sum(axis=1)  # (k, j)
    w = joint / np.maximum(c[:, None, :], np.finfo(float).tiny)  # mu_{i|j}
    # (two models: the sums over i written out, the same numbers as an einsum, a third faster)
    x0 = w[:, 0, :, None] * xm[:, 0, None] + w[:, 1, :, None] * xm[:, 1, None]
    # each mixed state's spread is w_1j w_2j (x_1 - x_2)(x_1 - x_2)^T, as in :func:`combine`
    p0 = w[:, 0, :, None, None] * pm[:, 0, None] + w[:, 1, :, None, None] * pm[:, 1, None]
    p0 += (w[:, 0] * w[:, 1])[:, :, None, None] * _spread(xm)[:, None]
    xp, pp = kalman.predict(x0.reshape(k * m, 6), p0.reshape(k * m, 6, 6), np.repeat(dt, m), q)
    return xp.reshape(k, m, 6), pp.reshape(k, m, 6, 6), c


def update(
    xp: FloatArray, pp: FloatArray, c: FloatArray, z: FloatArray, R: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Each model's Kalman update with its track's plot ``z`` ``(k, 3)``, ``R`` ``(k, 3, 3)``,
    and the new model probabilities (steps 4-5): ``(x, P, xm, Pm, mu)``, the first two the
    combined state and covariance."""
    k, m = c.shape
    if m == 1:
        x1, p1 = kalman.update_state(xp[:, 0], pp[:, 0], z, R)
        return x1, p1, x1[:, None], p1[:, None], np.ones((k, 1))
    rr = np.repeat(R, m, axis=0)
    flat_x, flat_p = xp.reshape(k * m, 6), pp.reshape(k * m, 6, 6)
    y, S = kalman.innovation(flat_x, flat_p, np.repeat(z, m, axis=0), rr)
    d2 = kalman.mahalanobis2(y, S)
    # log N(y; 0, S) up to the constant shared by the models (same dimension)
    loglike = (-0.5 * (d2 + np.log(np.abs(det3(S))))).reshape(k, m)
    loglike -= loglike.max(axis=1, keepdims=True)  # (scaled: no underflow of exp)
    post = np.exp(loglike) * c
    total = post.sum(axis=1, keepdims=True)
    # a likelihood that is not a number (a degenerate S) leaves the prior weights
    mu = np.where(np.isfinite(total) & (total > 0.0), post / np.where(total > 0.0, total, 1.0), c)
    xm, pm = kalman.update_innovation(flat_x, flat_p, rr, y, S)
    xm, pm = xm.reshape(k, m, 6), pm.reshape(k, m, 6, 6)
    x, P = combine(mu, xm, pm)
    return x, P, xm, pm, mu
