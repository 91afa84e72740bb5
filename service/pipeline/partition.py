"""Which worker of N owns what: rendezvous (highest random weight) hashing.

``--partition K/N`` makes a worker the K-th of N (``1 <= K <= N``) on one prefix.  Every name
(a radar id, a reference source id, a radar pair ``"a/b"`` with ``a < b``) has exactly one
owner: the worker ``k`` with the highest weight

    w(k, name) = the 8-byte BLAKE2b digest of the UTF-8 text "{k}:{name}", big-endian

(ties, which need a 64-bit collision, go to the lower ``k``); with a salt ``S`` > 0
(``TOPOFUSION_PARTITION_SALT``) the text is ``"{S}:{k}:{name}"``.  The assignment depends
only on the name, N and the salt, so an operator can predict it (``topofusion partition``),
every worker computes the same answer without talking to the others, and a name never moves
while N stays the same.  A weight does not depend on N, so going from N to N+1 workers moves only the names
the new worker wins, about ``1/(N+1)`` of them, and nothing else (the property rendezvous
hashing is chosen for).  Workers of one network must agree on N and on the salt.

The shares are random: with 66 radar pairs and 2 workers the larger share is 33 +- 4 pairs
(one standard deviation), and a given network may draw an uneven split (the national
scenario's 12 radar names give 22/44 pairs and 5/7 radars with no salt).  The salt is how an
operator picks a balanced assignment once, for the radars the network has:
:func:`balanced_salt` (``topofusion partition --balance``) tries salts and keeps the one whose
busiest worker has the smallest share (worker 1's counting what it does for the whole
network).  A salt is one number every worker is given, so the assignment stays a pure
function of the name (a radar added later goes where its weights say, nothing else moves),
the property rendezvous hashing is chosen for.

The owner of a radar tracks it (takes its plots, publishes its tracks and track states) and
reports the rejections of its messages; the owner of a pair correlates it.  A reference source
(AIS, ADS-B) is taken by every worker, and its rejections are reported by its owner only.  A
pair of a radar and a reference source belongs to the radar's owner, not to the hash of its
name: that worker alone has the radar's plots, which the radar's assessment against the
reference (contract §5.3) measures with the pair's confirmed tracks, so it then has all that
one worker has for it.  The joint bias estimate is solved by one worker,
:data:`BIAS_WORKER`, from the registration rows every pair owner publishes.
"""

from __future__ import annotations

import hashlib
import itertools
import re
from collections.abc import Container, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from service.geo import geodetic_to_ecef

#: The worker that solves and publishes the joint bias estimate over every pair.
BIAS_WORKER = 1
#: The largest salt (``TOPOFUSION_PARTITION_SALT``).
MAX_SALT = 2**31 - 1
#: The most workers of one network (N of ``--partition K/N``): every owner lookup weighs every
#: worker, and the exchange sends every table to every worker, so far beyond the continental
#: sizing's 4 (docs/scale-out.md) it costs more than it shares out.
MAX_WORKERS = 256
#: Salts :func:`balanced_salt` tries: with 1 000, a network of 12 radars and 66 pairs gets
#: shares within a few per cent of 1/N for N up to 4 (a search of under a second per N).
BALANCE_TRIES = 1000
#: What worker 1 of N > 1 does beyond its radars and pairs, as a share of one worker's whole
#: load: it draws the whole picture, solves the biases and decodes every other worker's links
#: and registration rows.  Measured 0.13-0.16 (bench/bench_partition.py, national and
#: continental scenarios, 2 and 4 workers): :func:`balanced_salt` gives worker 1 that much less.
FIRST_WORKER_EXTRA = 0.15
#: Sites at most this far apart (km) may see the same aircraft: two 300 km en-route radars
#: (``topofusion partition --pair-km``, the pairs :func:`balanced_salt` shares out).
PAIR_KM = 600.0

_SPEC = re.compile(r"^\s*(\d+)\s*/\s*(\d+)\s*$")


@lru_cache(maxsize=65536)
def _owner(name: str, count: int, salt: int = 0) -> int:
    best, owner = -1, 1
    for k in range(1, count + 1):
        text = f"{k}:{name}" if salt == 0 else f"{salt}:{k}:{name}"
        digest = hashlib.blake2b(text.encode(), digest_size=8).digest()
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
    #: Mixed into every weight (0: none); the same in every worker of a network.
    salt: int = 0

    def __post_init__(self) -> None:
        if not 1 <= self.index <= self.count:
            raise ValueError(f"partition {self.index}/{self.count}: need 1 <= K <= N")
        if self.count > MAX_WORKERS:
            raise ValueError(f"partition {self.index}/{self.count}: at most {MAX_WORKERS} workers (N)")
        if not 0 <= self.salt <= MAX_SALT:
            raise ValueError(f"partition salt {self.salt}: need 0 <= salt <= {MAX_SALT}")

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
        return 1 if self.count == 1 else _owner(name, self.count, self.salt)

    def owns(self, name: str) -> bool:
        """This worker owns a source (radar or reference) id."""
        return self.count == 1 or _owner(name, self.count, self.salt) == self.index

    def owns_pair(self, a: str, b: str, references: Container[str] = ()) -> bool:
        """This worker correlates the pair of sources ``a``, ``b`` (``references``: the ids of
        the reference sources; a pair of a radar and a reference goes with the radar)."""
        if self.count == 1:
            return True
        if (a in references) != (b in references):
            return self.owns(b if a in references else a)
        return _owner(pair_name(a, b), self.count, self.salt) == self.index


def candidate_pairs(
    ids: Sequence[str], positions: Mapping[str, tuple[float, float]], max_m: float
) -> list[tuple[str, str]]:
    """The pairs of ``ids`` whose cover can overlap: sites (``positions``: latitude and
    longitude, degrees) at most ``max_m`` apart; a pair with an id of no known position counts."""
    ecef = {rid: geodetic_to_ecef(*positions[rid], 0.0) for rid in ids if rid in positions}
    return [
        (a, b)
        for a, b in itertools.combinations(sorted(ids), 2)
        if a not in ecef or b not in ecef or float(np.linalg.norm(ecef[a] - ecef[b])) <= max_m
    ]


def shares(count: int, salt: int, radars: Sequence[str], pairs: Sequence[tuple[str, str]]) -> list[float]:
    """Each worker's share of the work: the mean of its share of ``radars`` (tracking) and of
    ``pairs`` (correlation), each 0..1, and for worker 1 of N > 1 also :data:`FIRST_WORKER_EXTRA`."""
    r = np.zeros(count)
    p = np.zeros(count)
    for name in radars:
        r[_owner(name, count, salt) - 1] += 1
    for a, b in pairs:
        p[_owner(pair_name(a, b), count, salt) - 1] += 1
    out = (r / max(len(radars), 1) + p / max(len(pairs), 1)) / 2
    out[0] += FIRST_WORKER_EXTRA if count > 1 else 0.0
    return [float(x) for x in out]


def balanced_salt(
    count: int, radars: Sequence[str], pairs: Sequence[tuple[str, str]], tries: int = BALANCE_TRIES
) -> int:
    """The salt in ``0..tries-1`` whose busiest worker has the smallest share (:func:`shares`;
    the lowest such salt): the same answer for the same radars, pairs and count."""
    best, best_salt = np.inf, 0
    for salt in range(tries):
        busiest = max(shares(count, salt, radars, pairs))
        if busiest < best - 1e-12:
            best, best_salt = busiest, salt
    return best_salt
