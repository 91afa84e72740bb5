"""Track-to-track correlation between radars under unknown systematic errors (pure numpy/scipy).

Methods (``METHODS``): ``svd-topology`` (default; Wu, Jiang, Ren 2011), ``basic-topology``
(its stepwise-rotation baseline), ``nearest`` (chi-square nearest neighbour), ``gmm`` and
``cfar``.  The engine owns one :class:`PairCorrelator` per radar pair and calls
:meth:`PairCorrelator.update`; :func:`estimate_biases` registers all radars jointly.
"""

from service.correlation.base import CorrelationMethod, DecisionContext, Decisions, PredictedTracks, Reason
from service.correlation.correlator import (
    METHODS,
    CorrelationParams,
    PairCorrelator,
    estimate_biases,
    joint_solution,
)
from service.correlation.pairs import PairBookParams, PairState
from service.correlation.registration import RadarBias, RegistrationParams

__all__ = [
    "METHODS",
    "CorrelationMethod",
    "CorrelationParams",
    "DecisionContext",
    "Decisions",
    "PairBookParams",
    "PairCorrelator",
    "PairState",
    "PredictedTracks",
    "RadarBias",
    "Reason",
    "RegistrationParams",
    "estimate_biases",
    "joint_solution",
]
