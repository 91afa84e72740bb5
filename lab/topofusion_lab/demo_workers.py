"""``topofusion demo --workers N``: a Zenoh router and N partitioned workers on one machine,
fed by the demo's simulator (docs/scale-out.md, "Running N workers by hand").

This process opens a router-mode Zenoh session on a free loopback TCP port (``--listen``
instead, when given; multicast scouting off), starts N ``topofusion run`` workers as child
processes (worker K with ``TOPOFUSION_PARTITION=K/N``, a client of the router, an HTTP port
each), waits until every one is ready and the partition is whole, then publishes the demo's
scenario into the router.  It prints one line per worker (its HTTP, picture and status URLs)
and a progress line every few seconds.  SIGINT/SIGTERM stops the simulator, then every
worker it started (SIGTERM, then SIGKILL after a timeout), then the router: exit status 0.
A worker that does not start ends the demo with exit status 2, naming the worker and the
end of its log, and with every worker stopped.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

log = logging.getLogger("topofusion")

#: The most workers ``--workers`` starts: each is a process of its own on this one machine (a
#: few hundred MB and a core's share each), so more only shows the exchange's overhead.
MAX_DEMO_WORKERS = 16
#: How long a worker may take to answer ``/readyz`` 200 (s, wall clock).
READY_TIMEOUT_S = 60.0
#: How long, once every worker is ready, until no partition is missing (s).
WHOLE_TIMEOUT_S = 30.0
#: A worker stopped by SIGTERM has its ``stop_grace_s`` to finish; beyond this much more, it is killed.
KILL_AFTER_S = 10.0
#: Wall seconds between two progress lines.
PROGRESS_EVERY_S = 5.0
#: Lines of a failed worker's log that are shown.
LOG_TAIL_LINES = 20


class WorkerFailedError(Exception):
    """A worker that did not start (exited, or not ready in time)."""


@dataclass
class Worker:
    """One ``topofusion run`` child process."""

    index: int
    count: int
    host: str
    port: int
    log_path: Path
    proc: subprocess.Popen[bytes]
    token: str | None = None
    reported_exit: bool = False

    @property
    def name(self) -> str:
        return f"worker {self.index}/{self.count}"

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def get(self, path: str, timeout_s: float = 2.0) -> tuple[int, Any]:
        """``GET path``: (HTTP status, JSON body or None)."""
        request = urllib.request.Request(self.url + path)
        if self.token:
            request.add_header("Authorization", f"Bearer {self.token}")
        try:
            with urllib.request.urlopen(request, timeout=timeout_s) as response:
                return response.status, json.loads(response.read() or b"null")
        except urllib.error.HTTPError as exc:
            return exc.code, None

    def status(self) -> dict[str, Any] | None:
        """Its ``/status``, or None when it does not answer."""
        try:
            code, body = self.get("/status")
        except (OSError, ValueError):
            return None
        return body if code == 200 and isinstance(body, dict) else None

    def tail(self, lines: int = LOG_TAIL_LINES) -> str:
        try:
            text = self.log_path.read_text(encoding="utf-8", errors="replace")
        except OSError:
            return "(no log)"
        last = text.rstrip().splitlines()[-lines:]
        return "\n".join(f"    {line}" for line in last) if last else "    (its log is empty)"


# -- arguments -----------------------------------------------------------------------------------


def _refuse(args: argparse.Namespace) -> None:
    """Flags that mean one worker, or another Zenoh layout, do not go with ``--workers``."""
    if getattr(args, "mode", None) not in (None, "router"):
        raise ValueError("--workers: this process is the Zenoh router; --mode does not apply")
    for flag, dest in (
        ("--zenoh-config", "zenoh_config"),
        ("--radars", "radars"),
        ("--partition", "partition"),
    ):
        if getattr(args, dest, None):
            raise ValueError(
                f"--workers: {flag} does not apply (each worker gets its partition K/N); to lay the "
                "network out otherwise, start the router and the workers by hand (docs/scale-out.md)"
            )


def _free_port(host: str) -> int:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _loopback(host: str) -> str:
    """Where this machine reaches a server bound to ``host`` (a wildcard: the loopback)."""
    if host in ("", "0.0.0.0"):
        return "127.0.0.1"
    if host == "::":
        return "::1"
    return host


def _url_host(host: str) -> str:
    host = _loopback(host)
    return f"[{host}]" if ":" in host else host


def _client_endpoint(endpoint: str) -> str:
    """The router's listen endpoint as a worker on this machine connects to it."""
    for wildcard, loopback in (("/0.0.0.0:", "/127.0.0.1:"), ("/[::]:", "/[::1]:")):
        endpoint = endpoint.replace(wildcard, loopback)
    return endpoint.split("#", 1)[0]


def _topofusion() -> list[str]:
    """The command that starts ``topofusion``: the console script beside this interpreter,
    else the interpreter with ``-m service``."""
    script = Path(sys.executable).parent / "topofusion"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "service"]


def _run_flags(args: argparse.Namespace) -> list[str]:
    """The demo's service flags every worker takes as they are."""
    flags: list[str] = []
    for flag, dest in (
        ("--sites", "sites"),
        ("--method", "method"),
        ("--window", "window"),
        ("--initiator", "initiator"),
        ("--log-level", "log_level"),
        ("--config", "config"),
    ):
        value = getattr(args, dest, None)
        if value is not None:
            flags += [flag, str(value)]
    return flags


def check_state_dir(state_dir: Path | None, count: int) -> None:
    """A ``--state-dir`` that holds the state of another count of workers is refused (one
    worker keeps ``DIR/state.bin``, N > 1 each ``DIR/worker-K-of-N``): with another count every
    worker would start without state at epoch 0, and give track ids given before."""
    from service.state.keeper import STATE_FILE

    if state_dir is None or not Path(state_dir).is_dir():
        return
    root = Path(state_dir)
    counts = {int(m.group(1)) for p in root.iterdir() if (m := re.fullmatch(r"worker-\d+-of-(\d+)", p.name))}
    if (root / STATE_FILE).exists():
        counts.add(1)
    found = sorted(counts - {count})
    if found:
        raise ValueError(
            f"--state-dir {root} holds the state of {found[0]} worker(s): with --workers {count} "
            f"track ids given before could come again; run with --workers {found[0]}, or give "
            "another --state-dir"
        )


# -- the workers ---------------------------------------------------------------------------------


def start_workers(
    count: int,
    connect: Sequence[str],
    settings: Any,
    args: argparse.Namespace,
    log_dir: Path,
    workers: list[Worker],
) -> None:
    """Start ``count`` workers into ``workers`` (none waited for), each added as soon as it
    runs: whatever fails on the way, the caller stops those started."""
    host = settings.http_host
    base_port = getattr(args, "http_port", None)
    token = settings.api_token.get_secret_value() if settings.api_token else None
    for k in range(1, count + 1):
        port = base_port + k - 1 if base_port else _free_port(_loopback(host))
        env = dict(os.environ)
        # The environment is read over a config file and under the flags: these settle what
        # each worker's config file or the caller's environment might say otherwise.
        env.update(
            TOPOFUSION_PARTITION=f"{k}/{count}",
            TOPOFUSION_ZENOH_MODE="client",
            TOPOFUSION_ZENOH_CONNECT=",".join(connect),
            TOPOFUSION_ZENOH_LISTEN="",
            TOPOFUSION_ZENOH_CONFIG="",
            TOPOFUSION_RADARS="",
            TOPOFUSION_HTTP_HOST=host,
            TOPOFUSION_HTTP_PORT=str(port),
            TOPOFUSION_PREFIX=settings.prefix,
            # each partitioned worker needs a state directory of its own
            TOPOFUSION_STATE_DIR=str(Path(settings.state_dir) / f"worker-{k}-of-{count}")
            if settings.state_dir
            else "",
        )
        log_path = log_dir / f"worker-{k}-of-{count}.log"
        with log_path.open("wb") as log_file:
            proc = subprocess.Popen(
                _term_with_parent([*_topofusion(), "run", *_run_flags(args)]),
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=log_file,
                stderr=subprocess.STDOUT,
            )
        workers.append(Worker(k, count, _url_host(host), port, log_path, proc, token))


#: Run in each worker's process before ``topofusion run`` (Linux), which it then becomes
#: (``execv``: the same pid): SIGTERM when the demo dies, even killed (SIGKILL, out of memory),
#: so that no worker outlives it serving a network whose router is gone (``prctl``'s
#: PR_SET_PDEATHSIG, 1, which ``execv`` keeps); a demo already gone by then ends it at once.
TERM_WITH_PARENT = (
    "import ctypes, os, signal, sys; ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM); "
    "os.getppid() == int(sys.argv[1]) or sys.exit(0); os.execv(sys.argv[2], sys.argv[2:])"
)


def _term_with_parent(command: list[str]) -> list[str]:
    """``command`` started so that it ends with the demo (:data:`TERM_WITH_PARENT`; as it is
    elsewhere than on Linux)."""
    if not sys.platform.startswith("linux"):
        return command
    return [sys.executable, "-c", TERM_WITH_PARENT, str(os.getpid()), *command]


def wait_ready(workers: list[Worker], stop: threading.Event) -> bool:
    """Wait until every worker answers ``/readyz`` 200 and its ``/status`` misses no partition.
    False: ``stop`` was set meanwhile.  Raises :class:`WorkerFailedError`."""

    def check_alive(w: Worker) -> None:
        code = w.proc.poll()
        if code is not None:
            raise WorkerFailedError(
                f"{w.name} (pid {w.proc.pid}) exited with status {code} before it was ready; "
                f"the end of its log:\n{w.tail()}"
            )

    def ready(w: Worker) -> bool:
        try:
            return w.get("/readyz")[0] == 200
        except (OSError, ValueError):
            return False

    def whole(w: Worker) -> bool:
        st = w.status()
        if st is None:
            return False
        partition = st.get("partition")
        return w.count == 1 or (partition is not None and not partition["missing"])

    for predicate, timeout_s, what in (
        (ready, READY_TIMEOUT_S, "ready (/readyz)"),
        (whole, WHOLE_TIMEOUT_S, "seeing every partition (/status)"),
    ):
        deadline = time.monotonic() + timeout_s
        waiting = list(workers)
        while waiting:
            for w in waiting:
                check_alive(w)
            waiting = [w for w in waiting if not predicate(w)]
            if not waiting:
                break
            if time.monotonic() > deadline:
                w = waiting[0]
                raise WorkerFailedError(
                    f"{w.name} (pid {w.proc.pid}) not {what} within {timeout_s:g} s; "
                    f"the end of its log:\n{w.tail()}"
                )
            if stop.wait(0.2):
                return False
    return True


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (Linux ``/proc``; elsewhere none are found)."""
    parent_of: dict[int, int] = {}
    try:
        entries = os.listdir("/proc")
    except OSError:
        return []
    for entry in entries:
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            parent_of[int(entry)] = int(stat.rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
    found: list[int] = []
    frontier = [pid]
    while frontier:
        parent = frontier.pop()
        children = [p for p, pp in parent_of.items() if pp == parent]
        found += children
        frontier += children
    return found


def running(pid: int) -> bool:
    """The process exists and is no zombie (Linux /proc)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def stop_workers(workers: list[Worker], timeout_s: float) -> None:
    """SIGTERM to every worker still running, then SIGKILL to any (and what it started) still
    there after ``timeout_s``.  What a worker started (its correlation process) may outlive it
    by a moment: it is waited for too, within the same time."""
    below: set[int] = set()
    for w in workers:
        if w.proc.poll() is None:
            below.update(descendants(w.proc.pid))
            with contextlib.suppress(ProcessLookupError):
                w.proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    for w in workers:
        below.update(descendants(w.proc.pid))  # (one started since)
        try:
            w.proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            print(f"demo: {w.name} (pid {w.proc.pid}) did not stop in time: killed", file=sys.stderr)
            w.proc.kill()
            w.proc.wait()
    while any(map(running, below)) and time.monotonic() < deadline:
        time.sleep(0.05)
    for pid in filter(running, below):
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)


# -- what is printed -----------------------------------------------------------------------------


def _clock(t: float | None) -> str:
    return time.strftime("%H:%M:%S", time.gmtime(t)) if t is not None else "--:--:--"


def progress_line(workers: list[Worker]) -> str:
    """The data time; each worker's radars, the plot batches of those it processed and the
    radar pairs it correlates (from its own ``/status``); the network's confirmed and tentative
    pairs and correlation updates (every worker's ``/status`` covers the whole network)."""
    parts: list[str] = []
    data_time: float | None = None
    network: dict[str, Any] | None = None
    for w in workers:
        if w.proc.poll() is not None:
            parts.append(f"{w.index}/{w.count} stopped ({w.proc.returncode})")
            continue
        st = w.status()
        if st is None:
            parts.append(f"{w.index}/{w.count} not answering")
            continue
        network = network or st
        times = [r["last_time_s"] for r in st["radars"] if r.get("last_time_s") is not None]
        data_time = max([*times, *([data_time] if data_time is not None else [])], default=None)
        partition = st.get("partition") or {}
        me = next((i for i in partition.get("workers", []) if i["partition"] == f"{w.index}/{w.count}"), None)
        own = sorted(me["radars"]) if me else sorted(r["radar_id"] for r in st["radars"])
        batches = sum(r["batches"] for r in st["radars"] if r["radar_id"] in own)
        pair_sets = me["pair_sets"] if me else len(own) * (len(own) - 1) // 2
        parts.append(f"{w.index}/{w.count} [{','.join(own) or '-'}] batches {batches}, pair sets {pair_sets}")
    whole = (
        f"pairs {network['pairs_confirmed']} confirmed / {network['pairs_tentative']} tentative, "
        f"correlation updates {network['correlation']['updates']}"
        if network
        else "no worker answers"
    )
    return f"demo: data {_clock(data_time)} | " + " | ".join(parts) + f" | network: {whole}"


def _say(text: str, out: TextIO | None = None) -> None:
    print(text, file=out or sys.stdout, flush=True)


# -- the command ---------------------------------------------------------------------------------


def _restore(handlers: dict[signal.Signals, Any]) -> None:
    for sig, handler in handlers.items():
        signal.signal(sig, handler)


def run_workers_demo(args: argparse.Namespace) -> int:
    """``topofusion demo --workers N`` (``args``: the demo command's arguments and ``workers``).
    Runs until SIGINT/SIGTERM: 0; a worker that does not start: 2.  Raises ``ValueError`` for
    flags that do not go with ``--workers`` before anything starts."""
    from service.cli.common import settings_from, setup_logging
    from service.transport.session import ZenohOptions, open_session
    from topofusion_lab.commands.simulate import SITE_EVERY_S, scenario_for
    from topofusion_lab.publisher import publish_scenario

    count = int(args.workers)
    if not 1 <= count <= MAX_DEMO_WORKERS:
        raise ValueError(f"--workers {count}: need 1 to {MAX_DEMO_WORKERS} (each worker is a process)")
    _refuse(args)
    settings = settings_from(args)
    setup_logging(settings.log_level)
    check_state_dir(settings.state_dir, count)
    scenario = scenario_for(args)  # an unknown scenario fails here, before anything starts

    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    listen = (
        tuple(args.listen) if getattr(args, "listen", None) else (f"tcp/127.0.0.1:{_free_port('127.0.0.1')}",)
    )
    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        router = open_session(
            ZenohOptions(mode="router", listen=listen, connect=tuple(getattr(args, "connect", None) or ()))
        )
    except BaseException:
        _restore(previous)
        raise
    log_dir = Path(tempfile.mkdtemp(prefix="topofusion-demo-"))
    workers: list[Worker] = []
    simulator: threading.Thread | None = None
    sim_stop = threading.Event()
    status = 0
    try:
        start_workers(count, [_client_endpoint(e) for e in listen], settings, args, log_dir, workers)
        _say(
            f"demo: router on {', '.join(listen)}; {count} worker(s) on prefix {settings.prefix!r} "
            f"starting (logs in {log_dir}, removed when the demo stops)"
        )
        if not wait_ready(workers, stop):
            return 0
        for w in workers:
            _say(
                f"demo: {w.name}  {w.url}  picture {w.url}/picture  status {w.url}/status  (pid {w.proc.pid})"
            )
        if args.start_time is None:  # the scenario starts now, not when the command did
            scenario = scenario_for(args)

        def simulate() -> None:
            try:
                publish_scenario(
                    router,
                    scenario,
                    settings.prefix,
                    args.speed,
                    args.seed,
                    sim_stop,
                    site_every_s=SITE_EVERY_S,
                )
                if not sim_stop.is_set():
                    _say("demo: the scenario has ended; the workers go on serving (Ctrl-C to stop)")
            except Exception:
                if not sim_stop.is_set():
                    log.exception("simulator failed")

        simulator = threading.Thread(target=simulate, name="demo-simulator", daemon=True)
        simulator.start()
        _say(
            f"demo: scenario {scenario.name!r} ({scenario.description}) at {args.speed}x through "
            f"{count} worker(s); Ctrl-C to stop"
        )
        while not stop.wait(PROGRESS_EVERY_S):
            for w in workers:
                if w.proc.poll() is not None and not w.reported_exit:
                    w.reported_exit = True
                    _say(
                        f"demo: {w.name} (pid {w.proc.pid}) exited with status {w.proc.returncode}; the "
                        f"others go on without its partition; the end of its log:\n{w.tail()}",
                        sys.stderr,
                    )
            _say(progress_line(workers))
    except WorkerFailedError as exc:
        _say(f"demo: {exc}", sys.stderr)
        status = 2
    finally:
        sim_stop.set()
        if simulator is not None:
            simulator.join(timeout=5.0)
        stop_workers(workers, settings.stop_grace_s + KILL_AFTER_S)
        router.close()
        shutil.rmtree(log_dir, ignore_errors=True)
        _restore(previous)
    if status == 0:
        _say(f"demo: stopped {count} worker(s) and the router")
    return status
