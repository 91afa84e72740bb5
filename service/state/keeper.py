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
* **What is refused.**  Whatever is at ``state.bin`` but a regular file within the format's
  size bounds, a file that is corrupt or cut short, of another format version, or written for
  another prefix or partition (:mod:`.fileformat`), a whole file with a value that cannot be
  believed (:mod:`.content`: not finite, a clock ahead of the file's own data time, an
  implausible ``seq``), or whose content the engine cannot take: the service starts clean,
  with one log line saying why, and the file is renamed ``state.bin.refused`` (replacing an
  older one) once the clean state is written.  Nothing of a refused file is taken or written
  back.
* **The epoch.**  Every start takes the epoch of the file it found plus one (0 without a
  file; a refused file's epoch still counts when its header can be read) and writes it at once,
  before any input: track ids of that start are ``{radar_id}-{E * 10**9 + n}``, so a start that
  is killed before its first periodic write still never gives an id twice.  Epochs are bounded
  (:data:`~.fileformat.MAX_EPOCH`): a start that would need one more is refused
  (:class:`EpochsExhaustedError`, the directory cannot be used) rather than number from 0 again,
  and the last :data:`EPOCHS_LEFT_WARNING` starts say how many are left.
* **A directory that cannot be written** at the start (a full disk, a read-only mount, its
  permissions) does not stop the start: what was read is restored, the start's epoch is written
  into the old file's header in place if it can be (:func:`~.fileformat.rewrite_epoch` needs
  no new block), the line says so, and the periodic writes are tried as usual.  Only when even
  that fails (or there was no file) can a later start give this start's ids again, and the line
  says that too.

Size: the registration memories dominate, bounded by their own parameters
(``RegistrationParams.max_rows`` rows per radar pair plus one update, about 130 bytes a row and
4 bytes per character of the two track ids, :meth:`RegistrationMemory.export`); sites, source
clocks and the bias solution are small.
"""

from __future__ import annotations

import contextlib
import errno
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
from typing import Any

from service.engine import Engine
from service.pipeline.restart import EngineState
from service.state.content import check
from service.state.fileformat import (
    MAX_EPOCH,
    MAX_FILE_BYTES,
    Header,
    RefusedError,
    decode,
    encode,
    read_file,
    rewrite_epoch,
)

log = logging.getLogger(__name__)

STATE_FILE = "state.bin"
REFUSED_SUFFIX = ".refused"
#: Temporary files: ``state.bin.<random>.tmp`` in the same directory (``os.replace`` is atomic
#: within one file system only).
_TMP_PREFIX, _TMP_SUFFIX = STATE_FILE + ".", ".tmp"
#: Starts left before the last epoch (:data:`~.fileformat.MAX_EPOCH`) from which every start
#: says so in its line (a warning): time for an operator to plan a fresh start.
EPOCHS_LEFT_WARNING = 1_000


class EpochsExhaustedError(OSError):
    """The directory's last track-id epoch was taken: a start with it is refused (a new epoch
    could only repeat ids).  An ``OSError``: the directory cannot be used."""


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
        #: Writes failed in a row (the start's too); the next that succeeds says so.
        self._failing = 0
        #: A refused file waits in place until a new one is written (its epoch still counts),
        #: then goes aside; ``_refused_note``: what became of it if not renamed.
        self._aside = False
        self._refused_note = ""

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
    def prepare(self) -> None:
        """Make the directory (``OSError`` if it cannot be made): a start checks it before it
        builds its engine, so a bad ``--state-dir`` fails at once, not after the engine's start."""
        self.directory.mkdir(parents=True, exist_ok=True)

    def check(self) -> None:
        """What a start with this directory would refuse, found without making or writing
        anything (``topofusion config``): ``OSError`` for a path that is or runs through
        something else than a directory, or a file that cannot be read, and
        :class:`EpochsExhaustedError` for a file at the last epoch."""
        existing = next(p for p in (self.directory, *self.directory.parents) if p.exists() or p.is_symlink())
        if not existing.exists():
            raise NotADirectoryError(errno.ENOTDIR, f"{existing} is a link to nothing (or a loop of links)")
        if not existing.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, f"{existing} is not a directory")
        if existing != self.directory:
            return  # (made at the start)
        try:
            loaded = self._load()
            written_by = loaded[0].epoch if loaded is not None else None
        except RefusedError as exc:  # (a refused file is put aside; its epoch still counts)
            written_by = exc.epoch
        self._next_epoch(written_by)

    def restore(self, engine: Engine) -> None:
        """Restore ``engine`` from the directory's file, before any input (module docstring),
        log one line saying what, and write the state with this start's epoch at once.

        ``OSError`` if the directory cannot be made or its file read (the service should not
        run then: its track ids could repeat those of an earlier start), and
        :class:`EpochsExhaustedError` at the last epoch.  A directory that cannot be written
        (a full disk) is not one: the start goes on read-only (module docstring)."""
        self.prepare()
        for stray in self.directory.glob(f"{_TMP_PREFIX}*{_TMP_SUFFIX}"):
            with contextlib.suppress(OSError):  # (a directory that cannot be written: it stays)
                stray.unlink(missing_ok=True)  # a write a crash cut short; state.bin is whole
        message, level = f"state {self.path}: none yet, starting clean", logging.INFO
        epoch, refused = 0, None
        written_by: int | None = None
        try:
            loaded = self._load()
        except RefusedError as exc:
            loaded, refused, written_by = None, str(exc), exc.epoch
        if loaded is not None:
            written_by = loaded[0].epoch
            epoch, refused, message = self._take(engine, *loaded)
            del loaded  # (its arrays: the engine has what it keeps)
        restored = refused is None and written_by is not None
        if refused is not None:  # the epoch of a refused file still counts when it is known
            epoch = self._next_epoch(written_by)
            level = logging.WARNING
        if not restored:  # the epoch applies all the same
            engine.restore_state(None, epoch)
        self._epoch = epoch
        self._aside = refused is not None
        self.writes += 1
        try:
            self._write(engine.export_state())
        except OSError as exc:
            self.failures += 1
            self._failing = 1
            failure: OSError | None = exc
        else:
            failure = None
        if refused is not None:
            why = " ".join(refused.split())  # one line, whatever an exception's text holds
            where = self._refused_note or f"renamed to {STATE_FILE}{REFUSED_SUFFIX}"
            if failure is not None:
                where = "left in place"
            message = f"state {self.path} refused ({why}): {where}, starting clean"
        message += f"; track-id epoch {epoch}"
        if MAX_EPOCH - 1 - epoch < EPOCHS_LEFT_WARNING:
            message += (
                f" ({MAX_EPOCH - 1 - epoch} more starts before the epochs run out: "
                f"delete {self.path} before then to start afresh)"
            )
            level = max(level, logging.WARNING)
        if failure is not None:
            kept, how = self._keep_epoch(epoch, restored, refused is not None and written_by is not None)
            message += (
                f"; the directory cannot be written ({type(failure).__name__}: {failure}): going on "
                f"read-only with the {'restored' if restored else 'clean'} state, a write is tried "
                f"again every {self.interval_s:g} s of data time; {how}"
            )
            level = max(level, logging.WARNING if kept else logging.ERROR)
        self._saved_clock = engine.data_clock_s
        log.log(level, "%s", message)

    def _take(self, engine: Engine, header: Header, tree: dict[str, Any]) -> tuple[int, str | None, str]:
        """Restore ``engine`` from a whole file's ``header`` and ``tree`` if every value can be
        believed: this start's epoch, why it was refused (None: restored) and the line."""
        try:
            check(header, tree, time.time())
            state = _state(tree)
            epoch = self._next_epoch(header.epoch)
            engine.restore_state(state, epoch)
        except RefusedError as exc:
            return 0, str(exc), ""
        except EpochsExhaustedError:
            raise
        except Exception as exc:  # a state the engine cannot take: it is left as it was
            return 0, f"unreadable content ({type(exc).__name__}: {exc})", ""
        return (
            epoch,
            None,
            f"state {self.path}: restored {state.summary()}, newest data "
            f"{_when(state.data_clock_s)} (written by epoch {header.epoch})",
        )

    def _load(self) -> tuple[Header, dict[str, Any]] | None:
        """The file's header and tree (None: no file); the file's bytes are let go on return."""
        try:
            data = read_file(self.path)
        except FileNotFoundError:
            return None
        return decode(data, self.prefix, self.partition)

    def _next_epoch(self, written_by: int | None) -> int:
        """The epoch after the file's (0 without one): :class:`EpochsExhaustedError` beyond
        the last (:data:`~.fileformat.MAX_EPOCH`), rather than an epoch whose ids were given."""
        if written_by is None:
            return 0
        if written_by + 1 >= MAX_EPOCH:
            why = (
                f"track-id epochs exhausted (the file's epoch is {written_by}, the last there is "
                f"{MAX_EPOCH - 1}: a new epoch could give ids an earlier start gave): delete "
                f"{self.path} to start afresh, track ids then count from 1 again"
            )
            log.error("state %s: %s", self.path, why)
            raise EpochsExhaustedError(errno.EOVERFLOW, why)
        return written_by + 1

    def _keep_epoch(self, epoch: int, restored: bool, refused: bool) -> tuple[bool, str]:
        """With a directory that cannot be written: this start's epoch into the old file's
        header, in place (:func:`~.fileformat.rewrite_epoch`), so that a later start takes the
        next one even if no write succeeds before it.  Whether it was, and how (for the log)."""
        repeat = "until a write succeeds, a later start may give this start's track ids again"
        if not (restored or refused):
            return False, f"epoch {epoch} is kept nowhere (no file with an epoch to write it into): {repeat}"
        try:
            rewrite_epoch(self.path, epoch, whole=restored)
        except OSError as exc:
            return False, f"epoch {epoch} could not be kept ({type(exc).__name__}: {exc}): {repeat}"
        return True, f"epoch {epoch} written into the old file in place, so no track id repeats"

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
            self._failing += 1
            log.error("state %s not written: %s: %s", self.path, type(exc).__name__, exc)
            return
        if self._failing:
            log.warning(
                "state %s written again after %d failed writes (track-id epoch %d)",
                self.path,
                self._failing,
                self._epoch,
            )
            self._failing = 0

    def _put_aside(self) -> str:
        """Rename a refused file ``state.bin.refused`` (replacing an older one): "" when done,
        else what happened instead (for the log; the new file then replaces it)."""
        try:
            os.replace(self.path, self.path.with_name(STATE_FILE + REFUSED_SUFFIX))
        except FileNotFoundError:
            return "no longer there"
        except OSError as exc:
            return f"replaced (it could not be renamed: {type(exc).__name__}: {exc})"
        return ""

    def _write(self, state: EngineState) -> None:
        """``state`` into ``state.bin``, atomically (module docstring)."""
        t0 = time.perf_counter()
        header = Header(self.prefix, self.partition, self._epoch, state.data_clock_s, time.time())
        data = encode(header, {f.name: getattr(state, f.name) for f in fields(EngineState)})
        if len(data) > MAX_FILE_BYTES:  # the next start would refuse it: the last one stays
            raise OSError(
                errno.EFBIG, f"a state of {len(data)} bytes, more than the {MAX_FILE_BYTES} a start reads"
            )
        fd, tmp = tempfile.mkstemp(dir=self.directory, prefix=_TMP_PREFIX, suffix=_TMP_SUFFIX)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            if self._aside:  # a refused file goes aside only now: until then its epoch counts
                self._refused_note = self._put_aside()
                self._aside = False
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
