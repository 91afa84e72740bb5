"""The members and links of the system tracks at one data time (see :mod:`.system_tracks`).

Each radar's tracks (tentative ones too: a radar track alone is a tentative or confirmed system
track of one member) are extrapolated to the update's time and bias-compensated with the
current joint estimate, their covariance widened by what the estimate's own uncertainty adds
(:func:`~service.correlation.registration.compensate`).  Reference tracks (AIS, ADS-B) are
extrapolated only.  The links are the confirmed pairs of every pair book, with their score
(:class:`Links`: taken from a book here, or received from the worker that correlates the pair).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace

import numpy as np

from service.columns import concat_rows
from service.correlation.pairkeys import find, id_codes
from service.correlation.pairs import PairBook
from service.correlation.prediction import PredictionParams, predict_tracks
from service.correlation.registration import BiasSolution, compensate
from service.fusion.system_tracks import FloatArray, IntArray, Members
from service.geo import Site
from service.tracking.base import TrackTable


@dataclass(frozen=True)
class Links:
    """The confirmed pairs of one pair book: ``track_a[k]`` of ``source_a`` with ``track_b[k]``
    of ``source_b``, at ``score[k]``."""

    source_a: str
    source_b: str
    track_a: np.ndarray
    track_b: np.ndarray
    score: np.ndarray

    @staticmethod
    def of_book(source_a: str, source_b: str, book: PairBook) -> Links:
        """A book's confirmed pairs (copies: the book changes on)."""
        conf = book.confirmed
        score = np.asarray(book.score[conf], dtype=float)
        return Links(source_a, source_b, book.track_a[conf], book.track_b[conf], score)


def members_and_links(
    time_s: float,
    radars: Mapping[str, tuple[Site, TrackTable]],
    references: Mapping[str, TrackTable],
    links: Iterable[Links],
    solution: BiasSolution | None,
    prediction: PredictionParams,
) -> tuple[Members, IntArray, IntArray, FloatArray]:
    """Members (radars in id order, then references) and the links ``(row a, row b, score)``
    between them (``links``: every pair book's confirmed pairs)."""
    every = replace(prediction, confirmed_only=False)
    parts: list[Members] = []
    for rid in sorted(radars):
        site, table = radars[rid]
        snap = predict_tracks(table, site, time_s, every)
        extra = np.zeros((len(snap), 3, 3))
        if solution is not None and len(snap):
            snap, extra = compensate(snap, *solution.of(rid))
        parts.append(
            _members(
                rid,
                False,
                table,
                snap.track_id,
                snap.position,
                snap.velocity,
                snap.pos_cov + extra,
                snap.vel_cov,
            )
        )
    for sid in sorted(references):
        table = references[sid]
        snap = predict_tracks(table, None, time_s, every)
        parts.append(
            _members(
                sid, True, table, snap.track_id, snap.position, snap.velocity, snap.pos_cov, snap.vel_cov
            )
        )
    members = _concat(parts)
    # Each source's members are contiguous and in track id order (its table's order): a book's
    # tracks are looked up within their source's block alone.
    # (their ids searched as integer codes where they have them, :func:`id_codes`)
    blocks: dict[str, tuple[int, np.ndarray, np.ndarray | None, np.ndarray]] = {}
    start = 0
    for part in parts:
        if len(part.source):
            ids = part.track_id
            order = np.arange(len(ids)) if bool(np.all(ids[1:] >= ids[:-1])) else np.argsort(ids)
            blocks[str(part.source[0])] = (start, ids[order], id_codes(ids[order]), order)
        start += len(part.source)

    def rows(source: str, query: np.ndarray) -> np.ndarray:
        block = blocks.get(source)
        if block is None or not len(query):
            return np.full(query.shape[0], -1, dtype=np.int64)
        offset, ids, codes, order = block
        query_codes = id_codes(query) if codes is not None else None
        if codes is not None and query_codes is not None:
            ids, query = codes, query_codes
        at = np.minimum(np.searchsorted(ids, query), ids.shape[0] - 1)
        return np.where(ids[at] == query, offset + order[at], -1)

    # Every link's tracks of one source are searched at once (one search a source, not two a
    # link: a national picture has 66 links a drawing), then handed back link by link.
    given = [link for link in links if len(link.track_a)]
    asked: dict[str, list[np.ndarray]] = {}
    for link in given:
        asked.setdefault(link.source_a, []).append(link.track_a)
        asked.setdefault(link.source_b, []).append(link.track_b)
    found = {source: rows(source, np.concatenate(parts)) for source, parts in asked.items()}
    taken = dict.fromkeys(found, 0)

    def next_rows(source: str, n: int) -> np.ndarray:
        start = taken[source]
        taken[source] = start + n
        return found[source][start : start + n]

    la, lb, sc = [], [], []
    for link in given:
        a = next_rows(link.source_a, len(link.track_a))
        b = next_rows(link.source_b, len(link.track_b))
        ok = (a >= 0) & (b >= 0)
        la.append(a[ok])
        lb.append(b[ok])
        sc.append(link.score[ok])
    if not la:
        return members, np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64), np.empty(0)
    return (
        members,
        np.concatenate(la).astype(np.int64),
        np.concatenate(lb).astype(np.int64),
        np.concatenate(sc),
    )


def _members(
    source: str,
    reference: bool,
    table: TrackTable,
    track_id: np.ndarray,
    position: FloatArray,
    velocity: FloatArray,
    pos_cov: FloatArray,
    vel_cov: FloatArray,
) -> Members:
    at = find(table.track_id.astype(str), track_id.astype(str))
    n = track_id.shape[0]
    return Members(
        source=np.full(n, source),
        track_id=track_id.astype(str),
        reference=np.full(n, reference),
        confirmed=table.confirmed[at] if n else np.empty(0, dtype=bool),
        position=position,
        velocity=velocity,
        pos_cov=pos_cov,
        vel_cov=vel_cov,
    )


def _concat(parts: list[Members]) -> Members:
    if not parts:
        e = np.empty(0)
        return Members(
            e.astype(str),
            e.astype(str),
            e.astype(bool),
            e.astype(bool),
            np.empty((0, 3)),
            np.empty((0, 3)),
            np.empty((0, 3, 3)),
            np.empty((0, 3, 3)),
        )
    return concat_rows(Members, parts)
