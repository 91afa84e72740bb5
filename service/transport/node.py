"""The running service: a Zenoh session, one worker thread around the engine, queryables.

Threads (docs/architecture.md):

* Zenoh's network thread runs the subscriber callbacks (directly, so that samples keep their
  wire order across keys), which only put ``(key, bytes, time)`` on a queue bounded in
  samples and in bytes (:class:`~service.transport.ingest_queue.BoundedQueue`).  When the
  queue is full the callback waits, at most ``queue_wait_s``, which pushes back on
  publishers using ``CongestionControl.BLOCK``; in router mode the same thread carries
  everybody's traffic, so the wait is short, and only after it is a sample dropped: every
  drop is counted by key (``/status`` ``queue.dropped`` and ``queue.dropped_by_key``) and
  logged.  The queue is fair by source: a source holds at most its share of it (a flooding
  source's excess is dropped at once, without stalling the network thread), and after a
  flooding source's sample the worker takes another's (``ingest_queue``, "Fair intake").
* A watcher thread follows the Zenoh connection (``/readyz`` says ``no zenoh connection``
  while a client or a peer with connect endpoints has lost them all; both changes are
  logged).  A client whose router is not up yet keeps trying with back-off on a connector
  thread while the HTTP port answers (``connecting to zenoh``).
* A stop (SIGTERM/SIGINT) undeclares the input subscribers first, gives the worker
  ``stop_grace_s`` to finish the queue, publishes the final outputs, and logs how many
  queued samples were processed and how many, if any, were left (contract §4.6).
* One worker thread takes samples in arrival order (but never two of a flooding source's
  while another source's waits), calls ``engine.ingest``, hands what it returns to the
  publisher thread, then swaps in a new immutable :class:`~service.engine.Snapshot`.
* One publisher thread puts the outputs.  The worker never waits on the network: partitioned
  workers publish to each other, and a worker blocked on a put to a peer whose queue is full
  while that peer is blocked on a put to it would stall both (the outbox is bounded by count,
  ``outbox_size``; beyond it the worker waits).
* Queryables and HTTP handlers read the latest snapshot without locks.

Partitioned (``--partition K/N``): the worker declares a liveliness token
``{prefix}/workers/{K}``, puts its own status on ``{prefix}/workers/{K}/status`` every
``status_interval_s`` (wall clock: this is operations, not data), and keeps the other workers'
latest statuses, so that ``/status`` (HTTP and ``get {prefix}/status``) describes the whole
network and says which partitions are missing.  Plots of radars another worker owns are
dropped in the Zenoh callback, before the queue.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import orjson
import zenoh

from service.engine import Engine, EngineConfig, Snapshot
from service.state import StateKeeper
from service.transport.ingest_queue import MAX_DROP_KEYS, OTHER_KEYS, BoundedQueue
from service.transport.network_status import merge_statuses, partition_section
from service.transport.session import OpenCancelledError, ZenohOptions, listening, open_session, unreachable
from service.wire.keys import PRIORITY_KINDS, Keys, parse_key
from service.wire.models import MAX_PAYLOAD_BYTES
from service.wire.outgoing import Outgoing
from service.wire.outputs import encode

log = logging.getLogger(__name__)

_STOP = object()
#: Readers' snapshot is rebuilt at most this often (s) while messages keep coming (and when
#: the worker falls idle): a partitioned worker takes a message from the others every few ms.
SNAPSHOT_MIN_S = 0.05
#: How often (s) an idle worker takes the correlation process's late answers.
IDLE_POLL_S = 0.05
#: Puts a new publisher makes before trusting its matching status (see ``_publish``).
UNCONDITIONAL_PUTS = 8
#: Most output publishers held; the least recently used beyond goes (``_bound_publishers``).
#: A national network's worker puts on about a hundred keys (tracks, pairs, system tracks).
MAX_PUBLISHERS = 1_024
#: At a stop, how long (s) past the grace the worker may take to finish the message it is on
#: and flush the engine (the final outputs) before the stop goes on without it.
FINISH_S = 5.0
#: How often (s) the watcher looks at the Zenoh connection: a lost router shows within this.
CONNECTION_POLL_S = 0.25
#: How often (s) the worker looks for sources silent on the wall clock (``pipeline.feed``).
EXPIRY_POLL_S = 1.0
#: A drop on a full queue is logged at most this often per key (s), with the count since.
DROP_LOG_INTERVAL_S = 10.0


class RateLimitedLog:
    """Logs ``what (reason): message`` at most once per ``interval_s`` and reason, with a count
    of the rest."""

    def __init__(
        self, interval_s: float = 10.0, what: str = "rejected", level: int = logging.WARNING
    ) -> None:
        self.interval_s = interval_s
        self.what = what
        self.level = level
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warn(self, reason: str, message: str) -> None:
        if reason not in self._last and len(self._last) >= MAX_DROP_KEYS:
            reason = OTHER_KEYS  # (made-up keys must not grow the table without end)
        now = time.monotonic()
        if now - self._last.get(reason, -1e9) >= self.interval_s:
            extra = self._suppressed.pop(reason, 0)
            suffix = f" (+{extra} more since last report)" if extra else ""
            log.log(self.level, "%s (%s): %s%s", self.what, reason, message, suffix)
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
        queue_wait_s: float = 0.5,
        session: zenoh.Session | None = None,
        radars: tuple[str, ...] = (),
        correlation_process: bool = True,
        outbox_size: int = 65536,
        status_interval_s: float = 1.0,
        peer_query_timeout_s: float = 10.0,
        peer_grace_s: float = 15.0,
        queue_bytes: int = 256 * 1024 * 1024,
        stop_grace_s: float = 20.0,
        stall_s: float = 30.0,
        state: StateKeeper | None = None,
    ) -> None:
        self.peer_query_timeout_s = peer_query_timeout_s
        self.engine = Engine(engine_config, correlation_process=correlation_process)
        self.partition = engine_config.partition
        self.status_interval_s = status_interval_s
        self.outbox: queue.Queue[Any] = queue.Queue(maxsize=outbox_size)
        #: Partitioned: the other workers' latest statuses (raw, by K) and who is alive.
        self._peer_status: dict[int, tuple[float, bytes]] = {}
        self._alive: set[int] = set()
        #: Workers whose token left, and when (monotonic): waited for until ``peer_grace_s``.
        self._gone_at: dict[int, float] = {}
        self._waited: set[int] | None = None
        self.peer_grace_s = peer_grace_s
        self._publisher: threading.Thread | None = None
        self.keys = Keys(engine_config.prefix)
        self.zenoh_options = zenoh_options
        #: Fair by source (``ingest_queue``): a flooding source drops its own excess, not others'.
        self.queue = BoundedQueue(queue_size, queue_bytes, fair_by=self._source_of)
        #: Partitioned: the other workers' messages, taken before inputs (see ``_next_item``);
        #: bounded like the inputs' (anyone who may put on their keys could flood it; a lost
        #: track-states change costs that radar until its owner's next full table).
        self.peer_queue = BoundedQueue(queue_size, queue_bytes)
        self._items = threading.Semaphore(0)  # one release per item put on either queue
        self.queue_wait_s = queue_wait_s
        self.stop_grace_s = stop_grace_s
        self.stall_s = stall_s
        #: ``--state-dir``: restored here, before any input (``OSError`` when the directory
        #: cannot be used), written on data time and at a stop.
        self.state = state
        if state is not None:
            state.restore(self.engine)
        self._drop_log = RateLimitedLog(DROP_LOG_INTERVAL_S, "dropped on a full ingest queue", logging.ERROR)
        self.radar_filter = radars
        self.snapshot: Snapshot = self.engine.snapshot()
        self.started_at = time.monotonic()
        self.processed = 0
        #: Of those, plot batches (said at a stop).
        self.processed_plots = 0
        #: When the worker last took a sample or found none (monotonic): progress, for /readyz.
        self._last_take = time.monotonic()
        #: Whether the session reaches what it must (see ``_linked_now``); the watcher's view.
        self._linked = True
        self._connecting = False
        self._inputs: list[Any] = []
        self._own_session = session is None
        self._session: zenoh.Session | None = session
        self._declared: list[Any] = []
        self._publishers: dict[str, list[Any]] = {}  # key -> [publisher, unconditional puts left]
        self._worker: threading.Thread | None = None
        #: Set when the stop begins (input taken no more); ``_stopped``: :meth:`stop` ran.
        self._stopping = threading.Event()
        self._stopped = False
        self._stop_began = 0.0
        self._stop_deadline = float("inf")
        self._queued_at_stop = 0
        self._taken_at_stop = 0
        #: Start and stop, and the connector's handing over of its session, one at a time.
        self._life = threading.Lock()
        #: Why the session could not be opened (a configuration Zenoh refused), or "".
        self.failure = ""
        #: Told of such a failure (the command ends then, with status 2).
        self.on_fatal: Callable[[str], None] | None = None

    # -- lifecycle -------------------------------------------------------------------------
    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError("node not started")
        return self._session

    def open(self) -> bool:
        """Open the Zenoh session (if not given one): True when open, False when the router
        cannot be reached yet (:meth:`start` then keeps trying); raises ``RuntimeError``
        saying why for any other failure (a configuration error)."""
        if self._session is None:
            try:
                self._session = open_session(self.zenoh_options)
            except RuntimeError as exc:
                if not unreachable(exc):
                    raise
                log.warning("%s; retrying with back-off", exc)
                return False
        return True

    def start(self) -> None:
        """Start the worker on an open session, or, while the router cannot be reached, a
        connector that opens it with back-off and starts the worker then."""
        with self._life:
            if self._worker is not None or self._connecting or self._stopping.is_set():
                return
            if not self.open():
                self._connecting = True
                threading.Thread(target=self._connect, name="topofusion-connect", daemon=True).start()
                return
            self._start_on_session()

    def _connect(self) -> None:
        """The connector: open the session with back-off until the router answers (or a stop),
        then start.  A failure that is not "unreachable" ends it: ``/readyz`` says why and
        ``on_fatal`` hears of it (the command then ends with status 2)."""

        def say(reason: str, wait_s: float) -> None:
            up = listening(self.zenoh_options.effective_connect())
            if up:
                log.warning(
                    "zenoh router at %s accepts connections but refused the session (a TLS "
                    "certificate, user or password it does not take, or not a Zenoh router): %s; "
                    "retrying in %.1f s",
                    ", ".join(up),
                    reason,
                    wait_s,
                )
            else:
                log.warning("zenoh router not reachable (%s); retrying in %.1f s", reason, wait_s)

        try:
            session = open_session(
                self.zenoh_options, math.inf, on_retry=say, retry_if=unreachable, stop=self._stopping
            )
        except OpenCancelledError:
            return
        except RuntimeError as exc:
            self.failure = str(exc)
            log.error("%s", exc)
            if self.on_fatal is not None:
                self.on_fatal(self.failure)
            return
        finally:
            self._connecting = False
        with self._life:
            if self._stopping.is_set():
                session.close()  # a stop came while the last attempt was under way
                return
            self._session = session
            log.info("zenoh router reached")
            self._start_on_session()

    def _start_on_session(self) -> None:
        s = self.session
        # Direct (not "indirect") callbacks: zenoh-python otherwise runs each subscriber's
        # callback on its own thread, and a site could then reach the queue after the plots
        # that followed it on the wire.  Run on Zenoh's network thread, the callbacks keep the
        # wire order across keys, and a full queue pushes back on the link itself.
        self._inputs = [
            s.declare_subscriber(key, zenoh.handlers.Callback(self._on_sample, indirect=False))
            for key in self._input_keys()
        ]
        if self._stopping.is_set():  # a signal while they were declared: stop_input missed them
            self._undeclare_inputs()
        self._declared = [
            s.declare_queryable(self.keys.status, self._on_status_query),
            s.declare_queryable(self.keys.pairs_all, self._on_pairs_query),
            s.declare_queryable(self.keys.system_tracks, self._on_system_query),
            s.declare_queryable(self.keys.performance_all, self._on_performance_query),
        ]
        if not self.partition.whole:
            # A worker not seen yet is waited for as one that just left: for peer_grace_s.
            self._gone_at = {
                k: time.monotonic() for k in range(1, self.partition.count + 1) if k != self.partition.index
            }
            self._declared += [
                s.declare_subscriber(
                    self.keys.worker_statuses, zenoh.handlers.Callback(self._on_worker_status, indirect=False)
                ),
                s.liveliness().declare_subscriber(self.keys.workers, self._on_worker_token, history=True),
                s.liveliness().declare_token(self.keys.worker(self.partition.index)),
            ]
        self._publisher = threading.Thread(
            target=self._send_outputs, name="topofusion-publisher", daemon=True
        )
        self._publisher.start()
        self._worker = threading.Thread(target=self._run, name="topofusion-worker", daemon=True)
        self._worker.start()
        self._linked = self._linked_now()
        threading.Thread(target=self._watch, name="topofusion-watch", daemon=True).start()
        log.info(
            "zenoh session open (mode=%s, listen=%s, connect=%s), prefix %r",
            self.zenoh_options.effective_mode,
            self.zenoh_options.effective_listen(),
            self.zenoh_options.effective_connect(),
            self.keys.prefix,
        )

    def _input_keys(self) -> list[str]:
        """Every radar's inputs (or only those of ``--radars``), and what partitioned workers
        send each other."""
        ids = self.radar_filter or ("*",)
        radar_keys = [k for rid in ids for k in (self.keys.site(rid), self.keys.plots(rid))]
        peer = list(self.keys.peer_inputs) if not self.partition.whole else []
        return [*radar_keys, self.keys.ais_inputs, self.keys.adsb_inputs, *peer]

    def stop_input(self, grace_s: float | None = None) -> None:
        """Take no more input: undeclare the input subscribers, close the queue (a sample a
        callback still brings is counted as dropped), and give the worker ``grace_s`` (default
        ``stop_grace_s``) from now to finish the queue.  The first step of a stop: the HTTP
        server calls it as soon as the signal comes.  Idempotent."""
        if self._stopping.is_set():
            return
        self._stop_began = time.monotonic()
        self._stop_deadline = self._stop_began + (self.stop_grace_s if grace_s is None else grace_s)
        self._stopping.set()
        self._undeclare_inputs()
        self._queued_at_stop, self._taken_at_stop = self.queue.close()

    def _undeclare_inputs(self) -> None:
        inputs, self._inputs = self._inputs, []
        for d in inputs:
            try:
                d.undeclare()
            except Exception:  # already gone with the session, or undeclared twice
                log.debug("undeclare failed", exc_info=True)

    def stop(self, grace_s: float | None = None) -> None:
        """Stop taking input, let the worker finish the queue for up to ``grace_s`` (default
        ``stop_grace_s``), publish the final outputs, write the state, close the session.
        Bounded: the grace plus ``FINISH_S`` for the worker, ``FINISH_S`` for the publisher.
        Idempotent."""
        with self._life:  # (a connector that reaches the router now closes its session)
            if self._stopped:
                return
            self._stopped = True
            self.stop_input(grace_s)
        worker = self._worker
        if worker is None:
            log.info("stop: no zenoh session was open; nothing was queued")
        else:
            self.queue.put_anyway(_STOP)
            self._items.release()
            # The worker gives up the queue at the deadline, then flushes the engine (the final
            # outputs); a message it is still on gets FINISH_S more, no longer.
            worker.join(max(0.0, self._stop_deadline - time.monotonic()) + FINISH_S)
            self._log_stop(busy=worker.is_alive())
            if self.state is not None and not worker.is_alive():
                self.state.save(self.engine)  # (a busy worker's engine is not read under it)
        for d in self._declared:
            try:
                d.undeclare()
            except Exception:  # already gone with the session
                log.debug("undeclare failed", exc_info=True)
        self._declared = []
        if self._publisher is not None:
            # The final outputs: whatever the worker handed over, put before the session closes.
            try:
                self.outbox.put(_STOP, timeout=FINISH_S)
            except queue.Full:
                log.error("stop: the publisher is %d outputs behind; not waiting", self.outbox.qsize())
            self._publisher.join(FINISH_S)
        for pub, _ in self._publishers.values():
            try:
                pub.undeclare()
            except Exception:  # already gone with the session
                log.debug("undeclare failed", exc_info=True)
        self._publishers = {}
        if worker is None or not worker.is_alive():
            self.engine.close()  # (not under a busy worker: the correlation child is a daemon)
        if self._own_session and self._session is not None:
            self._session.close()
        self._session = None

    def _log_stop(self, busy: bool) -> None:
        """The one line a stop owes (contract §4.6): how many of the input samples queued at
        the signal it processed, and how many it left, exactly (every sample the worker takes
        during a stop is processed: it looks at the deadline before taking one)."""
        queued = self.queue.items()
        left = [item for item in queued if item is not _STOP]
        marker_taken = len(left) == len(queued)  # (the stop marker is no sample)
        peers = self.peer_queue.qsize()  # the other workers' messages still waiting (partitioned)
        done = self.queue.taken - self._taken_at_stop - marker_taken
        plots = sum(1 for key, _, _ in left if key.endswith("/plots"))
        also = f"; {peers} messages of other workers left" if peers else ""
        if busy:
            log.error("stop: the worker is still busy %.0f s after the grace; not waiting", FINISH_S)
        if left or busy:
            log.error(
                "stop: the %.1f s grace ran out: processed %d, %d of %d queued samples left "
                "unprocessed (%d plot batches); %d plot batches processed in all%s",
                self._stop_deadline - self._stop_began,
                done,
                len(left),
                self._queued_at_stop,
                plots,
                self.processed_plots,
                also,
            )
        else:
            log.info(
                "stop: processed all %d queued samples in %.1f s; 0 left unprocessed; "
                "%d plot batches processed in all%s",
                done,
                time.monotonic() - self._stop_began,
                self.processed_plots,
                also,
            )

    @property
    def not_ready_reason(self) -> str:
        """Why ``/readyz`` is 503 (contract §4.6), or "" when ready."""
        if self._stopping.is_set():
            return "shutting down"
        if self.failure:
            return f"zenoh session failed: {self.failure}"
        if self._connecting:
            return "connecting to zenoh"
        if self._session is None or self._worker is None:
            return "not started"
        if not self._worker.is_alive():
            return "worker not running"
        if not self._linked:
            return "no zenoh connection"
        if self.stalled:
            return "worker stalled"
        return self.engine.feed.stale_reason(time.monotonic())

    @property
    def ready(self) -> bool:
        return not self.not_ready_reason

    @property
    def stalled(self) -> bool:
        """Input has waited ``stall_s`` with the worker taking none of it."""
        waiting = not self.queue.empty() or not self.peer_queue.empty()
        return waiting and time.monotonic() - self._last_take > self.stall_s

    def _linked_now(self) -> bool:
        """Whether the session reaches a router or peer, where it must: a client always, a
        peer or router only when told to connect somewhere (one with no connect endpoint
        stands alone, and its publishers connect to it)."""
        session = self._session
        if session is None:
            return False
        if self.zenoh_options.effective_mode != "client" and not self.zenoh_options.effective_connect():
            return True
        try:
            info = session.info
            return bool(info.routers_zid()) or bool(info.peers_zid())
        except Exception:  # the session is closing
            return False

    def _watch(self) -> None:
        """Follow the connection (wall clock, operations); say when it is lost and back."""
        lost_at = 0.0
        while not self._stopping.wait(CONNECTION_POLL_S):
            linked = self._linked_now()
            if linked == self._linked:
                continue
            self._linked = linked
            if not linked:
                lost_at = time.monotonic()
                log.error(
                    "zenoh connection lost: no router or peer of %s reachable; /readyz is 503 "
                    "until it is back (inputs published meanwhile do not arrive: seq gaps count them)",
                    self.zenoh_options.effective_connect() or "the session",
                )
            else:
                log.warning("zenoh connection back after %.1f s", time.monotonic() - lost_at)

    # -- Zenoh callbacks (no work here) ----------------------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if not self.partition.whole and key.endswith("/plots"):
            kind, ids = parse_key(key, self.keys.prefix)
            if kind == "plots" and not self.partition.owns(ids[0]):
                return  # another worker's radar
        size = len(sample.payload)
        # A payload above the contract's bound is rejected unread: not copied, not queued whole.
        item = (key, sample.payload.to_bytes() if size <= MAX_PAYLOAD_BYTES else size, time.time())
        peer = self.keys.classify_peer(key) if not self.partition.whole else None
        into = self.peer_queue if peer is not None and peer[0] in PRIORITY_KINDS else self.queue
        if into.put(item, size if size <= MAX_PAYLOAD_BYTES else 0, key, self.queue_wait_s):
            self._items.release()
        elif not self._stopping.is_set():
            self._drop_log.warn(key, f"no room for {self.queue_wait_s:.2f} s")

    def _source_of(self, key: str) -> str:
        """The ingest queue's class of a key: its source (a radar's site and plots together)."""
        kind = self.keys.classify(key)
        return kind[1] if kind is not None else key

    def _on_worker_status(self, sample: zenoh.Sample) -> None:
        kind, ids = parse_key(str(sample.key_expr), self.keys.prefix)
        if kind == "worker_status" and int(ids[0]) != self.partition.index:
            self._peer_status[int(ids[0])] = (time.monotonic(), sample.payload.to_bytes())

    def _on_worker_token(self, sample: zenoh.Sample) -> None:
        index = str(sample.key_expr).rsplit("/", 1)[-1]
        if not index.isdigit():
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self._alive.add(int(index))
            self._gone_at.pop(int(index), None)
        else:
            self._alive.discard(int(index))
            self._gone_at[int(index)] = time.monotonic()
            if int(index) != self.partition.index:
                log.warning(
                    "worker %s/%d left (its radars and pairs are missing)", index, self.partition.count
                )

    def _on_status_query(self, query: zenoh.Query) -> None:
        query.reply(self.keys.status, encode(self.status()), encoding=zenoh.Encoding.APPLICATION_JSON)

    def _on_system_query(self, query: zenoh.Query) -> None:
        body = encode(self.snapshot.system_tracks("confirmed"))
        query.reply(self.keys.system_tracks, body, encoding=zenoh.Encoding.APPLICATION_JSON)

    def _on_performance_query(self, query: zenoh.Query) -> None:
        """Each radar whose ``RadarPerformance`` key the query's selector names."""
        wanted = query.key_expr
        snap = self.snapshot
        for radar_id in sorted(snap.sites):
            key = self.keys.performance(radar_id)
            if wanted.intersects(zenoh.KeyExpr(key)):
                body = snap.radar_performance(radar_id)
                if body is not None:
                    query.reply(key, encode(body), encoding=zenoh.Encoding.APPLICATION_JSON)

    def _on_pairs_query(self, query: zenoh.Query) -> None:
        wanted = query.key_expr
        for view in self.snapshot.pair_views:
            key = self.keys.pairs(view.radar_a, view.radar_b)
            if wanted.intersects(zenoh.KeyExpr(key)):
                query.reply(key, encode(view.body("all")), encoding=zenoh.Encoding.APPLICATION_JSON)

    # -- worker ------------------------------------------------------------------------------
    def _run(self) -> None:
        next_status = next_expiry = 0.0
        last_snapshot = 0.0
        while True:
            # Idle with answers of the correlation process still to come: look again soon.
            wait = IDLE_POLL_S if self.engine.answers_pending else self.status_interval_s
            if time.monotonic() >= self._stop_deadline:
                break  # a stop's grace ran out: what is queued stays there, counted by stop()
            item = self._next_item(wait)
            if time.monotonic() >= next_expiry:  # sources silent on the wall clock (pipeline.feed)
                next_expiry = time.monotonic() + EXPIRY_POLL_S
                self._publish(self.engine.expire_silent(time.monotonic()))
            if item is None:
                out = self.engine.poll()
                if out:
                    self._publish(out)
                if self.state is not None:  # a write may wait for the correlation process's part
                    self.state.maybe_save(self.engine)
                self.snapshot = self.engine.snapshot()  # (cached by the engine when unchanged)
                last_snapshot = time.monotonic()
            if item is _STOP:
                break
            if not self.partition.whole:
                self._update_waited()
            if item is not None:
                self._handle(*item)
                if self.state is not None:
                    self.state.maybe_save(self.engine)
                # A fresh snapshot when the inputs run dry, at most every SNAPSHOT_MIN_S (the
                # other workers' messages keep coming in between), and every 64 messages.
                now = time.monotonic()
                if self.processed % 64 == 0 or (self.queue.empty() and now - last_snapshot >= SNAPSHOT_MIN_S):
                    self.snapshot = self.engine.snapshot()
                    last_snapshot = now
            if not self.partition.whole and time.monotonic() >= next_status:
                next_status = time.monotonic() + self.status_interval_s
                own = self._own_status()
                self._publish([Outgoing(self.keys.worker_status(self.partition.index), lambda own=own: own)])  # type: ignore[misc]
        self._publish(self.engine.flush())
        self.snapshot = self.engine.snapshot()

    def _update_waited(self) -> None:
        """The workers the merger waits for: those alive, and those whose token left less than
        ``peer_grace_s`` ago.  A token that leaves and comes back (a session that lost its
        router for a moment under load) must not make the others stop waiting: they would
        correlate without its tables and take them late, out of order."""
        now = time.monotonic()
        waited = set(self._alive) | {k for k, t in self._gone_at.items() if now - t < self.peer_grace_s}
        if waited != self._waited:
            self._waited = waited
            self._publish(self.engine.set_alive(waited))

    def _next_item(self, wait: float) -> Any:
        """The next message, the other workers' tables, rows and progress first: they only move
        the correlation along (in data-time order whatever the order they are taken in), while
        inputs queued before them would otherwise keep the merger waiting and the tables piling
        up.  None: nothing came for ``wait`` s."""
        took = self._items.acquire(timeout=wait)
        self._last_take = time.monotonic()
        if not took:
            return None
        try:
            return self.peer_queue.get_nowait()
        except IndexError:  # (one release per item put: the item is on the inputs' queue)
            return self.queue.get_nowait()

    def _handle(self, key: str, payload: bytes | int, received: float) -> None:
        self.processed += 1
        self.processed_plots += key.endswith("/plots")
        try:
            if isinstance(payload, int):  # the size of a payload too large to take
                out = self.engine.reject_too_large(key, payload, received)
            else:
                out = self.engine.ingest(key, payload, received)
        except Exception:  # engine.ingest never raises on input; this is a last resort
            log.exception("engine failed on %s", key)
            return
        self._publish(out)

    def _publish(self, out: list[Outgoing]) -> None:
        """Hand outputs to the publisher thread (waits only when its outbox is full)."""
        if out:
            self.outbox.put(out)

    def _send_outputs(self) -> None:
        while True:
            out = self.outbox.get()
            if out is _STOP:
                break
            self._put(out)

    def _put(self, out: list[Outgoing]) -> None:
        """Put each output whose key has a subscriber (an output nobody hears is never encoded).

        A new publisher learns of the subscribers that already exist a round trip after it is
        declared, so its first ``UNCONDITIONAL_PUTS`` outputs are put whatever its matching
        status says; errors are always put.
        """
        session = self._session
        if session is None:
            return
        for msg in out:
            errors = msg.key == self.keys.errors  # (logged by the engine, each source and reason)
            try:
                entry = self._publishers.pop(msg.key, None)  # (re-inserted: newest last)
                if entry is None:
                    self._bound_publishers()
                    # What partitioned workers send each other must not be dropped under load
                    # (a lost track-states message costs that radar until its next full table).
                    peer = self.keys.classify_peer(msg.key) is not None
                    pub = session.declare_publisher(
                        msg.key,
                        encoding=zenoh.Encoding.APPLICATION_JSON,
                        congestion_control=zenoh.CongestionControl.BLOCK
                        if peer
                        else zenoh.CongestionControl.DROP,
                    )
                    entry = [pub, UNCONDITIONAL_PUTS]
                self._publishers[msg.key] = entry
                pub, fresh = entry
                if errors or fresh > 0 or pub.matching_status.matching:
                    entry[1] = fresh - 1
                    pub.put(msg.payload)
            except Exception:
                log.exception("publish failed on %s", msg.key)

    def _bound_publishers(self) -> None:
        """Room for one more publisher: output keys come and go with radar ids (a retired
        radar's tracks and pairs), so the least recently used beyond ``MAX_PUBLISHERS`` goes."""
        while len(self._publishers) >= MAX_PUBLISHERS:
            oldest = next(iter(self._publishers))
            try:
                self._publishers.pop(oldest)[0].undeclare()
            except Exception:  # (a session closing under it: nothing left to free)
                log.debug("undeclaring the publisher of %s failed", oldest, exc_info=True)

    # -- views ---------------------------------------------------------------------------------
    def _own_status(self) -> dict[str, Any]:
        snap = self.snapshot
        own: dict[str, Any] = {
            "uptime_s": round(time.monotonic() - self.started_at, 3),
            "zenoh": {
                "mode": self.zenoh_options.effective_mode,
                "listen": self.zenoh_options.effective_listen(),
                "connect": self.zenoh_options.effective_connect(),
            },
            **snap.status_core(),
            "queue": self.queue_status(),
            "feed": self.engine.feed.status(time.monotonic(), self.engine.sequencer),
        }
        if self.state is not None:
            own["state"] = self.state.status()
        if not self.partition.whole:
            own["partition"] = partition_section(
                self.partition,
                self._alive | {self.partition.index},
                {self.partition.index: (0.0, [r["radar_id"] for r in own["radars"]], len(snap.pair_views))},
            )
            own["partition"]["progress"] = snap.progress
        return own

    def queue_status(self) -> dict[str, Any]:
        """``/status`` ``queue``: depth and bounds, and the drops by key (contract §4.6)."""
        dropped = self.queue.dropped_counts() | self.peer_queue.dropped_counts()  # (distinct keys)
        return {
            "depth": self.queue.qsize(),
            "capacity": self.queue.max_items,
            "high_water": self.queue.high_water,
            "dropped": sum(dropped.values()),
            "bytes": self.queue.nbytes(),
            "capacity_bytes": self.queue.max_bytes,
            "dropped_by_key": dropped,
        }

    def status(self) -> dict[str, Any]:
        """This worker's status; partitioned, the whole network's: every live worker's radars,
        pairs and rejections from its latest status, and which partitions are missing."""
        own = self._own_status()
        if self.partition.whole:
            return own
        now = time.monotonic()
        peers: dict[int, tuple[float, dict[str, Any]]] = {}
        for k, (seen, raw) in list(self._peer_status.items()):
            if k in self._alive:
                try:
                    peers[k] = (now - seen, orjson.loads(raw))
                except orjson.JSONDecodeError:
                    continue
        return merge_statuses(own, peers, self.partition, self._alive | {self.partition.index})

    def radars(self) -> list[dict[str, Any]]:
        """``GET /radars``; partitioned, every radar of the network with its owner's counters."""
        own = self.snapshot.radars()
        if self.partition.whole:
            return own
        seen = {r["radar_id"] for r in own}
        keys = ("batches", "plots", "rejected", "lost_batches", "last_time_s")
        counters = {r["radar_id"]: r for r in self.status()["radars"]}
        others = []
        for rid, site in sorted(self.snapshot.sites.items()):
            if rid not in seen:
                c = counters.get(rid, {})
                others.append(
                    {**site.model_dump(), **{k: c.get(k, 0 if k != "last_time_s" else None) for k in keys}}
                )
        return sorted(own + others, key=lambda r: str(r["radar_id"]))

    def pair_sets(
        self, radar_a: str | None = None, radar_b: str | None = None, status: str = "confirmed"
    ) -> list[dict[str, Any]]:
        """``GET /pairs``; partitioned, the other workers' pair sets too (a Zenoh ``get``)."""
        own = self.snapshot.pair_sets(radar_a, radar_b, status)
        if self.partition.whole or self._session is None:
            return own
        have = {(p["radar_a"], p["radar_b"]) for p in self.snapshot.pair_sets(radar_a, radar_b, "all")}
        wanted = {x for x in (radar_a, radar_b) if x is not None}
        out = list(own)
        replies = self._session.get(
            self.keys.pairs_all, consolidation=zenoh.ConsolidationMode.NONE, timeout=self.peer_query_timeout_s
        )
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                body = orjson.loads(reply.ok.payload.to_bytes())
                key = (body["radar_a"], body["radar_b"])
            except (orjson.JSONDecodeError, KeyError, TypeError):
                continue
            if key in have or not wanted <= set(key):
                continue
            have.add(key)
            if status != "all":
                body = {**body, "pairs": [p for p in body.get("pairs", []) if p.get("status") == status]}
            out.append(body)
        return sorted(out, key=lambda p: (p["radar_a"], p["radar_b"]))
