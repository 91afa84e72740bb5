"""``/status`` latency and ingest rate with and without operator-picture clients, side by side.

The real service runs as ``topofusion run`` in a process of its own, a Zenoh client of a router
on a free loopback port, while a simulated stream is published as fast as the service takes it
(the publisher blocks when the ingest queue is full, so the batches processed per second are
the service's ingest rate).  Each phase starts a fresh service and publishes the same stream:

1. no picture clients;
2. ``--clients`` clients of ``GET /picture/events``, each with its own ``max_items`` and
   ``interval_s`` (``--interval``), reading everything;
3. as many clients that send their request and never read.

A thread asks ``/status`` every ``STATUS_EVERY_S`` on one keep-alive connection and times each
answer.  Printed per phase: ``/status`` p50/p95/max, the ingest rate (batches/s between
``RATE_FROM`` and the end of the stream), the ingest queue's deepest point, the data lag at the
end (wall time from the last put to the last batch processed), the service's CPU (cores, its
main process), what the clients received, and how often the service dropped one that does not read.
Goals: ``/status`` p95 <= 200 ms and ingest >= 90 % of phase 1's, in phases 2 and 3.

Run: ``.venv/bin/python bench/bench_picture_clients.py [--clients 200] [--scenario national]``
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import select
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import zenoh

from service.transport.session import ZenohOptions, open_session

#: Seconds between two ``/status`` requests of the latency probe.
STATUS_EVERY_S = 0.1
#: The ingest rate is measured from this share of the batches processed to the last one (the
#: first ones fill the trackers' windows: not the steady state).
RATE_FROM = 0.2
#: What a phase may take at most (s), whatever the service does.
PHASE_LIMIT_S = 300.0
#: A ``/status`` request that takes longer counts as failed (and as this long).
STATUS_TIMEOUT_S = 10.0
#: A client that lost its stream comes back after this long (s), as a browser's EventSource.
RECONNECT_S = 2.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def stream(name: str, duration_s: float) -> list[tuple[str, bytes]]:
    from dataclasses import replace

    from topofusion_lab.scenarios.catalog import get_scenario
    from topofusion_lab.scenarios.simulator import wire_messages

    scenario = replace(get_scenario(name), duration_s=duration_s)
    return list(wire_messages(scenario, 1, "fusion"))


@dataclass
class Clients:
    """``count`` picture clients on an event loop of their own (a thread)."""

    base: tuple[str, int]
    count: int
    interval_s: float
    read: bool
    events: int = 0
    bytes: int = 0
    refused: int = 0
    dropped: int = 0
    stop: threading.Event = field(default_factory=threading.Event)
    thread: threading.Thread | None = None

    def query(self, i: int) -> str:
        # every client its own max_items, 50 to about 20 000
        return f"/picture/events?max_items={50 + 97 * i}&interval_s={self.interval_s}&status=all"

    async def one(self, i: int) -> None:
        while not self.stop.is_set():
            await (self.read_all(i) if self.read else self.never_read(i))
            await asyncio.sleep(RECONNECT_S)

    async def read_all(self, i: int) -> None:
        host, port = self.base
        try:
            reader, writer = await asyncio.open_connection(host, port)
        except OSError:
            self.refused += 1
            return
        writer.write(f"GET {self.query(i)} HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
        try:
            head = await reader.readuntil(b"\r\n\r\n")
            if b" 200 " not in head.split(b"\r\n", 1)[0]:
                self.refused += 1
                return
            while not self.stop.is_set():
                chunk = await reader.read(1 << 16)
                if not chunk:
                    return
                self.bytes += len(chunk)
                self.events += chunk.count(b"event: snapshot")
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            pass
        finally:
            writer.close()

    async def never_read(self, i: int) -> None:
        """Send the request, then read nothing; a reset (the service dropping it) is seen
        without reading, by polling the socket for an error."""
        host, port = self.base
        sock = socket.socket()
        sock.setblocking(False)
        try:
            await asyncio.get_running_loop().sock_connect(sock, (host, port))
            sock.send(f"GET {self.query(i)} HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
            poller = select.poll()
            poller.register(sock.fileno(), 0)  # POLLERR and POLLHUP are always reported
            while not self.stop.is_set():
                if poller.poll(0):
                    self.dropped += 1
                    return
                await asyncio.sleep(0.2)
        except OSError:
            self.refused += 1
        finally:
            sock.close()

    def start(self) -> None:
        async def run() -> None:
            tasks = [asyncio.create_task(self.one(i)) for i in range(self.count)]
            while not self.stop.is_set():
                await asyncio.sleep(0.1)
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

        self.thread = threading.Thread(target=asyncio.run, args=(run(),), name="clients", daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        if self.thread is not None:
            self.thread.join(timeout=10)


def cpu_s(pid: int) -> float:
    """CPU seconds (user and system) the process has used so far (its own threads)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def tree_cpu_s(pid: int) -> float:
    """CPU seconds of the process and its children (the correlation process)."""
    total = cpu_s(pid)
    for task in Path(f"/proc/{pid}/task").iterdir():
        for child in (task / "children").read_text().split():
            with contextlib.suppress(OSError):  # (a child that has just ended)
                total += cpu_s(int(child))
    return total


def bench_cpu_s() -> float:
    """CPU seconds this bench (its clients, publisher and probe) has used so far."""
    t = os.times()
    return t.user + t.system


def machine_busy_s() -> tuple[float, float]:
    """(busy, all) CPU seconds of the whole machine so far (other programs included)."""
    cells = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = cells[3] + cells[4]
    return (sum(cells) - idle) / os.sysconf("SC_CLK_TCK"), sum(cells) / os.sysconf("SC_CLK_TCK")


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def phase(
    router: str, messages: list[tuple[str, bytes]], clients: int, read: bool, interval_s: float
) -> dict[str, Any]:
    port = free_port()
    env = {
        **os.environ,
        "TOPOFUSION_LOG_LEVEL": "WARNING",
        "TOPOFUSION_ZENOH_MODE": "client",
        "TOPOFUSION_ZENOH_CONNECT": router,
        "TOPOFUSION_HTTP_PORT": str(port),
    }
    log = tempfile.TemporaryFile()  # noqa: SIM115 (closed once the service has stopped)
    service = subprocess.Popen([sys.executable, "-m", "service", "run"], env=env, stderr=log)
    publisher = open_session(ZenohOptions(mode="client", connect=(router,)))
    crowd = Clients(("127.0.0.1", port), clients, interval_s, read)
    try:
        http = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=STATUS_TIMEOUT_S)
        deadline = time.monotonic() + 60
        while True:
            try:
                if http.get("/readyz").status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline or service.poll() is not None:
                log.seek(0)
                raise RuntimeError(f"the service did not become ready:\n{log.read().decode()[-3000:]}")
            time.sleep(0.2)
        pub = publisher.declare_publisher("fusion/radar/A/plots")
        while not pub.matching_status.matching:
            time.sleep(0.05)
        pub.undeclare()
        if clients:
            crowd.start()
            time.sleep(2.0)  # every client connected and served before the stream starts
        total = sum(k.endswith("/plots") for k, _ in messages)
        published = threading.Event()
        put_done = [0.0]

        def publish() -> None:
            for key, payload in messages:
                publisher.put(
                    key,
                    payload,
                    encoding=zenoh.Encoding.APPLICATION_JSON,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
            put_done[0] = time.monotonic()
            published.set()

        latencies: list[float] = []
        failures = 0
        samples: list[tuple[float, int, int]] = []  # (t, batches processed, queue depth)
        thread = threading.Thread(target=publish, name="publish", daemon=True)
        t0 = time.monotonic()
        bench0 = bench_cpu_s()
        cpu0, tree0, machine0 = cpu_s(service.pid), tree_cpu_s(service.pid), machine_busy_s()
        thread.start()
        while time.monotonic() - t0 < PHASE_LIMIT_S:
            a = time.perf_counter()
            try:
                st = http.get("/status").json()
            except httpx.HTTPError:
                failures += 1
                latencies.append(time.perf_counter() - a)
                continue
            latencies.append(time.perf_counter() - a)
            done = sum(r["batches"] for r in st["radars"])
            samples.append((time.monotonic(), done, st["queue"]["depth"]))
            if done >= total:
                break
            time.sleep(STATUS_EVERY_S)
        end = samples[-1][0]
        wall = max(1e-9, end - t0)
        cpu = (cpu_s(service.pid) - cpu0) / wall
        tree = (tree_cpu_s(service.pid) - tree0) / wall
        machine1 = machine_busy_s()
        busy = (machine1[0] - machine0[0]) / max(1e-9, machine1[1] - machine0[1])
        own = bench_cpu_s() - bench0
        thread.join(timeout=30)
        start = next((s for s in samples if s[1] >= RATE_FROM * total), samples[0])
        rate = (samples[-1][1] - start[1]) / max(1e-9, samples[-1][0] - start[0])
        return {
            "status_p50_ms": 1e3 * statistics.median(latencies),
            "status_p95_ms": 1e3 * percentile(latencies, 0.95),
            "status_max_ms": 1e3 * max(latencies),
            "status_failed": failures,
            "ingest_batches_s": rate,
            "processed": f"{samples[-1][1]}/{total}",
            "queue_max": max(s[2] for s in samples),
            "lag_at_end_s": max(0.0, end - put_done[0]) if published.is_set() else float("nan"),
            "service_cpu_cores": cpu,
            "with_correlation": tree,
            "bench_cpu_cores": own / wall,
            "machine_busy_pct": 100 * busy,
            "client_events": crowd.events,
            "client_mb": crowd.bytes / 1e6,
            "client_refused": crowd.refused,
            "client_dropped": crowd.dropped,
        }
    finally:
        crowd.close()
        publisher.close()
        service.send_signal(signal.SIGTERM)
        try:
            service.wait(timeout=40)
        except subprocess.TimeoutExpired:
            service.kill()
            service.wait()
        log.close()


def median_of(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """Each figure's median over the rounds (numbers; the first round's otherwise)."""
    out = {}
    for key, first in rounds[0].items():
        values = [r[key] for r in rounds]
        numeric = all(isinstance(v, (int, float)) for v in values)
        out[key] = statistics.median(values) if numeric else first
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clients", type=int, default=200)
    ap.add_argument("--interval", type=float, default=0.2, help="the clients' interval_s")
    ap.add_argument("--scenario", default="national")
    ap.add_argument("--duration", type=float, default=150.0, help="data seconds of the stream")
    ap.add_argument("--rounds", type=int, default=1, help="phases run in turn this many times (medians)")
    ap.add_argument("--only", choices=("none", "reading", "silent"), action="append")
    args = ap.parse_args()
    messages = stream(args.scenario, args.duration)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohOptions(mode="router", listen=(endpoint,)))
    phases = {
        "none": (0, True),
        "reading": (args.clients, True),
        "silent": (args.clients, False),
    }
    rounds: dict[str, list[dict[str, Any]]] = {k: [] for k in phases if not args.only or k in args.only}
    try:
        # in turn, so that whatever else the machine does weighs on every phase alike
        for k in range(args.rounds):
            for name in rounds:
                count, read = phases[name]
                print(f"round {k + 1}, phase {name}: {count} clients ...", file=sys.stderr, flush=True)
                rounds[name].append(phase(endpoint, messages, count, read, args.interval))
                ratio = (
                    rounds[name][-1]["ingest_batches_s"] / rounds[next(iter(rounds))][-1]["ingest_batches_s"]
                )
                print(f"  ingest {100 * ratio:.0f} % of the round's first phase", file=sys.stderr, flush=True)
    finally:
        router.close()
    results = {name: median_of(r) for name, r in rounds.items()}
    n = sum(k.endswith("/plots") for k, _ in messages)
    print(f"\n{args.scenario}, {args.duration:.0f} data s ({n} batches); clients: {args.clients}, ", end="")
    print(f"interval_s={args.interval}, max_items 50..{50 + 97 * (args.clients - 1)}, status=all", end="")
    print(f"; medians of {args.rounds} rounds" if args.rounds > 1 else "")
    heads = {"none": "no clients", "reading": "reading", "silent": "never reading"}
    print(f"{'':22s}" + "".join(f"{heads[k]:>16s}" for k in results))
    for key in next(iter(results.values())):
        cells = []
        for r in results.values():
            v = r[key]
            digits = 2 if key.endswith("_cores") else 1
            cells.append(f"{v:16.{digits}f}" if isinstance(v, float) else f"{v!s:>16s}")
        print(f"{key:22s}" + "".join(cells))
    if "none" in rounds:
        for name in rounds:
            if name != "none":
                each = [
                    r["ingest_batches_s"] / b["ingest_batches_s"]
                    for r, b in zip(rounds[name], rounds["none"], strict=True)
                ]
                shown = ", ".join(f"{100 * x:.0f}" for x in each)
                print(
                    f"ingest {heads[name]}: {100 * statistics.median(each):.0f} % of no clients "
                    f"(median; round by round: {shown} %)"
                )


if __name__ == "__main__":
    main()
