"""The service's queryables (contract §1): ``get {prefix}/status``, ``{prefix}/pairs/**``,
``{prefix}/system/tracks`` and ``{prefix}/radar/*/performance``, answered from the latest
snapshot without locks (Zenoh's threads run them).  Partitioned, only the worker that draws the
system tracks (worker 1) declares ``{prefix}/system/tracks``: the others' answer would be empty."""

from __future__ import annotations

from typing import Any, Protocol

import zenoh

from service.engine import Snapshot
from service.pipeline.partition import Partition
from service.wire.keys import Keys
from service.wire.outputs import encode

_JSON = zenoh.Encoding.APPLICATION_JSON


class Views(Protocol):
    """What the queryables read: the node's status and latest snapshot."""

    @property
    def snapshot(self) -> Snapshot: ...

    def status(self) -> dict[str, Any]: ...


#: The system tracks a ``get {prefix}/system/tracks?status=...`` may ask for (default confirmed).
SYSTEM_STATUSES = ("confirmed", "tentative", "all")


def declare_queryables(
    session: zenoh.Session, keys: Keys, views: Views, partition: Partition | None = None
) -> list[Any]:
    """Declare the queryables on ``session``; returns them (to undeclare at the stop)."""

    def on_status(query: zenoh.Query) -> None:
        query.reply(keys.status, encode(views.status()), encoding=_JSON)

    def on_system(query: zenoh.Query) -> None:
        status = query.parameters.get("status")
        status = "confirmed" if status is None else status  # (``status=``: refused, as over HTTP)
        if status not in SYSTEM_STATUSES:
            # (the parameter quoted in part: a selector may be kilobytes long)
            query.reply_err(f"status {status[:40]!r}: expected one of {', '.join(SYSTEM_STATUSES)}")
            return
        query.reply(keys.system_tracks, encode(views.snapshot.system_tracks(status)), encoding=_JSON)

    def on_performance(query: zenoh.Query) -> None:
        """Each radar whose ``RadarPerformance`` key the query's selector names (partitioned:
        each radar this worker owns, the one worker with its plots, so one answer a radar)."""
        wanted = query.key_expr
        snap = views.snapshot
        for radar_id in sorted(snap.sites):
            key = keys.performance(radar_id)
            mine = partition is None or partition.owns(radar_id)
            if mine and wanted.intersects(zenoh.KeyExpr(key)):
                body = snap.radar_performance(radar_id)
                if body is not None:
                    query.reply(key, encode(body), encoding=_JSON)

    def on_pairs(query: zenoh.Query) -> None:
        wanted = query.key_expr
        for view in views.snapshot.pair_views:
            key = keys.pairs(view.radar_a, view.radar_b)
            if wanted.intersects(zenoh.KeyExpr(key)):
                query.reply(key, encode(view.body("all")), encoding=_JSON)

    draws = partition is None or partition.whole or partition.solves_biases
    return [
        session.declare_queryable(keys.status, on_status),
        session.declare_queryable(keys.pairs_all, on_pairs),
        *([session.declare_queryable(keys.system_tracks, on_system)] if draws else []),
        session.declare_queryable(keys.performance_all, on_performance),
    ]
