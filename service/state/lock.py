"""One process to a state directory: an exclusive lock on the directory itself, held for the
life of the process.

Two processes on one directory (a directory shared by mistake between workers, an old
process still running beside its replacement) would read the same file and take the same
track-id epoch, so the ids of one would repeat the other's; and each would write over the
other's state.  The second start is refused instead.  The lock is taken on the directory
(``flock`` of a read-only descriptor), so a directory the service may only read (a read-only
mount, its permissions) is locked too and the start goes on read-only as before; it goes with
the process: one killed (even by SIGKILL) leaves the directory free.  The holder writes its
pid into ``DIR/state.lock`` where it can, for the message (never through a link); the same
process may take the lock again (a start after a refused one, tests that start twice)."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import stat
from pathlib import Path

#: The file in the state directory that names the holder's pid (for the message only).
LOCK_FILE = "state.lock"

#: The directories this process holds, by resolved path: their descriptors.
_HELD: dict[Path, int] = {}


def lock_directory(directory: Path) -> None:
    """Take ``directory``'s lock for this process, or raise ``OSError`` (``EBUSY``) saying
    another process holds it (its pid where its lock file says).  The directory must exist."""
    where = Path(directory).resolve()
    if where in _HELD:
        return
    fd = os.open(where, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        holder = _holder(where)
        raise OSError(
            errno.EBUSY,
            f"in use by another process{f' (pid {holder})' if holder else ''}: each service, each "
            "partitioned worker, needs a state directory of its own",
        ) from None
    except BaseException:
        os.close(fd)
        raise
    _HELD[where] = fd
    with contextlib.suppress(OSError):  # (a directory that cannot be written: no pid named)
        pid = os.open(where / LOCK_FILE, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o644)
        try:
            os.write(pid, f"{os.getpid()}\n".encode())
        finally:
            os.close(pid)


def release_directory(directory: Path) -> None:
    """Let ``directory`` go (the node's stop): another process may take it while this one
    lives on (a test's, a host's)."""
    fd = _HELD.pop(Path(directory).resolve(), None)
    if fd is not None:
        os.close(fd)  # (closing the descriptor releases its flock)


def _holder(where: Path) -> str:
    """The pid the holder wrote (empty: none readable; never read through a link)."""
    try:
        fd = os.open(where / LOCK_FILE, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:
        return ""
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return ""
        text = os.read(fd, 32).decode("ascii", "replace").strip()
    finally:
        os.close(fd)
    return text if text.isdigit() else ""
