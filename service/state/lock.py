"""One process to a state directory: an exclusive lock on ``DIR/state.lock``, held for the
life of the process.

Two processes on one directory (a directory shared by mistake between workers, an old
process still running beside its replacement) would read the same file and take the same
track-id epoch, so the ids of one would repeat the other's; and each would write over the
other's state.  The second start is refused instead, naming the process that holds it.
``flock`` locks go with the process: one killed (even by SIGKILL) leaves the directory free.
The lock is the process's, so the same process may take it again (a start after a refused
one, tests that start twice)."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from pathlib import Path

#: The lock file in the state directory (it holds the holder's pid, for the message).
LOCK_FILE = "state.lock"

#: The directories this process holds, by resolved path: their lock files' descriptors.
_HELD: dict[Path, int] = {}


def lock_directory(directory: Path) -> None:
    """Take ``directory``'s lock for this process, or raise ``OSError`` (``EBUSY``) naming
    the process that holds it.  The directory must exist."""
    where = Path(directory).resolve()
    if where in _HELD:
        return
    fd = os.open(where / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
        os.close(fd)
        raise OSError(
            errno.EBUSY,
            f"in use by another process (pid {holder}): each service, each partitioned worker, "
            "needs a state directory of its own",
        ) from None
    except BaseException:
        os.close(fd)
        raise
    with contextlib.suppress(OSError):  # (the pid is for the message only)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    _HELD[where] = fd
