"""The state keeper: ``DIR/state.bin`` read at start, written on data time and at a stop.

The service's worker calls :meth:`StateKeeper.restore` before it takes any input,
:meth:`StateKeeper.maybe_save` after every message it handled and :meth:`StateKeeper.save`
at a graceful stop (contract §4.6 "State"; docs/operations/state.md for the operator).

* **When.**  A write is due once the engine's newest data clock has moved ``interval_s`` of
  data time past the state last written (the first clock after a write without data is the
  baseline): the same input gives the same writes at any replay speed, and a service without
  input writes nothing new.  Checking costs a comparison.
* **How.**  The engine's part of the state is taken on the worker's thread, between two
  messages; with the correlation in its own process, that process takes its part at the same
  point of its input and answers while the worker goes on (the write starts with the message
  after the answer; the final write at a stop waits for the process).  Encoding and the disk are a writer
  thread's: a temporary file in ``DIR``, flushed and ``fsync``-ed, then
  ``os.replace``-d over ``state.bin`` (atomic), and the directory ``fsync``-ed.  A crash at any
  moment leaves the previous whole file; a temporary file a crash left behind is deleted at the
  next start.  While a write is still under way a due write waits for the next message.
* **What is refused.**  A file that is corrupt or cut short, of another format version, or
  written for another prefix or partition (:mod:`.fileformat`), or whose content the engine
  cannot take, is renamed ``state.bin.refused`` (replacing an older one) and the service starts
  clean, with one log line saying why.
* **The epoch.**  Every start takes the epoch of the file it found plus one (0 without a
  file; a refused file's epoch still counts when its header can be read) and writes it at once,
  before any input: track ids of that start are ``{radar_id}-{E * 10**9 + n}``, so a start that
  is killed before its first periodic write still never gives an id twice.

Size: the registration memories dominate, bounded by their own parameters
(``RegistrationParams.max_rows`` rows per radar pair plus one update, about 130 bytes a row and
4 bytes per character of the two track ids, :meth:`RegistrationMemory.export`); sites, source
clocks and the bias solution are small.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import fields
from datetime import UTC, datetime
from pathlib import Path

from service.engine import Engine
from service.pipeline.restart import EngineState
from service.state.fileformat import Header, RefusedError, decode, encode

log = logging.getLogger(__name__)

STATE_FILE = "state.bin"
REFUSED_SUFFIX = ".refused"
#: Temporary files: ``state.bin.<random>.tmp`` in the same directory (``os.replace`` is atomic
#: within one file system only).
_TMP_PREFIX, _TMP_SUFFIX = STATE_FILE + ".", ".tmp"


class StateKeeper:
    """One state directory of one worker (``prefix``, ``partition`` ``"K/N"``)."""

    def __init__(self, directory: Path, prefix: str, partition: str, interval_s: float = 30.0) -> None:
        self.directory = Path(directory)
        self.path = self.directory / STATE_FILE
        self.prefix = prefix
        self.partition = str(partition)
        self.interval_s = float(interval_s)
        self._epoch = 0
        #: Data clock of the state last written (-inf: it held no data).
        self._saved_clock = -math.inf
        self._writer: threading.Thread | None = None
        #: A state asked of the engine and not answered yet (:meth:`Engine.request_state`).
        self._requested: Callable[[], EngineState | None] | None = None
        #: Seconds the last write took: asking for the state (the worker's; with the correlation
        #: process, its part comes with a later message) and encoding and writing it (the
        #: writer thread's).
        self.last_export_s = 0.0
        self.last_write_s = 0.0
        #: Bytes of the last file written.
        self.last_bytes = 0
        #: Writes started (at the start, periodic and final).
        self.writes = 0
        #: Of those, the ones on disk and the ones that failed (a full disk...).
        self.written = 0
        self.failures = 0
        #: Data clock of the state last on disk (None: none yet, or it held no data).
        self.written_clock_s: float | None = None

    def status(self) -> dict[str, object]:
        """``/status`` ``state``: where, which epoch, how the writes go (contract §4.6)."""
        return {
            "directory": str(self.directory),
            "epoch": self._epoch,
            "writes": self.written,
            "failures": self.failures,
            "data_time_s": self.written_clock_s,
            "bytes": self.last_bytes,
            "write_s": round(self.last_write_s, 3),
        }

    @property
    def epoch(self) -> int:
        """This start's track-id epoch (0 on the first start with the directory)."""
        return self._epoch

    # -- start -------------------------------------------------------------------------------
    def restore(self, engine: Engine) -> None:
        """Restore ``engine`` from the directory's file, before any input (module docstring),
        log one line saying what, and write the state with this start's epoch at once.

        ``OSError`` if the directory cannot be made, read or written: the service should not
        run then (its track ids could repeat those of an earlier start)."""
        self.directory.mkdir(parents=True, exist_ok=True)
        for stray in self.directory.glob(f"{_TMP_PREFIX}*{_TMP_SUFFIX}"):
            stray.unlink(missing_ok=True)  # a write a crash cut short; state.bin is whole
        try:
            data: bytes | None = self.path.read_bytes()
        except FileNotFoundError:
            data = None
        message, level = f"state {self.path}: none yet, starting clean", logging.INFO
        epoch, restored = 0, False
        if data is not None:
            written_by: int | None = None
            try:
                header, tree = decode(data, self.prefix, self.partition)
                written_by = header.epoch
                state = _state(tree)
                engine.restore_state(state, written_by + 1)
                epoch, restored = written_by + 1, True
                message = (
                    f"state {self.path}: restored {state.summary()}, newest data "
                    f"{_when(state.data_clock_s)} (written by epoch {written_by})"
                )
            except RefusedError as refused:
                epoch, message = self._refuse(str(refused), refused.epoch)
                level = logging.WARNING
            except Exception as exc:  # a state the engine cannot take: it is left as it was
                why = f"unreadable content ({type(exc).__name__}: {exc})"
                epoch, message = self._refuse(why, written_by)
                level = logging.WARNING
        if not restored:  # the epoch applies all the same
            engine.restore_state(None, epoch)
        self._epoch = epoch
        self.writes += 1
        self._write(engine.export_state())
        self._saved_clock = engine.data_clock_s
        log.log(level, "%s; track-id epoch %d", message, epoch)

    def _refuse(self, why: str, epoch: int | None) -> tuple[int, str]:
        """Rename the file aside; the epoch to start with and the line to log."""
        refused = self.path.with_name(STATE_FILE + REFUSED_SUFFIX)
        os.replace(self.path, refused)
        why = " ".join(why.split())  # one line, whatever an exception's text holds
        return (
            0 if epoch is None else epoch + 1,
            f"state {self.path} refused ({why}): renamed to {refused.name}, starting clean",
        )

    # -- while running -------------------------------------------------------------------------
    def maybe_save(self, engine: Engine) -> None:
        """After every handled message: write the state when ``interval_s`` of data time has
        passed since the last write (a comparison or two when not due)."""
        if self._requested is not None:
            self._collect()
            return
        clock = engine.data_clock_s
        if self._saved_clock == -math.inf:
            self._saved_clock = clock  # the first data after a write without any: the baseline
            return
        if clock < self._saved_clock + self.interval_s:
            return
        if self._writer is not None and self._writer.is_alive():
            return  # the last write is still under way: the next message tries again
        self._saved_clock = clock  # a failed write too is tried again one interval later
        t0 = time.perf_counter()
        try:
            self._requested = engine.request_state()
        except Exception as exc:  # e.g. the correlation process died: the next write may work
            log.error("state %s not written: %s: %s", self.path, type(exc).__name__, exc)
        self.last_export_s = time.perf_counter() - t0
        self._collect()

    def _collect(self) -> None:
        """The requested state, once the engine has it, to the writer thread."""
        assert self._requested is not None
        try:
            state = self._requested()
        except Exception as exc:
            self._requested = None
            log.error("state %s not written: %s: %s", self.path, type(exc).__name__, exc)
            return
        if state is None:
            return  # the correlation process has not answered yet
        self._requested = None
        self.writes += 1
        self._writer = threading.Thread(
            target=self._write_logged, args=(state,), name="state-writer", daemon=True
        )
        self._writer.start()

    def save(self, engine: Engine) -> None:
        """The final write at a graceful stop (after the worker's last message; it waits for
        the correlation process); a failure is logged, not raised (the stop goes on)."""
        self.wait()
        self._requested = None  # this state is newer
        self._saved_clock = engine.data_clock_s
        t0 = time.perf_counter()
        try:
            state = engine.export_state()
        except Exception as exc:
            log.error("state %s not written: %s: %s", self.path, type(exc).__name__, exc)
            return
        self.last_export_s = time.perf_counter() - t0
        self.writes += 1
        self._write_logged(state)

    def wait(self) -> None:
        """Until the write under way, if any, is on disk."""
        if self._writer is not None:
            self._writer.join()

    # -- the file ------------------------------------------------------------------------------
    def _write_logged(self, state: EngineState) -> None:
        try:
            self._write(state)
        except Exception as exc:  # a full disk must not stop the worker; the next write may work
            self.failures += 1
            log.error("state %s not written: %s: %s", self.path, type(exc).__name__, exc)

    def _write(self, state: EngineState) -> None:
        """``state`` into ``state.bin``, atomically (module docstring)."""
        t0 = time.perf_counter()
        header = Header(self.prefix, self.partition, self._epoch, state.data_clock_s, time.time())
        data = encode(header, {f.name: getattr(state, f.name) for f in fields(EngineState)})
        fd, tmp = tempfile.mkstemp(dir=self.directory, prefix=_TMP_PREFIX, suffix=_TMP_SUFFIX)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
        # the rename itself survives a power cut only once the directory is on disk
        dir_fd = os.open(self.directory, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
        self.last_bytes = len(data)
        self.last_write_s = time.perf_counter() - t0
        self.written += 1
        self.written_clock_s = state.data_clock_s


def _state(tree: dict[str, object]) -> EngineState:
    """The engine state of a file's tree (``TypeError`` if its fields are not those)."""
    return EngineState(**tree)  # type: ignore[arg-type]


def _when(clock: float | None) -> str:
    if clock is None:
        return "none"
    return datetime.fromtimestamp(clock, UTC).isoformat(timespec="seconds")
