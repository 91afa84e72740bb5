"""The gates' chi-square quantiles (service/chi2.py): scipy.stats' numbers, without its import."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from scipy.stats import chi2

from service.chi2 import chi2_quantile, chi2_upper


def test_the_quantiles_are_scipy_stats_numbers() -> None:
    p = np.array([1e-9, 0.01, 0.5, 0.9, 0.99, 0.999, 1 - 1e-9])
    dof = np.arange(1, 13)
    for k in dof:
        assert np.array_equal(chi2_quantile(p, k), chi2.ppf(p, k))
        for alpha in (1e-6, 1e-3, 0.01, 0.05):
            assert chi2_upper(alpha, k) == chi2.ppf(1.0 - alpha, k)
    # broadcast over degrees of freedom, as the gates use them
    assert np.array_equal(chi2_upper(0.01, dof), chi2.ppf(0.99, dof))
    # a number's quantile is looked up once; each call still hands out an array of its own
    first = chi2_upper(0.01, 3)
    first[...] = -1.0
    assert chi2_upper(0.01, 3) == chi2.ppf(0.99, 3) == chi2_upper(0.01, 3.0)


def test_a_service_process_does_not_import_scipy_stats() -> None:
    """0.6-1 s of every start (each worker, each correlation process, each CLI call)."""
    code = (
        "import sys, service.cli.serve, service.api.app, service.transport.node, service.engine\n"
        "print('scipy.stats' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert out.stdout.strip() == "False", out.stdout + out.stderr
