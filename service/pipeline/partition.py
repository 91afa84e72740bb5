"""Which worker of N owns what: rendezvous (highest random weight) hashing.

``--partition K/N`` makes a worker the K-th of N (``1 <= K <= N``) on one prefix.  Every name
(a radar id, a reference source id, a radar pair ``"a/b"`` with ``a < b``) has exactly one
owner: the worker ``k`` with the highest weight

    w(k, name) = the 8-byte BLAKE2b digest of the UTF-8 text "{k}:{name}", big-endian

(ties, which need a 64-bit collision, go to the lower ``k``).  The assignment depends only on
the name and on N, so an operator can predict it (``topofusion partition``), every worker
computes the same answer without talking to the others, and a name never moves while N stays
the same.  A weight does not depend on N, so going from N to N+1 workers moves only the names
the new worker wins, about ``1/(N+1)`` of them, and nothing else (the property rendezvous
hashing is chosen for).  Workers of one network must agree on N.

The owner of a radar tracks it (takes its plots, publishes its tracks and track states) and
reports the rejections of its messages; the owner of a pair correlates it.  A reference source
(AIS, ADS-B) is taken by every worker, since every worker may own pairs with it, and its
rejections are reported by its owner only.  The joint bias estimate is solved by one worker,
:data:`BIAS_WORKER`, from the registration rows every pair owner publishes.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from functools import lru_cache

#: The worker that solves and publishes the joint bias estimate over every pair.
BIAS_WORKER = 1

_SPEC = re.compile(r"^\s*(\d+)\s*/\s*(\d+)\s*$")


@lru_cache(maxsize=65536)
def _owner(name: str, count: int) -> int:
    best, owner = -1, 1
    for k in range(1, count + 1):
        digest = hashlib.blake2b(f"{k}:{name}".encode(), digest_size=8).digest()
        weight = int.from_bytes(digest, "big")
        if weight > best:
            best, owner = weight, k
    return owner


def pair_name(a: str, b: str) -> str:
    """The name of a source pair for ownership: ``"a/b"`` in string order."""
    return f"{a}/{b}" if a < b else f"{b}/{a}"


@dataclass(frozen=True)
class Partition:
    """Worker ``index`` of ``count`` (both from 1); ``1/1`` owns everything."""

    index: int = 1
    count: int = 1

    def __post_init__(self) -> None:
        if not 1 <= self.index <= self.count:
            raise ValueError(f"partition {self.index}/{self.count}: need 1 <= K <= N")

    @staticmethod
    def parse(spec: str) -> Partition:
        """``"K/N"`` (e.g. ``"2/3"``); raises ``ValueError`` saying what is wrong."""
        m = _SPEC.match(spec)
        if not m:
            raise ValueError(f"partition {spec!r}: expected K/N, e.g. 1/1 or 2/3")
        return Partition(int(m.group(1)), int(m.group(2)))

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"

    @property
    def whole(self) -> bool:
        """The only worker: owns every name."""
        return self.count == 1

    @property
    def solves_biases(self) -> bool:
        return self.index == BIAS_WORKER

    def owner(self, name: str) -> int:
        """The worker (1..N) that owns ``name``."""
        return 1 if self.count == 1 else _owner(name, self.count)

    def owns(self, name: str) -> bool:
        """This worker owns a source (radar or reference) id."""
        return self.count == 1 or _owner(name, self.count) == self.index

    def owns_pair(self, a: str, b: str) -> bool:
        """This worker correlates the pair of sources ``a``, ``b``."""
        return self.count == 1 or _owner(pair_name(a, b), self.count) == self.index
