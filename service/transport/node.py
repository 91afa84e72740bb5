"""The running service: one Zenoh session, one worker thread around the engine, queryables.

:class:`ServiceNode` composes the parts (docs/architecture.md), each in its module:

* :mod:`~service.transport.session`: the session (a client whose router is not up yet keeps
  trying with back-off on a connector thread while the HTTP port answers) and its watcher;
* :mod:`~service.transport.intake`: Zenoh's network thread runs the input callbacks, which
  only put ``(key, bytes, time)`` on queues bounded in samples and in bytes, fair by source;
* :mod:`~service.transport.worker` and :mod:`~service.transport.publisher`: one thread around
  the engine, one putting its outputs (the worker never waits on the network);
* :mod:`~service.transport.readiness` (``/readyz``), :mod:`~service.transport.queryables`,
  and, partitioned (``--partition K/N``), :mod:`~service.transport.network_status`: the
  other workers, whose latest statuses make ``/status`` describe the whole network.

A stop (SIGTERM/SIGINT) undeclares the input subscribers first, gives the worker
``stop_grace_s`` to finish the queue, publishes the final outputs, and logs how many queued
samples were processed and how many, if any, were left (contract §4.6).

The engine is built, and restored from the state directory, outside the node
(:mod:`service.startup`); :meth:`ServiceNode.from_settings` builds both from the settings.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from service.config import EngineConfig
from service.engine import Engine, Snapshot
from service.settings import Settings
from service.startup import build_engine, start_engine
from service.state import StateKeeper
from service.state.lock import release_directory
from service.transport.intake import Intake
from service.transport.network_status import (
    PeerWorkers,
    network_pair_sets,
    network_performance,
    network_radars,
    network_system_tracks,
)
from service.transport.options import NodeOptions
from service.transport.publisher import MAX_PUBLISHERS, UNCONDITIONAL_PUTS, Publisher
from service.transport.queryables import declare_queryables
from service.transport.readiness import Readiness
from service.transport.session import Connection, ZenohOptions
from service.transport.worker import FINISH_S, Worker

__all__ = ["FINISH_S", "MAX_PUBLISHERS", "UNCONDITIONAL_PUTS", "NodeOptions", "ServiceNode"]

log = logging.getLogger(__name__)


class ServiceNode:
    """Owns the Zenoh session and the worker; start/stop are idempotent."""

    def __init__(
        self,
        engine: Engine | EngineConfig,
        zenoh_options: ZenohOptions,
        options: NodeOptions | None = None,
        *,
        session: zenoh.Session | None = None,
        state: StateKeeper | None = None,
        correlation_process: bool = True,
        **option_kw: Any,
    ) -> None:
        """``engine``: built (and restored from ``state`` already: :mod:`service.startup`), or
        its configuration, then built and restored here by the same factory (with
        ``correlation_process``).  ``options``, or the same as keywords (``option_kw``).
        ``session``: an open session to use (not closed by the node)."""
        if isinstance(engine, EngineConfig):
            engine = build_engine(engine, correlation_process, state)
        if options is None:
            options = NodeOptions(**option_kw)
        elif option_kw:
            raise TypeError(f"options given twice: {sorted(option_kw)}")
        self.engine = engine
        self.options = options
        self.zenoh_options = zenoh_options
        self.keys = engine.keys
        self.partition = engine.config.partition
        #: ``--state-dir``: written on data time and at a stop.
        self.state = state
        self.started_at = time.monotonic()
        #: Set when the stop begins (input taken no more); ``_stopped``: :meth:`stop` ran.
        self._stopping = threading.Event()
        self._stopped = False
        #: Start and stop, and the connector's handing over of its session, one at a time.
        self._life = threading.Lock()
        #: Told of a session Zenoh refused (the command ends then, with status 2).
        self.on_fatal: Callable[[str], None] | None = None
        self.connection = Connection(zenoh_options, session, self._stopping, self._life, self._failed)
        o = options
        self.intake = Intake(
            self.keys, self.partition, o.radars, o.queue_size, o.queue_bytes, o.queue_wait_s, self._stopping
        )
        self.peers = None if self.partition.whole else PeerWorkers(self.keys, self.partition, o.peer_grace_s)
        self.publisher = Publisher(self.keys, o.outbox_size, MAX_PUBLISHERS)
        self.worker = Worker(
            engine, self.intake, self.publisher, self.peers, state, self._own_status, o.status_interval_s
        )
        self.readiness = Readiness(
            self._stopping, self.connection, self.worker, self.intake, engine, o.stall_s
        )
        self.queue, self.peer_queue = self.intake.queue, self.intake.peer_queue
        self._inputs: list[Any] = []
        self._declared: list[Any] = []

    @classmethod
    def from_settings(cls, settings: Settings, session: zenoh.Session | None = None) -> ServiceNode:
        """The service's node of the settings: the engine built and restored
        (:func:`service.startup.start_engine`: ``ConfigError`` naming a bad parameter,
        ``RuntimeError`` naming a state directory that cannot be used), the Zenoh options and
        the node's options of the settings."""
        engine, state = start_engine(settings)
        return cls(
            engine,
            ZenohOptions.from_settings(settings),
            NodeOptions.from_settings(settings),
            session=session,
            state=state,
        )

    # -- the parts' state, as the readers and the tests know it ----------------------------------
    @property
    def snapshot(self) -> Snapshot:
        return self.worker.snapshot

    @property
    def processed(self) -> int:
        return self.worker.processed

    @property
    def failure(self) -> str:
        """Why the session could not be opened (a configuration Zenoh refused), or ""."""
        return self.connection.failure

    @property
    def _session(self) -> zenoh.Session | None:
        return self.connection.session

    @property
    def session(self) -> zenoh.Session:
        if self.connection.session is None:
            raise RuntimeError("node not started")
        return self.connection.session

    @property
    def _publishers(self) -> dict[str, list[Any]]:
        return self.publisher.publishers

    def _input_keys(self) -> list[str]:
        return self.intake.input_keys()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.intake.on_sample(sample)

    def _failed(self, reason: str) -> None:
        if self.on_fatal is not None:
            self.on_fatal(reason)

    # -- lifecycle ---------------------------------------------------------------------------------
    def open(self) -> bool:
        """Open the Zenoh session (if not given one): True when open, False when the router
        cannot be reached yet (:meth:`start` then keeps trying); raises ``RuntimeError``
        saying why for any other failure (a configuration error)."""
        return self.connection.open()

    def start(self) -> None:
        """Start the worker on an open session, or, while the router cannot be reached, a
        connector that opens it with back-off and starts the worker then."""
        with self._life:
            if self.worker.thread is not None or self.connection.connecting or self._stopping.is_set():
                return
            if not self.open():
                self.connection.connect_later(self._start_on_session)
                return
            self._start_on_session()

    def _start_on_session(self) -> None:
        s = self.session
        # Direct (not "indirect") callbacks: zenoh-python otherwise runs each subscriber's
        # callback on its own thread, and a site could then reach the queue after the plots
        # that followed it on the wire.  Run on Zenoh's network thread, the callbacks keep the
        # wire order across keys, and a full queue pushes back on the link itself.
        # What this worker puts for the others (its tables, links, rows, progress) it would hear
        # back on the same keys, only to drop it: those keys take other sessions' samples only.
        peers = set(self.keys.peer_inputs)
        self._inputs = [
            s.declare_subscriber(
                key,
                zenoh.handlers.Callback(self._on_sample, indirect=False),
                allowed_origin=zenoh.Locality.REMOTE if key in peers else None,
            )
            for key in self._input_keys()
        ]
        if self._stopping.is_set():  # a signal while they were declared: stop_input missed them
            self._undeclare(self._inputs)
        self._declared = declare_queryables(s, self.keys, self, self.partition)
        if self.peers is not None:
            self._declared += self.peers.declare(s)
        self.publisher.start(s)
        self.worker.start()
        self.connection.watch()
        log.info("zenoh session open (%s), prefix %r", self.connection.describe(), self.keys.prefix)

    def stop_input(self, grace_s: float | None = None) -> None:
        """Take no more input: undeclare the input subscribers, close the queue (a sample a
        callback still brings is counted as dropped), and give the worker ``grace_s`` (default
        ``stop_grace_s``) from now to finish the queue.  The first step of a stop: the HTTP
        server calls it as soon as the signal comes.  Idempotent."""
        if self._stopping.is_set():
            return
        self.worker.begin_stop(self.options.stop_grace_s if grace_s is None else grace_s)
        self._stopping.set()
        self._undeclare(self._inputs)
        self.worker.close_queue()

    @staticmethod
    def _undeclare(declared: list[Any]) -> None:
        taken = list(declared)
        declared.clear()
        for d in taken:
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
        started = self.worker.thread is not None
        done = self.worker.finish()
        if started and done and self.state is not None:
            self.state.save(self.engine)  # (a busy worker's engine is not read under it)
        self._undeclare(self._declared)
        self.publisher.stop(FINISH_S)  # the final outputs, put before the session closes
        if done:
            self.engine.close()  # (not under a busy worker: the correlation child is a daemon)
        self.publisher.session = None
        self.connection.close()
        if done and self.state is not None:  # (a busy worker may write it yet: kept till exit)
            self.state.wait()
            release_directory(self.state.directory)

    # -- views -------------------------------------------------------------------------------------
    @property
    def not_ready_reason(self) -> str:
        """Why ``/readyz`` is 503 (contract §4.6), or "" when ready."""
        return self.readiness.not_ready_reason

    @property
    def ready(self) -> bool:
        return not self.not_ready_reason

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
            "feed": self.engine.feed.status(time.monotonic(), self.engine.sequencer, snap.outputs_time_s),
        }
        if self.state is not None:
            own["state"] = self.state.status()
        if self.peers is not None:
            own_radars = [r["radar_id"] for r in own["radars"]]
            own["partition"] = self.peers.own_section(own_radars, len(snap.pair_views), snap.progress)
        return own

    def queue_status(self) -> dict[str, Any]:
        """``/status`` ``queue``: depth and bounds, and the drops by key (contract §4.6)."""
        return self.intake.status()

    def status(self) -> dict[str, Any]:
        """This worker's status; partitioned, the whole network's: every live worker's radars,
        pairs and rejections from its latest status, and which partitions are missing."""
        own = self._own_status()
        return own if self.peers is None else self.peers.network_status(own)

    def radars(self) -> list[dict[str, Any]]:
        """``GET /radars``; partitioned, every radar of the network with its owner's counters."""
        own = self.snapshot.radars()
        if self.peers is None:
            return own
        counters = {r["radar_id"]: r for r in self.status()["radars"]}
        return network_radars(own, self.snapshot.sites, counters)

    def system_tracks(self, status: str = "confirmed") -> dict[str, Any] | None:
        """``GET /system-tracks``; partitioned, worker 1's (it draws them; a Zenoh ``get``),
        None while worker 1 does not answer."""
        snap, session = self.snapshot, self.connection.session
        if self.peers is None or self.partition.solves_biases:
            return snap.system_tracks(status)
        if session is None:
            return None
        return network_system_tracks(session, self.keys, status, self.options.peer_query_timeout_s)

    def radar_performance(self, radar_id: str) -> dict[str, Any] | None:
        """``GET /radars/{id}/performance`` (None: no such radar); partitioned, the radar's
        owner's, the one worker that measures it (a Zenoh ``get``; this worker's own, every
        figure null, while the owner does not answer)."""
        snap, session = self.snapshot, self.connection.session
        own = snap.radar_performance(radar_id)
        if own is None or self.peers is None or self.partition.owns(radar_id) or session is None:
            return own
        if self.partition.owner(radar_id) not in self.peers.alive:
            return own  # (its owner is gone: no query to wait out)
        timeout_s = self.options.peer_query_timeout_s
        return network_performance(session, self.keys, radar_id, timeout_s) or own

    def pair_sets(
        self, radar_a: str | None = None, radar_b: str | None = None, status: str = "confirmed"
    ) -> list[dict[str, Any]]:
        """``GET /pairs``; partitioned, the other workers' pair sets too (a Zenoh ``get``)."""
        snap, session = self.snapshot, self.connection.session
        own = snap.pair_sets(radar_a, radar_b, status)
        if self.peers is None or session is None:
            return own
        timeout_s = self.options.peer_query_timeout_s
        return network_pair_sets(session, self.keys, snap, own, (radar_a, radar_b), status, timeout_s)
