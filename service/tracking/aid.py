"""Association aided by another radar's track of the same aircraft.

In a formation a radar whose cross-range error is half the spacing cannot tell neighbours apart
by one scan's plots: its tracks take a neighbour's plot and swap (docs/results.md, formations).
Another radar may see the same aircraft far more precisely, and the correlation already says
which of its tracks that is (a *confirmed pair*).  With the aid on, the engine hands each
tracker, before its batch, the :class:`PartnerReferences` of the correlation's confirmed pairs
(:mod:`service.pipeline.partner_aid`): for a track flying in a formation (``_Tracks.formation``,
the quiet model's search of :mod:`.formation`: where one scan's plots are ambiguous, and
nowhere else, so a network of lone aircraft pays nothing) with a confirmed partner whose
registration
is known to within ``AidParams.registration_sigma_m`` and whose position, brought into this
radar's view, is more precise than the track's own, a *reference*: that position at the plot's
time in this radar's ENU frame, with its covariance (the partner's and the registration's).

A candidate plot ``z`` (covariance ``R``) of such a track then costs, in the one-to-one
assignment only, its squared Mahalanobis distance from the reference,

    d^2 = (z - r)^T (R + C)^-1 (z - r),

the same chi-square form as the track's own gate (the innovation against the sum of the two
covariances, :mod:`.kalman`); a candidate whose aided cost exceeds the gate is no candidate.
The gate itself, the filter update and every other step stay the track's own: the aid decides
which plot, never where the track goes.  Measured in the lab's bounds on association in
formations (docs/evaluation/formation-bounds.md, "Aided by the service's own pairs").
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from service.geo import FloatArray


class PartnerReferences(Protocol):
    """The references of a radar's tracks for one batch (module docstring)."""

    def __call__(
        self, track_ids: NDArray[np.str_], times_s: FloatArray, own_spread_m2: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """For candidate ``k`` (its track ``track_ids[k]``, its plot's time ``times_s[k]``, the
        track's horizontal spread ``own_spread_m2[k]``, the trace of its ENU position
        covariance's horizontal block): the reference ``(n, 3)`` in this radar's ENU frame and
        its covariance ``(n, 3, 3)``; NaN rows where the track has none more precise."""
        ...


def horizontal_spread(cov: FloatArray) -> FloatArray:
    """The trace of the horizontal 2 x 2 block of each ``(n, >= 2, >= 2)`` covariance (m^2):
    the one figure by which a track and a reference are compared for precision."""
    return np.asarray(np.trace(cov[:, :2, :2], axis1=1, axis2=2), dtype=float)


def aided_d2(z: FloatArray, cov_z: FloatArray, ref: FloatArray, ref_cov: FloatArray) -> FloatArray:
    """Each candidate's cost from its reference (module docstring), vectorised over the
    candidates: ``z`` ``(n, 3)`` plots, ``cov_z`` ``(n, 3, 3)`` their covariances, ``ref`` and
    ``ref_cov`` from :class:`PartnerReferences`.  NaN where the reference is NaN."""
    out = np.full(z.shape[0], np.nan)
    ok = ~np.isnan(ref[:, 0])
    if ok.any():
        y = z[ok] - ref[ok]
        s = cov_z[ok] + ref_cov[ok]
        out[ok] = np.einsum("ni,ni->n", y, np.linalg.solve(s, y[:, :, None])[:, :, 0])
    return out


def moved(
    position: FloatArray, velocity: FloatArray, covariance: FloatArray, dt_s: FloatArray, psd: float
) -> tuple[FloatArray, FloatArray]:
    """States ``(n, 3)`` positions, velocities and their ``(n, 6, 6)`` covariances, each moved
    ``dt_s[k]`` on a constant velocity: the positions and their ``(n, 3, 3)`` covariances, the
    prediction of the constant-velocity model ``F = [[I, dt I], [0, I]]``, ``F P F^T`` with the
    white-noise acceleration of spectral density ``psd`` (m^2/s^3) per axis, ``psd |dt|^3 / 3``
    on the position (Bar-Shalom, Li, Kirubarajan 2001, Eq. 6.2.2-12, as :mod:`.kalman`)."""
    dt = np.asarray(dt_s, dtype=float)[:, None, None]
    p = covariance
    cov = p[:, :3, :3] + dt * (p[:, :3, 3:] + p[:, 3:, :3]) + dt**2 * p[:, 3:, 3:]
    cov = cov + (psd * np.abs(dt) ** 3 / 3.0) * np.eye(3)
    return position + velocity * dt[:, :, 0], cov
