"""Candidate pairs by an absolute-position gate in ECEF (SVD paper Section 2 step 2).

The paper keeps candidates closer than 10 km in ECEF, wide enough for the systematic errors
it expects (Section 1.2: angle bias below 5 deg, range bias below 1 km, so at 100 km the
displacement reaches ~9 km).  One ``cKDTree.sparse_distance_matrix`` gives all pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from service.correlation.base import FloatArray


@dataclass(frozen=True)
class CandidateParams:
    """The absolute-position gate."""

    #: ECEF distance below which two tracks are candidates (the paper's 10 km).  Must exceed the
    #: largest displacement the biases produce (range bias + range x angle bias of both radars).
    gate_m: float = 10_000.0


def candidate_pairs(
    pos_a: FloatArray, pos_b: FloatArray, gate_m: float
) -> tuple[NDArray[np.intp], NDArray[np.intp], FloatArray]:
    """All ``(i, j)`` with ``|pos_a[i] - pos_b[j]| <= gate_m``, sorted by (i, j); also the distances."""
    if pos_a.shape[0] == 0 or pos_b.shape[0] == 0:
        e = np.empty(0, dtype=np.intp)
        return e, e.copy(), np.empty(0)
    sdm = cKDTree(pos_a).sparse_distance_matrix(cKDTree(pos_b), gate_m, output_type="ndarray")
    ia = sdm["i"].astype(np.intp)
    ib = sdm["j"].astype(np.intp)
    order = np.argsort(ia * pos_b.shape[0] + ib)  # (i, j) order; the keys are unique
    return ia[order], ib[order], sdm["v"][order].astype(float)
