"""Which checkout a benchmark measures (imported by the benchmarks that compare trees).

A script run as ``python bench/X.py`` imports ``service`` from wherever Python finds it first:
with this project's development install (``make install``, an editable one) that is the tree
the virtual environment was installed from, not necessarily the checkout the script lies in.
Two checkouts compared side by side, each run with the one virtual environment, then measure
the same code twice.  ``PYTHONPATH=<checkout>:<checkout>/lab`` makes a run measure its own
checkout; :func:`warn_if_elsewhere` says when it does not.
"""

from __future__ import annotations

import sys
from pathlib import Path

import service

#: The checkout this benchmark lies in.
ROOT = Path(__file__).resolve().parents[1]


def warn_if_elsewhere() -> None:
    """A line on stderr when ``service`` comes from another tree than this benchmark's."""
    tree = Path(service.__file__).resolve().parents[1]
    if tree != ROOT:
        print(
            f"WARNING: measuring the service of {tree}, not of this checkout {ROOT}: run with "
            f"PYTHONPATH={ROOT}:{ROOT}/lab to measure this one",
            file=sys.stderr,
        )
