"""The contract's words: source ids, correlation method names and rejection reasons.

Each is defined here once; models, key grammar, settings and the command line take them from
here.  The numerics name their methods with the same strings (a test holds them equal), but do
not import this package: the maths does not depend on the wire.
"""

from __future__ import annotations

import re
from typing import Literal, get_args

#: A ``{radar_id}`` / ``{source_id}`` (contract §1), without anchors, for embedding in patterns.
ID_REGEX = r"[A-Za-z0-9_-]{1,64}"
#: The same, anchored: a whole id.
ID_PATTERN = rf"^{ID_REGEX}$"
_ID = re.compile(ID_PATTERN)


def is_source_id(value: str) -> bool:
    return _ID.fullmatch(value) is not None


#: Correlation method names (contract §3); the first is the default.
Method = Literal["svd-topology", "basic-topology", "nearest", "gmm", "cfar"]
METHODS: tuple[str, ...] = get_args(Method)

#: ``Pair.basis``: what a pair's latest decision rested on (the topology match of one update,
#: the bias-compensated test of one update once registered, the accumulated evidence of the
#: pair's history, a bias-free reference source).
PairBasis = Literal["topology", "registered", "history", "reference"]
PAIR_BASES: tuple[str, ...] = get_args(PairBasis)

#: ``Rejection.reason`` (contract §1).
RejectionReason = Literal[
    "malformed_json",
    "schema",
    "unknown_radar",
    "duplicate_seq",
    "too_large",
    "non_finite",
    "out_of_range",
    "internal",
]
REJECTION_REASONS: tuple[str, ...] = get_args(RejectionReason)
