"""One radar's tracks as another radar would report them, by a pair's registration.

The aid of association (:mod:`service.tracking.aid`) needs a partner track's position in the
aided radar's own frame, its own systematic errors included (the tracker works in what its
radar reports), and how well that is known.  With the pair correlator's registration, the five
terms of each radar (:mod:`.registration`, the model (*): range offset, azimuth, elevation,
range gain, time bias) and their joint covariance:

* the partner's reported position, its terms taken out exactly (:func:`remove_bias`), is where
  the aircraft is; the aided radar's terms put back in by the same with their signs turned
  (the model's inverse to first order: the terms are a few hundred metres, milliradians and
  seconds) is where the aided radar reports it (:func:`into_view`);
* the registration's covariance goes through that transform's Jacobian in the ten terms,
  ``J C J^T`` (:func:`view_with_covariance`), and adds to the partner track's own position
  covariance turned into the aided radar's ENU axes.

A term held at zero by the solution (a range gain or time bias the data do not show) is no
error: its rows and columns of the covariance are zeroed.
"""

from __future__ import annotations

import numpy as np

from service.correlation.registration import GAIN, N_TERMS, PPM, TIME, polar_jacobian_enu, remove_bias
from service.geo import FloatArray, Site


def into_view(
    source: Site,
    target: Site,
    ecef: FloatArray,
    velocity: FloatArray,
    source_terms: FloatArray,
    target_terms: FloatArray,
) -> FloatArray:
    """ECEF positions ``(n, 3)`` as radar ``source`` reports them, as radar ``target`` would
    (module docstring); ``velocity`` ECEF ``(n, 3)``, for the time biases."""
    return remove_bias(target, remove_bias(source, ecef, source_terms, velocity), -target_terms, velocity)


def view_with_covariance(
    source: Site,
    target: Site,
    ecef: FloatArray,
    velocity: FloatArray,
    position_cov_ecef: FloatArray,
    terms: FloatArray,
    terms_cov: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Positions of ``source`` (ECEF ``(n, 3)``, their ECEF velocities and position covariances
    ``(n, 3, 3)``) in ``target``'s ENU frame with their covariance (module docstring), by the
    terms ``terms`` ``(10,)`` (``target``'s five, then ``source``'s) of joint covariance
    ``terms_cov`` ``(10, 10)``.  Returns the positions ``(n, 3)``, their covariances ``(n, 3,
    3)`` and the registration's part of those alone ``(n, 3, 3)``.

    The Jacobian in the terms, to first order in them (each transform is within milliradians
    and parts per million of the identity): the target's polar terms move a position along
    the polar Jacobian ``J`` of Eq. 2 at the position (:func:`polar_jacobian_enu`), its gain
    along the line of sight by ``1e-6`` of the range, its time bias by minus the velocity; the
    source's terms the other way, in the source's axes turned into the target's."""
    own, theirs = terms[:N_TERMS], terms[N_TERMS:]
    cov = np.array(terms_cov, dtype=float, copy=True)
    held = np.flatnonzero(terms == 0.0)
    cov[held, :] = 0.0
    cov[:, held] = 0.0
    base = target.ecef_to_enu(into_view(source, target, ecef, velocity, theirs, own))
    turn = target.rotation.T @ source.rotation  # (source ENU to target ENU)
    seen = source.ecef_to_enu(ecef)
    vel = velocity @ target.rotation  # (target ENU)
    jac = np.empty((ecef.shape[0], 3, 2 * N_TERMS))
    jac[:, :, :3] = polar_jacobian_enu(base)
    jac[:, :, GAIN] = PPM * base
    jac[:, :, TIME] = -vel
    jac[:, :, N_TERMS : N_TERMS + 3] = -(turn @ polar_jacobian_enu(seen))
    jac[:, :, N_TERMS + GAIN] = -PPM * (seen @ turn.T)
    jac[:, :, N_TERMS + TIME] = vel
    registration = jac @ cov @ np.swapaxes(jac, 1, 2)
    to_enu = target.rotation.T  # (the site's rotation takes ENU to ECEF)
    track = to_enu @ position_cov_ecef @ to_enu.T
    return base, track + registration, registration
