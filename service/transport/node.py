"""The running service: a Zenoh session, one worker thread around the engine, queryables.

Threads (README "Architecture"):

* Zenoh's network thread runs the subscriber callbacks (directly, so that samples keep their
  wire order across keys), which only put ``(key, bytes, time)`` on a bounded queue.  When
  the queue is full the callback waits (up to ``put_timeout_s``), which stalls Zenoh's
  reader and pushes back to publishers using ``CongestionControl.BLOCK``; only if that
  wait times out is a sample dropped, and every drop is counted (``/status``
  ``queue.dropped``, metric ``topofusion_queue_dropped_total``) and logged.
* One worker thread takes samples in arrival order, calls ``engine.ingest`` and publishes
  what it returns, then swaps in a new immutable :class:`~service.engine.Snapshot`.
* Queryables and HTTP handlers read the latest snapshot without locks.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any

import zenoh

from service.engine import Engine, EngineConfig, Outgoing, Snapshot
from service.transport.session import ZenohOptions, open_session
from service.wire.keys import Keys
from service.wire.outputs import encode

log = logging.getLogger(__name__)

_STOP = object()
#: Puts a new publisher makes before trusting its matching status (see ``_publish``).
UNCONDITIONAL_PUTS = 8


@dataclass
class QueueStats:
    capacity: int
    dropped: int = 0
    high_water: int = 0


class RateLimitedLog:
    """Logs a rejection reason at most once per ``interval_s``, with a count of the rest."""

    def __init__(self, interval_s: float = 10.0) -> None:
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warn(self, reason: str, message: str) -> None:
        now = time.monotonic()
        if now - self._last.get(reason, -1e9) >= self.interval_s:
            extra = self._suppressed.pop(reason, 0)
            suffix = f" (+{extra} more since last report)" if extra else ""
            log.warning("rejected (%s): %s%s", reason, message, suffix)
            self._last[reason] = now
        else:
            self._suppressed[reason] = self._suppressed.get(reason, 0) + 1


class ServiceNode:
    """Owns the Zenoh session and the worker; start/stop are idempotent."""

    def __init__(
        self,
        engine_config: EngineConfig,
        zenoh_options: ZenohOptions,
        queue_size: int = 4096,
        put_timeout_s: float = 10.0,
        session: zenoh.Session | None = None,
        radars: tuple[str, ...] = (),
        correlation_process: bool = True,
    ) -> None:
        self.engine = Engine(engine_config, correlation_process=correlation_process)
        self.keys = Keys(engine_config.prefix)
        self.zenoh_options = zenoh_options
        self.queue: queue.Queue[Any] = queue.Queue(maxsize=queue_size)
        self.queue_stats = QueueStats(capacity=queue_size)
        self.put_timeout_s = put_timeout_s
        self.radars = radars
        self.snapshot: Snapshot = self.engine.snapshot()
        self.started_at = time.monotonic()
        self.not_ready_reason = "not started"
        self.processed = 0
        self._own_session = session is None
        self._session: zenoh.Session | None = session
        self._declared: list[Any] = []
        self._publishers: dict[str, list[Any]] = {}  # key -> [publisher, unconditional puts left]
        self._worker: threading.Thread | None = None
        self._rejections = RateLimitedLog()
        self._stopping = threading.Event()

    # -- lifecycle -------------------------------------------------------------------------
    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError("node not started")
        return self._session

    def open(self) -> None:
        """Open the Zenoh session (if not given one); raises ``RuntimeError`` saying why not."""
        if self._session is None:
            self._session = open_session(self.zenoh_options)

    def start(self) -> None:
        if self._worker is not None:
            return
        self.open()
        s = self.session
        # Direct (not "indirect") callbacks: zenoh-python otherwise runs each subscriber's
        # callback on its own thread, and a site could then reach the queue after the plots
        # that followed it on the wire.  Run on Zenoh's network thread, the callbacks keep the
        # wire order across keys, and a full queue pushes back on the link itself.
        self._declared = [
            s.declare_subscriber(key, zenoh.handlers.Callback(self._on_sample, indirect=False))
            for key in self._input_keys()
        ]
        self._declared += [
            s.declare_queryable(self.keys.status, self._on_status_query),
            s.declare_queryable(self.keys.pairs_all, self._on_pairs_query),
        ]
        self._worker = threading.Thread(target=self._run, name="topofusion-worker", daemon=True)
        self._worker.start()
        self.not_ready_reason = ""
        log.info(
            "zenoh session open (mode=%s, listen=%s, connect=%s), prefix %r",
            self.zenoh_options.effective_mode,
            self.zenoh_options.effective_listen(),
            self.zenoh_options.effective_connect(),
            self.keys.prefix,
        )

    def _input_keys(self) -> list[str]:
        """Every radar's inputs, or only the owned radars' (partitioning by configuration)."""
        ids = self.radars or ("*",)
        radar_keys = [k for rid in ids for k in (self.keys.site(rid), self.keys.plots(rid))]
        return [*radar_keys, self.keys.ais_inputs]

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop taking samples, finish the queue, close the session (bounded by ``timeout_s``)."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        self.not_ready_reason = "shutting down"
        for d in self._declared:
            try:
                d.undeclare()
            except Exception:  # already gone with the session
                log.debug("undeclare failed", exc_info=True)
        self._declared = []
        if self._worker is not None:
            try:
                self.queue.put(_STOP, timeout=timeout_s)
            except queue.Full:
                log.warning("worker queue full at shutdown; abandoning %d samples", self.queue.qsize())
            self._worker.join(timeout=timeout_s)
        for pub, _ in self._publishers.values():
            try:
                pub.undeclare()
            except Exception:  # already gone with the session
                log.debug("undeclare failed", exc_info=True)
        self._publishers = {}
        self.engine.close()
        if self._own_session and self._session is not None:
            self._session.close()
        self._session = None

    @property
    def ready(self) -> bool:
        return self._session is not None and self._worker is not None and self._worker.is_alive()

    # -- Zenoh callbacks (no work here) ----------------------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        item = (str(sample.key_expr), sample.payload.to_bytes(), time.time())
        try:
            self.queue.put(item, timeout=self.put_timeout_s)
        except queue.Full:
            self.queue_stats.dropped += 1
            log.error("ingest queue full for %.1f s: dropped a sample on %s", self.put_timeout_s, item[0])

    def _on_status_query(self, query: zenoh.Query) -> None:
        query.reply(self.keys.status, encode(self.status()), encoding=zenoh.Encoding.APPLICATION_JSON)

    def _on_pairs_query(self, query: zenoh.Query) -> None:
        wanted = query.key_expr
        for view in self.snapshot.pair_views:
            key = self.keys.pairs(view.radar_a, view.radar_b)
            if wanted.intersects(zenoh.KeyExpr(key)):
                query.reply(key, encode(view.body("all")), encoding=zenoh.Encoding.APPLICATION_JSON)

    # -- worker ------------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            item = self.queue.get()
            if item is _STOP:
                break
            self._handle(*item)
            self.queue_stats.high_water = max(self.queue_stats.high_water, self.queue.qsize() + 1)
            if self.queue.empty() or self.processed % 64 == 0:
                self.snapshot = self.engine.snapshot()
        self._publish(self.engine.flush())
        self.snapshot = self.engine.snapshot()

    def _handle(self, key: str, payload: bytes, received: float) -> None:
        self.processed += 1
        try:
            out = self.engine.ingest(key, payload, received)
        except Exception:  # engine.ingest never raises on input; this is a last resort
            log.exception("engine failed on %s", key)
            return
        self._publish(out)

    def _publish(self, out: list[Outgoing]) -> None:
        """Put each output whose key has a subscriber (an output nobody hears is never encoded).

        A new publisher learns of the subscribers that already exist a round trip after it is
        declared, so its first ``UNCONDITIONAL_PUTS`` outputs are put whatever its matching
        status says; errors are always put.
        """
        session = self._session
        if session is None:
            return
        for msg in out:
            errors = msg.key == self.keys.errors
            if errors:
                body = msg.body()
                self._rejections.warn(body["reason"], f"{body['key']}: {body['detail']}")
            try:
                entry = self._publishers.get(msg.key)
                if entry is None:
                    pub = session.declare_publisher(msg.key, encoding=zenoh.Encoding.APPLICATION_JSON)
                    entry = self._publishers[msg.key] = [pub, UNCONDITIONAL_PUTS]
                pub, fresh = entry
                if errors or fresh > 0 or pub.matching_status.matching:
                    entry[1] = fresh - 1
                    pub.put(msg.payload)
            except Exception:
                log.exception("publish failed on %s", msg.key)

    # -- views ---------------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        snap = self.snapshot
        return {
            "uptime_s": round(time.monotonic() - self.started_at, 3),
            "zenoh": {
                "mode": self.zenoh_options.effective_mode,
                "listen": self.zenoh_options.effective_listen(),
                "connect": self.zenoh_options.effective_connect(),
            },
            **snap.status_core(),
            "queue": {
                "depth": self.queue.qsize(),
                "capacity": self.queue_stats.capacity,
                "high_water": self.queue_stats.high_water,
                "dropped": self.queue_stats.dropped,
            },
        }
