"""Chi-square quantiles, the gates' thresholds (pure numpy and ``scipy.special``).

The expression scipy's ``chi2.ppf`` evaluates, ``2 gammaincinv(dof / 2, p)``, without
importing ``scipy.stats`` (0.6-1 s of every process's start, measured) or paying
``rv_continuous``'s per-call argument handling (a large share of a small call).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import gammaincinv


def chi2_quantile(p: ArrayLike, dof: ArrayLike) -> NDArray[np.float64]:
    """The ``p`` quantile of chi-square with ``dof`` degrees of freedom, ``chi2.ppf(p, dof)``."""
    return np.asarray(2 * gammaincinv(np.asarray(dof, dtype=float) / 2, p), dtype=float)


def chi2_upper(alpha: float, dof: ArrayLike) -> NDArray[np.float64]:
    """Upper ``alpha`` quantile, ``chi2.ppf(1 - alpha, dof)`` (``alpha`` a number: the gates'
    named parameters).  A number of degrees of freedom is looked up once per ``(alpha, dof)``:
    the gates ask for the same few thousands of times a second."""
    if isinstance(dof, (int, float, np.integer, np.floating)) and not isinstance(dof, bool):
        return np.asarray(_chi2_upper_of(float(alpha), float(dof)))
    return chi2_quantile(1.0 - alpha, dof)


@lru_cache(maxsize=1024)
def _chi2_upper_of(alpha: float, dof: float) -> float:
    return float(chi2_quantile(1.0 - alpha, dof))
