"""`topofusion demo --workers N` end to end: a router and two partitioned `topofusion run`
workers on one machine, fed by the demo's simulator, then stopped by SIGINT with nothing left
behind (lab/topofusion_lab/demo_workers.py, docs/scale-out.md "Running N workers by hand")."""

from __future__ import annotations

import functools
import os
import queue
import re
import shlex
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.doc_commands import (
    PROCESS_S,
    ROOT,
    TOPOFUSION,
    Proc,
    code_block,
    commands,
    environment,
    free_ports,
    started,
    with_ports,
)
from tests.support import wait_for
from topofusion_lab.demo_workers import descendants, running

#: ``demo: worker K/N  URL  picture URL  status URL  (pid P)``
WORKER_LINE = re.compile(
    r"^demo: worker (\d+)/(\d+)  (http://\S+)  picture (\S+)  status (\S+)  \(pid (\d+)\)$"
)
#: The command as a user types it (``topofusion demo --workers N``).
DEMO = [TOPOFUSION, "demo"]


def _status(url: str) -> dict[str, Any]:
    response = httpx.get(url + "/status", timeout=5)
    response.raise_for_status()
    body: dict[str, Any] = response.json()
    return body


@pytest.mark.slow
def test_demo_with_two_workers_serves_the_whole_network_and_stops_cleanly() -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    env["PYTHONUNBUFFERED"] = "1"
    args = ["--scenario", "two-radar", "--speed", "10", "--seed", "1", "--workers", "2"]
    proc = subprocess.Popen(
        [*DEMO, *args, "--log-level", "WARNING"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    lines: queue.Queue[str] = queue.Queue()
    output: list[str] = []

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line.rstrip("\n"))

    reader = threading.Thread(target=read, name="demo-output", daemon=True)
    reader.start()
    worker_pids: list[int] = []
    try:
        # -- the worker lines: K/N, the HTTP, picture and status URLs, the pid --------------
        workers: dict[int, dict[str, Any]] = {}
        deadline = time.monotonic() + 60
        while len(workers) < 2:
            assert reader.is_alive() or not lines.empty(), "demo ended early:\n" + "\n".join(output)
            assert time.monotonic() < deadline, "no worker lines within 60 s:\n" + "\n".join(output)
            try:
                line = lines.get(timeout=0.5)
            except queue.Empty:
                continue
            output.append(line)
            m = WORKER_LINE.match(line)
            if m:
                k, n, url, picture, status, pid = m.groups()
                assert n == "2"
                assert picture == f"{url}/picture" and status == f"{url}/status"
                workers[int(k)] = {"url": url, "pid": int(pid)}
                worker_pids.append(int(pid))
        assert sorted(workers) == [1, 2]
        assert workers[1]["url"] != workers[2]["url"]
        for w in workers.values():
            assert w["pid"] in descendants(proc.pid), "each worker is a child of the demo"
        worker_pids += [c for w in workers.values() for c in descendants(w["pid"])]

        # -- every partition present, both workers processing their own radars ----------------
        def owners(url: str) -> dict[str, int]:
            st = _status(url)
            assert st["partition"]["count"] == 2 and st["partition"]["missing"] == []
            assert all(i["alive"] for i in st["partition"]["workers"])
            infos = st["partition"]["workers"]
            return {rid: int(i["partition"].split("/")[0]) for i in infos for rid in i["radars"]}

        def processing(url: str) -> bool:
            st = _status(url)
            own = {i["partition"]: set(i["radars"]) for i in st["partition"]["workers"]}
            me = own.get(st["partition"]["partition"], set())
            return bool(me) and all(r["batches"] > 0 for r in st["radars"] if r["radar_id"] in me)

        def both_and_processing(url: str) -> bool:
            return set(owners(url).values()) == {1, 2} and processing(url)

        for w in workers.values():  # each sees the radars of both, and processes its own
            wait_for(functools.partial(both_and_processing, w["url"]), timeout=30)
        owner = owners(workers[1]["url"])

        # -- worker 1 serves pairs of radars owned by both workers -------------------------------
        def mixed_pairs() -> list[dict[str, Any]]:
            pair_sets = httpx.get(workers[1]["url"] + "/pairs", timeout=15).json()
            return [
                ps
                for ps in pair_sets
                if {owner.get(ps["radar_a"]), owner.get(ps["radar_b"])} == {1, 2} and ps["pairs"]
            ]

        found = wait_for(mixed_pairs, timeout=40, interval=0.5)
        assert any(p["status"] == "confirmed" for ps in found for p in ps["pairs"])
        picture = httpx.get(workers[1]["url"] + "/picture", timeout=5)
        assert picture.status_code == 200 and "html" in picture.headers["content-type"]

        # -- a progress line naming both workers --------------------------------------------------
        def progress() -> bool:
            while not lines.empty():
                output.append(lines.get())
            return any(line.startswith("demo: data ") and "| 2/2 " in line for line in output)

        wait_for(progress, timeout=15, interval=0.2)

        # -- SIGINT: exit 0, every worker (and what it started) gone ----------------------------
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=45)
        reader.join(timeout=5)
        while not lines.empty():
            output.append(lines.get())
        assert code == 0, "\n".join(output)
        assert any(line.startswith("demo: stopped 2 worker(s)") for line in output), "\n".join(output)
        assert not running(proc.pid)
        left = [pid for pid in worker_pids if running(pid)]
        assert not left, f"processes left behind: {left}"
    finally:
        _end(proc, worker_pids)  # (only when the test failed before the demo stopped)


def _with_environment(marker: str) -> list[int]:
    """Processes whose environment holds ``marker`` (Linux /proc; this user's only)."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit() and int(entry) != os.getpid():
            try:
                environ = Path(f"/proc/{entry}/environ").read_bytes()
            except OSError:
                continue
            if marker.encode() in environ and running(int(entry)):
                found.append(int(entry))
    return found


def test_demo_exits_2_naming_a_worker_that_does_not_start(tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("")  # each worker's state directory would be below a file: it cannot start
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    args = ["--scenario", "two-radar", "--workers", "2", "--state-dir", str(blocker)]
    proc = subprocess.Popen(
        [*DEMO, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        out, err = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:  # only when the test failed before the demo ended
            proc.kill()
            proc.wait(timeout=10)
    assert proc.returncode == 2, out + err
    m = re.search(r"demo: worker ([12])/2 \(pid (\d+)\) exited with status \d+ before it was ready", err)
    assert m, err
    assert f"worker-{m.group(1)}-of-2 cannot be used" in err, "the end of its log is shown"
    assert not running(int(m.group(2)))
    assert not _with_environment(str(blocker)), "a worker was left behind"


def test_demo_refuses_a_state_directory_of_another_worker_count(tmp_path: Path) -> None:
    """A ``--state-dir`` that holds the state of another count of workers: each worker would
    start at epoch 0 without state, and give track ids a run before gave (it did, silently)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    one, two = tmp_path / "one", tmp_path / "two"
    one.mkdir()
    (one / "state.bin").write_bytes(b"")  # a one-process demo's (or run's) state
    (two / "worker-1-of-2").mkdir(parents=True)  # a demo of two workers'
    for state, workers, held in ((one, "3", 1), (two, "1", 2), (two, "3", 2)):
        args = ["--scenario", "two-radar", "--http-port", "0", "--workers", workers]
        args += ["--state-dir", str(state)]
        res = subprocess.run([*DEMO, *args], capture_output=True, text=True, env=env, timeout=90)
        said = f"--state-dir {state} holds the state of {held} worker(s): with --workers {workers}"
        assert res.returncode == 2 and said in res.stderr, (args, res.stderr)
        assert "Traceback" not in res.stderr


def _run_line(line: str) -> tuple[list[str], dict[str, str]]:
    """A documented command line: its argv (``topofusion`` the venv's) and the settings
    before it; a trailing ``&`` dropped."""
    words = shlex.split(line.removesuffix("&").strip())
    settings = {}
    while "=" in words[0]:
        name, value = words.pop(0).split("=", 1)
        settings[name] = value
    assert words[0] == "topofusion", line
    return [TOPOFUSION, *words[1:]], settings


@pytest.mark.slow
def test_the_two_workers_by_hand_of_the_docs(tmp_path: Path) -> None:
    """docs/scale-out.md, "Running N workers by hand": the block as written, free ports for
    the fixed ones."""
    ports = free_ports()
    block = code_block(ROOT / "docs" / "scale-out.md", "## Running N workers by hand", index=1)
    # with_ports gives endpoints (":7447") theirs; the HTTP ports are settings here ("PORT=8000")
    texts = [
        re.sub(r"(?<=_PORT=)(8000|8001)\b", lambda m: ports[m.group(1)], line) for line in commands(block)
    ]
    lines = [_run_line(with_ports(text, ports)) for text in texts]
    assert [argv[1] for argv, _ in lines] == ["run", "run", "simulate"]
    urls = [f"http://127.0.0.1:{ports[p]}" for p in ("8000", "8001")]
    (argv1, env1), (argv2, env2), (argv_sim, _) = lines
    with (
        started(argv1, tmp_path, environment(**env1)) as worker1,
        started(argv2, tmp_path, environment(**env2)) as worker2,
    ):

        def whole(url: str) -> bool:
            try:
                st = httpx.get(url + "/status", timeout=2).json()
            except httpx.HTTPError:
                return False
            return st["partition"]["count"] == 2 and st["partition"]["missing"] == []

        def whole_or_ended(url: str, w: Proc) -> bool:
            return whole(url) or w.popen.poll() is not None

        for url, w in zip(urls, (worker1, worker2), strict=True):
            wait_for(functools.partial(whole_or_ended, url, w), timeout=PROCESS_S)
            assert w.popen.poll() is None, w.output()
        with started(argv_sim, tmp_path) as sim:

            def pairs_across() -> bool:
                pair_sets = httpx.get(urls[0] + "/pairs", timeout=15).json()
                return any(p["status"] == "confirmed" for ps in pair_sets for p in ps["pairs"])

            # A and B: worker 2 owns A and the pair, worker 1 owns B (`topofusion partition --count 2`)
            wait_for(pairs_across, timeout=40, interval=0.5)
            assert sim.popen.poll() is None, sim.output()
        for w in (worker1, worker2):
            w.popen.send_signal(signal.SIGTERM)
        for w in (worker1, worker2):
            assert w.popen.wait(timeout=30) == 0, w.output()


def test_a_killed_demo_takes_its_workers_with_it() -> None:
    """SIGKILL of ``demo --workers 2`` (no handler runs): its workers are told by the kernel
    (Linux) and stop, rather than serve on for ever without their router (they did)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    env["PYTHONUNBUFFERED"] = "1"
    args = ["--scenario", "two-radar", "--speed", "10", "--workers", "2", "--log-level", "WARNING"]
    proc = subprocess.Popen(
        [*DEMO, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    pids: list[int] = []
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            m = WORKER_LINE.match(line.rstrip("\n"))
            if m:
                pids.append(int(m.group(6)))
            if len(pids) == 2:
                break
        assert len(pids) == 2, "no worker lines"
        proc.kill()
        proc.wait(timeout=10)
        wait_for(lambda: not any(running(pid) for pid in pids), timeout=40, interval=0.5)
    finally:
        _end(proc, pids)


def _end(proc: subprocess.Popen[str], pids: list[int]) -> None:
    """The demo and the processes ``pids`` killed by their pids where they still run."""
    if proc.poll() is None:
        proc.kill()
        proc.wait(timeout=10)
    for pid in pids:
        if running(pid):
            os.kill(pid, signal.SIGKILL)
    if proc.stdout is not None:
        proc.stdout.close()
