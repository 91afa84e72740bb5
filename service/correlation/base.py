"""The small contract every correlation method implements (pure numpy).

A :class:`PredictedTracks` is one radar's tracks brought to the common data time of an update
(:func:`service.correlation.prediction.predict_tracks`).  A :class:`CorrelationMethod` turns two
snapshots into *single decisions* over candidate pairs (:class:`Decisions`): one row per
candidate, with an accept flag, a cost for the one-to-one assignment and the method's
statistics.  Everything over time (the M-of-N book, the evidence, registration) lives in
:class:`service.correlation.correlator.PairCorrelator`, shared by all methods.

Expected non-results are values: a candidate that cannot be decided (too few neighbours,
degenerate fit, ...) carries a :class:`Reason` instead of raising.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

from service.columns import concat_rows, take_rows
from service.geo import Site

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]


class Reason(IntEnum):
    """Why a single decision came out as it did (0 = accepted)."""

    ACCEPTED = 0
    TOO_FEW_NEIGHBOURS = 1  # no decision: not enough (matched) neighbours for a fit
    DEGENERATE_FIT = 2  # no decision: collinear / coincident points, singular covariance
    ROTATION_WEIGHT = 3  # rejected: rotation weight below threshold (Section 1.5)
    SCALE = 4  # rejected: similarity scale physically impossible
    SHAPE_TEST = 5  # rejected: topology residuals fail the chi-square / F test (Section 1.4)
    POSITION_TEST = 6  # rejected: reference position inconsistent with the neighbours' fit
    VELOCITY_TEST = 7  # rejected: velocities inconsistent
    GATE = 8  # rejected: chi-square gate of an absolute-position test
    UNEQUAL_LENGTH = 9  # no decision: sequences of unequal length (basic method)
    AMBIGUOUS = 10  # no decision: a competitor within the ambiguity margin
    NOT_ASSIGNED = 11  # accepted but lost the one-to-one assignment
    HISTORY = 12  # rejected: the pair's accumulated evidence fails its test (:mod:`.evidence`)


class Basis(IntEnum):
    """What a pair's latest decision rested on (the wire's ``Pair.basis``; -1: none given)."""

    TOPOLOGY = 0  # the topology-sequence match of one update (before registration)
    REGISTERED = 1  # the bias-compensated chi-square of one update (once registered)
    HISTORY = 2  # the accumulated evidence of the pair's history (:mod:`.evidence`)
    REFERENCE = 3  # a bias-free reference source's report (AIS, ADS-B)


#: The wire's words for :class:`Basis` (a test holds them equal to the contract's).
BASIS_NAMES: tuple[str, ...] = tuple(b.name.lower() for b in Basis)

#: Reasons meaning "could not decide" rather than "decided: not the same target".
NO_DECISION_REASONS = np.array(
    [Reason.TOO_FEW_NEIGHBOURS, Reason.DEGENERATE_FIT, Reason.UNEQUAL_LENGTH, Reason.AMBIGUOUS]
)

#: :data:`NO_DECISION_REASONS` as a table over every int8 code taken as a byte (a lookup costs
#: a tenth of ``np.isin`` on the few decisions of a prompt one).
_NO_DECISION_TABLE = np.zeros(256, dtype=bool)
_NO_DECISION_TABLE[NO_DECISION_REASONS] = True


def no_decision(reason: NDArray[np.integer]) -> NDArray[np.bool_]:
    """Per reason code: does it mean "could not decide" (:data:`NO_DECISION_REASONS`)?"""
    return np.asarray(_NO_DECISION_TABLE[np.asarray(reason).astype(np.uint8)])


@dataclass(frozen=True)
class PredictedTracks:
    """One source's tracks at the common data time of an update (row ``i`` = one track).

    ``position``/``velocity`` are ECEF as the source reports them (biases not removed
    unless ``compensated``); ``pos_cov``/``vel_cov`` are the 3x3 ECEF blocks of the
    extrapolated covariance; ``enu`` and ``enu_velocity`` are the same states in the
    source's own ENU frame (``site`` None: a bias-free reference source such as AIS, whose
    ENU frame is that of the other side's site when one is needed).
    """

    track_id: NDArray[np.str_]
    position: FloatArray
    velocity: FloatArray
    pos_cov: FloatArray
    vel_cov: FloatArray
    site: Site | None
    enu: FloatArray
    enu_velocity: FloatArray
    compensated: bool = False
    #: Each track's Mode S address (None: none); None: the source gave none at all.
    mode_s: NDArray[np.object_] | None = None
    #: Each track's quality (``TrackTable.quality``: how unambiguous its recent plot
    #: associations were, in [0, 1]; NaN: not known); None: the source gave none at all.
    quality: FloatArray | None = None
    #: Each track's integer key (:class:`~.pairkeys.TrackKeys`, what the correlation's books
    #: and evidence identify tracks by); None: not given (a snapshot only drawn or decided on).
    track_key: NDArray[np.int64] | None = None

    def __len__(self) -> int:
        return int(self.track_id.shape[0])

    @property
    def keys(self) -> NDArray[np.int64]:
        """``track_key``, which the snapshot must carry (``predict_tracks(..., keys=...)``)."""
        if self.track_key is None:
            raise ValueError("a snapshot without track keys: predict_tracks(..., keys=...) gives them")
        return self.track_key

    def enu_cov(self) -> FloatArray:
        """Position covariance in the source's own ENU frame, ``(n, 3, 3)``."""
        if self.site is None:
            return self.pos_cov
        r = self.site.rotation
        return r.T @ self.pos_cov @ r


@dataclass(frozen=True)
class Decisions:
    """Single decisions over candidate pairs ``(index_a[k], index_b[k])`` of one update.

    ``cost`` orders accepted candidates for the one-to-one assignment (lower is better,
    roughly a chi-square excess); ``statistic`` is the method's test statistic (for
    ``svd-topology`` the F statistic, chi-square over its degrees of freedom).
    """

    index_a: IntArray
    index_b: IntArray
    accepted: BoolArray
    reason: NDArray[np.int8]
    cost: FloatArray
    statistic: FloatArray
    rotation_weight: FloatArray
    scale: FloatArray
    neighbors: NDArray[np.int64]
    extras: dict[str, FloatArray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.index_a.shape[0])

    @staticmethod
    def empty() -> Decisions:
        return Decisions.build(np.empty(0, dtype=np.intp), np.empty(0, dtype=np.intp))

    @staticmethod
    def build(
        index_a: IntArray,
        index_b: IntArray,
        accepted: BoolArray | None = None,
        reason: NDArray[np.int8] | None = None,
        cost: FloatArray | None = None,
        statistic: FloatArray | None = None,
        rotation_weight: FloatArray | None = None,
        scale: FloatArray | None = None,
        neighbors: NDArray[np.int64] | None = None,
    ) -> Decisions:
        n = int(index_a.shape[0])
        return Decisions(
            np.asarray(index_a, dtype=np.intp),
            np.asarray(index_b, dtype=np.intp),
            np.zeros(n, dtype=bool) if accepted is None else accepted,
            np.zeros(n, dtype=np.int8) if reason is None else reason.astype(np.int8),
            np.zeros(n) if cost is None else cost,
            np.full(n, np.nan) if statistic is None else statistic,
            np.full(n, np.nan) if rotation_weight is None else rotation_weight,
            np.full(n, np.nan) if scale is None else scale,
            np.zeros(n, dtype=np.int64) if neighbors is None else neighbors.astype(np.int64),
        )

    @staticmethod
    def concat(parts: list[Decisions]) -> Decisions:
        """The rows of ``parts`` one after the other; an extra column missing from a part is NaN there."""
        if not parts:
            return Decisions.empty()
        if len(parts) == 1:
            return parts[0]
        keys = sorted({k for p in parts for k in p.extras})
        extras = {k: np.concatenate([p.extras.get(k, np.full(len(p), np.nan)) for p in parts]) for k in keys}
        return concat_rows(Decisions, parts, extras=extras)

    def take(self, index: IntArray | BoolArray) -> Decisions:
        return take_rows(self, index, extras={k: v[index] for k, v in self.extras.items()})


@dataclass(frozen=True)
class DecisionContext:
    """What the stream knows beyond one snapshot, handed to a method on each update.

    ``registered``: the snapshots are already bias-compensated with the current
    registration (then absolute-position tests are meaningful); ``registration_cov``: the
    extra covariance (ECEF, per track of A and of B) the registration's own uncertainty adds
    to an absolute position difference; ``confirmed_a``/``confirmed_b``: index pairs of
    currently confirmed pairs (for priors).  ``reference_a``/``reference_b``: the rows of A and
    of B that may form candidate pairs (None: every row); the other rows still count as
    neighbours of a reference.  A caller restricts them only for a method that re-verified
    the rest (:meth:`CorrelationMethod.reverify`); a method without a ``reverify`` may ignore them.
    """

    time_s: float
    registered: bool = False
    registration_cov_a: FloatArray | None = None
    registration_cov_b: FloatArray | None = None
    confirmed_a: IntArray = field(default_factory=lambda: np.empty(0, dtype=np.intp))
    confirmed_b: IntArray = field(default_factory=lambda: np.empty(0, dtype=np.intp))
    reference_a: IntArray | None = None
    reference_b: IntArray | None = None


class CorrelationMethod(ABC):
    """One correlation method: two snapshots in, single decisions over candidates out.

    Implementations are deterministic functions of their inputs and parameters; state over
    time is kept by the caller.  ``requires_sites`` tells whether the method needs both
    sources to be radars with a site (topology methods do).
    """

    name: str = ""
    requires_sites: bool = True

    @abstractmethod
    def decide(self, a: PredictedTracks, b: PredictedTracks, context: DecisionContext) -> Decisions:
        """Single decisions for every candidate pair of this update (of the reference rows of
        ``context`` when it names them and the method re-verifies)."""

    def reverify(
        self, a: PredictedTracks, b: PredictedTracks, ia: IntArray, ib: IntArray, context: DecisionContext
    ) -> Decisions | None:
        """A cheap re-check of the currently confirmed pairs ``(ia[k], ib[k])``, or None when the
        method has none for this context (the default: every pair goes to :meth:`decide`).

        The accepted rows are kept without a full decision, and the caller then restricts
        :meth:`decide` to the other rows (``context.reference_a``/``reference_b``), which a
        method implementing this must honour.
        """
        return None
