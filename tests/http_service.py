"""The service as an operator runs it (``python -m service run`` in a process of its own, a Zenoh
client of a router on a free loopback port, HTTP on another), for the HTTP limit tests, and the
raw sockets those tests open.  The process is stopped by its own pid; every socket is closed.
"""

from __future__ import annotations

import contextlib
import os
import resource
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO

import httpx

from tests.support import free_port, wait_for

#: How long the service may take to answer ``/readyz`` after it is started (s).
START_S = 30.0
#: How long it may take to stop after SIGTERM before it is killed (s).
STOP_S = 30.0
#: ``python -m service`` under an open-file limit of its own.
LIMITED = (
    "import resource, runpy, sys; resource.setrlimit(resource.RLIMIT_NOFILE, ({0}, {0})); "
    "sys.argv[0] = 'topofusion'; runpy.run_module('service', run_name='__main__')"
)


@dataclass
class Served:
    """A running service: its address, its process and what it logged so far."""

    host: str
    port: int
    process: subprocess.Popen[bytes]
    _log: IO[bytes]

    @property
    def base_url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def log(self) -> str:
        self._log.flush()
        self._log.seek(0)
        return self._log.read().decode(errors="replace")


def _ready(url: str) -> bool:
    try:
        return httpx.get(url + "/readyz", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


@contextlib.contextmanager
def served(router: str, settings: dict[str, str], open_files: int | None = None) -> Iterator[Served]:
    """The service with ``settings`` (``TOPOFUSION_*`` variables; no other of the environment),
    a client of ``router``; ``open_files``: its open-file limit (soft and hard)."""
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    env |= {
        "PYTHONUNBUFFERED": "1",
        "TOPOFUSION_ZENOH_MODE": "client",
        "TOPOFUSION_ZENOH_CONNECT": router,
        "TOPOFUSION_HTTP_PORT": str(port),
        # one process: the tests here are about HTTP, and a second process costs a start-up
        "TOPOFUSION_CORRELATION_PROCESS": "false",
        **settings,
    }

    command = [sys.executable, "-m", "service", "run"]
    if open_files is not None:  # set in the child itself, before the service starts
        command = [sys.executable, "-c", LIMITED.format(open_files), "run"]
    with tempfile.TemporaryFile() as log:
        proc = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT)
        service = Served("127.0.0.1", port, proc, log)
        try:
            url = service.base_url
            wait_for(lambda: _ready(url) or proc.poll() is not None, timeout=START_S, interval=0.1)
            assert proc.poll() is None, f"the service ended (status {proc.returncode}):\n{service.log()}"
            yield service
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=STOP_S)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(timeout=10)


def open_idle(host: str, port: int, count: int, head: bytes = b"") -> list[socket.socket]:
    """``count`` connections, opened at once (non-blocking connects), each having sent
    ``head`` (a request head never finished, or nothing) and nothing more."""
    socks = []
    try:
        for _ in range(count):
            s = socket.socket()
            socks.append(s)
            s.setblocking(False)
            s.connect_ex((host, port))
        # poll, not select: the descriptors may be past select's 1 024
        poller = select.poll()
        pending = {s.fileno(): s for s in socks}
        for fd in pending:
            poller.register(fd, select.POLLOUT)
        deadline = time.monotonic() + 15.0
        while pending and time.monotonic() < deadline:
            for fd, _ in poller.poll(500):
                s = pending.pop(fd)
                poller.unregister(fd)
                if head and s.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) == 0:
                    with contextlib.suppress(OSError):
                        s.send(head)
        return socks
    except BaseException:
        for s in socks:
            s.close()
        raise


def _readable(s: socket.socket) -> bool:
    poller = select.poll()
    poller.register(s.fileno(), select.POLLIN)
    return bool(poller.poll(0))


def closed_by_peer(s: socket.socket) -> bool:
    """Whether the server has closed (or refused, or reset) the connection; reads what came."""
    try:
        while _readable(s):
            if not s.recv(65536):
                return True
        return False
    except (ConnectionResetError, BrokenPipeError):
        return True
    except BlockingIOError:
        return False
    except OSError:  # never connected (refused at the kernel's backlog)
        return True


def reset_by_peer(s: socket.socket) -> bool:
    """Whether the connection was reset (or closed both ways), seen without reading from it."""
    poller = select.poll()
    poller.register(s.fileno(), 0)  # POLLERR and POLLHUP are reported whatever is asked
    return bool(poller.poll(0))


def ensure_open_files(count: int) -> None:
    """This process may hold ``count`` more descriptors (the soft limit raised if need be)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = count + 256
    if soft != resource.RLIM_INFINITY and soft < want:
        target = want if hard == resource.RLIM_INFINITY else min(want, hard)
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
