"""The correlation stage in a child process: tracking and correlation on two cores at once.

The engine feeds its correlation stage in release order (a radar's tracks after each batch,
reference reports, site moves, departures).  :class:`ChildProcessRunner` takes the same calls
and sends each as a message down a pipe to a child process that owns a
:class:`~service.pipeline.correlation_stage.CorrelationStage`; the child answers every message
with what it changed (the views of the pairs it updated, the biases when it re-solved them, its
timings).  The child sees the same inputs in the same order as an in-process stage, so the pairs
and biases are the same, bit for bit; they only arrive later: the pair sets a batch updates are
handed out by a later call, and :meth:`ChildProcessRunner.finish` waits for all of them.

At most ``max_in_flight`` messages are sent and not yet answered: when correlation falls
behind, tracking waits for it (memory stays bounded, nothing is dropped).  If the child dies, it is started
afresh and the failure is reported; pairs then re-confirm and registration re-learns from the
next updates.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import multiprocessing as mp
import queue
import signal
import threading
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import replace
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from service.correlation import CorrelationParams, PairCorrelator
from service.correlation.registration import RegistrationRowsData
from service.geo import Site
from service.pipeline.correlation_runner import Answer, Answers, Key, answer
from service.pipeline.correlation_stage import CadenceParams, CorrelationStage, change_radars, timings_dict
from service.pipeline.partition import Partition
from service.pipeline.shared_links import SharedLinks
from service.pipeline.system_stage import Drawing
from service.reference import ReferenceParams
from service.tracking.base import TrackTable

log = logging.getLogger(__name__)

#: While waiting for the child (a free slot, an answer), check this often (s) that it and the
#: threads talking to it are still there: a dead one is restarted instead of waited for.
LIVENESS_CHECK_S = 1.0


def _serve(requests: Connection, answers: Connection, *stage_args: Any) -> None:
    """The child: apply each message to one stage, answer each with what changed.

    It ignores SIGINT: a Ctrl-C in a terminal goes to the whole process group, and the child's
    end is the parent's to decide (it sends ``None``, or the pipe closes when the parent dies),
    after the last answers of a stop."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    stage = CorrelationStage(*stage_args)
    gc.collect()
    gc.freeze()  # (the modules and the stage's set-up: out of the collector's full scans)
    while True:
        try:
            msg = requests.recv()
        except EOFError:  # the parent died without a word (SIGKILL): the child ends quietly
            return
        if msg is None:
            break
        op, args = msg
        got = answer(stage, op, args)
        timings = stage.timings()  # (taken again only after a pair's full update)
        # A picture taken by this call is of the tables the parent sent: it has them (and fills
        # them in, :meth:`ChildProcessRunner._answered_radars`), they are not sent back.
        drawings = [replace(d, radars=None) if d.taken_now else d for d in got.drawings]
        try:
            answers.send(replace(got, timings=timings, drawings=drawings))
        except (BrokenPipeError, ConnectionResetError):  # (the same, while it answered)
            return
    answers.close()


class ChildProcessRunner(Answers):
    """A :class:`CorrelationStage` in a child process, behind the same calls."""

    def __init__(
        self,
        method: str,
        cadence: CadenceParams | None = None,
        reference: ReferenceParams | None = None,
        correlation: CorrelationParams | None = None,
        partition: Partition | None = None,
        aid: bool = False,
        max_in_flight: int = 64,
    ) -> None:
        super().__init__((correlation or CorrelationParams()).prediction)
        self._args = (method, cadence, reference, correlation, partition, aid)
        self.max_in_flight = max_in_flight
        #: The child's latest ``timings()`` (its update time histogram with them).
        self._timings: dict[str, Any] = timings_dict()
        #: The messages sent and not answered yet, oldest first: a radar message's data time
        #: (None: another message) and the message's change of the radars' tables (None: none).
        self._unanswered: deque[tuple[float | None, tuple[str, Any] | None]] = deque()
        #: The radars' sites and tables as the child holds them after the last answer taken
        #: (its stage's ``_radars``): a picture the child draws at once is of these, so its
        #: tables need not come back down the pipe.
        self._radars: dict[str, tuple[Site, TrackTable]] = {}
        self.restarts = 0
        #: The last answer applied (:meth:`_call` reads its result).
        self._last: Answer | None = None
        #: The latest ``export_state`` the child answered (:meth:`request_state`).
        self._exported: dict[str, Any] | None = None
        self._start()

    def _start(self) -> None:
        # spawn, not fork: the parent runs Zenoh's and uvicorn's threads, which a fork would copy
        # in whatever state they are in.
        ctx = mp.get_context("spawn")
        req_r, self._requests = ctx.Pipe(duplex=False)
        answers, ans_w = ctx.Pipe(duplex=False)
        self._process = ctx.Process(
            target=_serve, args=(req_r, ans_w, *self._args), name="topofusion-correlation", daemon=True
        )
        self._process.start()
        req_r.close()
        ans_w.close()
        # Two threads move the messages: a writer sends them (a pipe takes a message only as
        # fast as the child reads it, and the engine must not wait for that), a reader takes
        # every answer off the pipe as soon as it is written (so the child never waits to
        # answer and the two cannot deadlock).  ``_slots`` bounds the messages not yet answered.
        self._outbox: queue.Queue[Any] = queue.Queue()
        self._inbox: queue.Queue[Answer | None] = queue.Queue()
        self._slots = threading.BoundedSemaphore(self.max_in_flight)
        self._writer = threading.Thread(
            target=self._write,
            args=(self._requests, self._outbox, self._inbox),
            name="correlation-requests",
            daemon=True,
        )
        self._reader = threading.Thread(
            target=self._read,
            args=(answers, self._inbox, self._slots),
            name="correlation-answers",
            daemon=True,
        )
        self._writer.start()
        self._reader.start()
        self._pending = 0

    @staticmethod
    def _write(requests: Connection, outbox: queue.Queue[Any], inbox: queue.Queue[Answer | None]) -> None:
        try:
            while True:
                msg = outbox.get()
                requests.send(msg)
                if msg is None:
                    break
        except (BrokenPipeError, OSError):
            inbox.put(None)  # the child is gone
        finally:
            requests.close()

    @staticmethod
    def _read(
        answers: Connection, inbox: queue.Queue[Answer | None], slots: threading.BoundedSemaphore
    ) -> None:
        try:
            while True:
                inbox.put(answers.recv())
                slots.release()
        except Exception:  # EOF: the child is gone; anything else: the pipe cannot be trusted
            inbox.put(None)
        finally:
            answers.close()

    # -- the pipe ----------------------------------------------------------------------------
    def _send(self, op: str, *args: Any) -> None:
        while not self._slots.acquire(timeout=LIVENESS_CHECK_S):
            if not (self._process.is_alive() and self._reader.is_alive() and self._writer.is_alive()):
                self._lost("stopped answering")
        self._outbox.put((op, args))
        self._unanswered.append(
            (
                float(args[3]) if op == "radar" else None,
                (op, args[:3]) if op in ("radar", "forget", "moved") else None,
            )
        )
        self._pending += 1
        self._apply(block=False)

    def _apply(self, block: bool, through_s: float = math.inf) -> None:
        """Apply the answers received (``block``: wait until every message is answered, or,
        with ``through_s``, every radar table up to that data time)."""
        while self._pending and (through_s == math.inf or self._oldest_unanswered() <= through_s):
            try:
                got = self._inbox.get(block=block, timeout=LIVENESS_CHECK_S if block else None)
            except queue.Empty:
                if not block:
                    return
                if not (self._process.is_alive() and self._reader.is_alive()):
                    self._lost("stopped answering")
                    return
                continue
            if got is None:
                self._lost("no answer")
                return
            self._pending -= 1
            self._last = got
            if got.result is not None:
                self._exported = got.result
            if self._unanswered:
                self._apply_change(self._unanswered.popleft()[1])
            if got.drawings:
                got = replace(got, drawings=[self._answered_radars(d) for d in got.drawings])
            if got.timings is not None:
                self._timings = got.timings
            self._take_answer(got)

    def _call(self, op: str, *args: Any) -> Any:
        """Send one message and wait for its answer (and every earlier one's): what the stage's
        call returned.  ``RuntimeError`` if the call failed or the child died meanwhile (the
        failure is raised here, not reported as a failed message)."""
        restarts = self.restarts
        self._send(op, *args)
        self._apply(block=True)
        got = self._last
        if self.restarts != restarts or got is None:
            raise RuntimeError(f"correlation process died during {op}")
        if got.error is not None:
            if got.error in self._errors:
                self._errors.remove(got.error)
            raise RuntimeError(got.error[1])
        return got.result

    def _lost(self, what: str) -> None:
        code = self._process.exitcode
        log.error("correlation process died (%s, exit code %s); starting it afresh", what, code)
        detail = f"correlation process died ({what}); its pairs and registration start afresh"
        self._errors.append(("", detail))
        self.restarts += 1
        # the calls it did not answer are answered empty: a radar's tracks are still published
        for t, _ in self._unanswered:
            self._answers.append(Answer("radar" if t is not None else "lost", [], None, None))
        self._unanswered.clear()
        self._radars = {}  # (a child started afresh holds no table)
        self._process.kill()
        self._outbox.put(None)
        self._start()  # (the system tracks are drawn here: their numbers go on)

    def _apply_change(self, change: tuple[str, Any] | None) -> None:
        """An answered message's change of the radars' tables, as the child's stage made it."""
        if change is None:
            return
        # (a call the child's stage failed failed there the same way, before any change)
        with contextlib.suppress(Exception):
            change_radars(self._radars, *change)

    def _answered_radars(self, drawing: Drawing) -> Drawing:
        """``drawing`` with the radars' tables filled in where the child left them out."""
        return drawing if drawing.radars is not None else replace(drawing, radars=dict(self._radars))

    def _oldest_unanswered(self) -> float:
        """The data time of the oldest radar table not answered yet (inf: none)."""
        return next((t for t, _ in self._unanswered if t is not None), math.inf)

    def wait_through(self, time_s: float) -> None:
        """Wait until every radar table up to data time ``time_s`` sent is answered (the aid of
        association, :mod:`.partner_aid`); the later ones go on in the child meanwhile."""
        self._apply(block=True, through_s=time_s)

    def correlated_through(self, released_s: float) -> float:
        """Data time up to which every update has been answered, given that everything up to
        ``released_s`` was sent."""
        pending = [t for t, _ in self._unanswered if t is not None]
        return float(np.nextafter(pending[0], -np.inf)) if pending else released_s

    @property
    def pending(self) -> int:
        """Messages sent and not answered yet."""
        return self._pending

    def poll(self) -> None:
        """Take the answers that arrived (without waiting): an idle engine hands them out."""
        self._apply(block=False)

    # -- the stage's calls ---------------------------------------------------------------------
    def radar(self, radar_id: str, geometry: Site, table: TrackTable, time_s: float) -> None:
        # Truth labels (evaluation only) are no input of correlation: not sent.
        unlabelled = replace(table, truth_id=np.full(len(table), None, dtype=object))
        self._send("radar", radar_id, geometry, unlabelled, time_s)  # answered later: take_ready

    def reference(self, source_id: str, time_s: float, *columns: Any) -> None:
        self._send("reference", source_id, time_s, *columns)

    def silent(self, source_id: str) -> None:
        self._send("silent", source_id)

    def forget(self, source_id: str) -> None:
        self._send("forget", source_id)

    def moved(self, site: Site) -> None:
        self._send("moved", site)

    def mirror_rows(self, key: Key, site_a: Site, site_b: Site | None, rows: RegistrationRowsData) -> None:
        self._send("mirror_rows", key, site_a, site_b, rows)

    def mirror_links(self, shared: SharedLinks) -> None:
        self._send("mirror_links", shared)

    def others_through(self, time_s: float) -> None:
        self._send("others_through", time_s)

    def export_state(self) -> dict[str, Any]:
        """:meth:`CorrelationStage.export_state` of the child, once it has answered everything
        sent before (the engine's state is then of the same moment)."""
        state: dict[str, Any] = self._call("export_state")
        self._exported = None  # (the answer's copy: not held twice)
        return state

    def request_state(self) -> Callable[[], dict[str, Any] | None]:
        """:meth:`export_state` without waiting: the child answers it after what was sent
        before, while the engine goes on.  Returns a function that gives the state once it is
        answered (None until then; the answers are taken with the next messages or
        :meth:`poll`), and raises ``RuntimeError`` if the child died meanwhile."""
        restarts = self.restarts
        self._exported = None
        self._send("export_state")

        def ready() -> dict[str, Any] | None:
            state, self._exported = self._exported, None
            if state is None and self.restarts != restarts:
                raise RuntimeError("correlation process died before it answered")
            return state

        return ready

    def restore_state(self, state: Mapping[str, Any] | None, epoch: int, sites: Mapping[str, Site]) -> None:
        """:meth:`CorrelationStage.restore_state` in the child (its biases come back with the
        answer).  A child started afresh later (it died) starts without it."""
        self.drawer.restart(epoch)
        self._call("restore_state", state, dict(sites))

    def finish(self) -> None:
        """Solve the final biases and wait until every message is answered."""
        self._send("finish")
        self._apply(block=True)

    def timings(self) -> dict[str, Any]:
        return dict(self._timings)

    def pair_correlators(self) -> list[PairCorrelator]:
        """None in this process: the child holds them."""
        return []

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the child (after it answered what it holds)."""
        self._outbox.put(None)
        self._writer.join(timeout_s)
        self._process.join(timeout_s)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(timeout_s)
        self._reader.join(timeout_s)
