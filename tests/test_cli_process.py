"""The service as an operator runs it: `topofusion run` / `demo` in a subprocess with contract flags."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from service.transport.session import ZenohOptions, open_session
from tests.doc_commands import PROCESS_S, started
from tests.scenario_helpers import scenario_messages
from tests.support import free_port, put_json, wait_for, wait_subscribed

TOPOFUSION = str(Path(sys.executable).parent / "topofusion")


@contextmanager
def process(args: list[str], settings: dict[str, str] | None = None) -> Iterator[subprocess.Popen[str]]:
    """`topofusion ARGS` with no TOPOFUSION_* setting but ``settings``; killed if still running."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env = {k: v for k, v in env.items() if not k.startswith("TOPOFUSION_")} | (settings or {})
    proc = subprocess.Popen(
        [TOPOFUSION, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()  # only reached when a test failed before stopping it
            proc.wait(timeout=10)
        if proc.stdout is not None:
            proc.stdout.close()  # (a test that killed the process itself did not read it)


def _http_ready(url: str) -> bool:
    try:
        return httpx.get(url + "/readyz", timeout=1).status_code == 200
    except httpx.HTTPError:
        return False


def _stop(proc: subprocess.Popen[str], sig: signal.Signals) -> tuple[int, float, str]:
    t0 = time.monotonic()
    proc.send_signal(sig)
    out, _ = proc.communicate(timeout=15)
    return proc.returncode, time.monotonic() - t0, out


def test_run_command_ingests_over_zenoh_and_stops_on_sigterm() -> None:
    zport, hport = free_port(), free_port()
    listen = f"tcp/127.0.0.1:{zport}"
    url = f"http://127.0.0.1:{hport}"
    args = ["run", "--mode", "peer", "--listen", listen, "--http-port", str(hport), "--prefix", "fusion"]
    with process(args) as proc:
        wait_for(lambda: _http_ready(url) or proc.poll() is not None, timeout=30)
        assert proc.poll() is None, proc.stdout.read() if proc.stdout else ""
        stream = scenario_messages("two-radar", duration_s=20.0)
        n_batches = sum(k.endswith("/plots") for k, _ in stream)
        session = open_session(ZenohOptions(mode="client", connect=(listen,)))
        try:
            wait_subscribed(session, "fusion/radar/A/plots")
            wait_subscribed(session, "fusion/radar/A/site")
            for key, payload in stream:
                put_json(session, key, payload)
            put_json(session, "fusion/radar/A/plots", b"not json")

            def counted() -> bool:
                st = httpx.get(url + "/status", timeout=2).json()
                return sum(r["batches"] for r in st["radars"]) == n_batches and st["rejected"]

            try:
                wait_for(counted, timeout=30)
            except AssertionError:
                raise AssertionError(httpx.get(url + "/status", timeout=2).text) from None
            status = httpx.get(url + "/status", timeout=2).json()
            assert status["zenoh"] == {"mode": "peer", "listen": [listen], "connect": []}
            assert status["rejected"] == {"malformed_json": 1}
            replies = list(session.get("fusion/status"))
            assert json.loads(replies[0].ok.payload.to_bytes())["radars"][0]["batches"] > 0
        finally:
            session.close()
        code, took, out = _stop(proc, signal.SIGTERM)
    assert code == 0, out
    assert took < 5.0, f"took {took:.1f} s to stop"
    assert "Traceback" not in out, out


def test_demo_runs_the_simulator_and_stops_on_sigint() -> None:
    hport = free_port()
    url = f"http://127.0.0.1:{hport}"
    args = ["demo", "--listen", f"tcp/127.0.0.1:{free_port()}", "--http-port", str(hport), "--speed", "8"]
    with process(args) as proc:
        wait_for(lambda: _http_ready(url) or proc.poll() is not None, timeout=30)
        assert proc.poll() is None

        def picture() -> bool:
            st = httpx.get(url + "/status", timeout=2).json()
            confirmed = sum(r["tracks_confirmed"] for r in st["radars"])
            return confirmed >= 20 and st["pairs_confirmed"] >= 5

        wait_for(picture, timeout=60, interval=0.5)
        code, took, out = _stop(proc, signal.SIGINT)
    assert code == 0, out
    assert took < 5.0
    assert "batches" in out and "confirmed tracks" in out  # the progress line
    assert "Traceback" not in out, out


def test_bad_settings_exit_with_a_clear_error() -> None:
    env = {**os.environ, "TOPOFUSION_HTTP_PORT": "not-a-port"}
    res = subprocess.run([TOPOFUSION, "run"], capture_output=True, text=True, env=env, timeout=30)
    assert res.returncode == 2
    assert "http_port" in res.stderr.lower()
    res = subprocess.run(
        [TOPOFUSION, "run", "--sites", "/nonexistent/sites.json", "--http-port", "0"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert res.returncode == 2 and "sites file not found" in res.stderr
    not_a_dir = Path(__file__)  # a file where the state directory should be
    res = subprocess.run(
        [TOPOFUSION, "run", "--state-dir", str(not_a_dir), "--http-port", "0", "--mode", "client"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2 and f"state directory {not_a_dir} cannot be used" in res.stderr


def test_refused_zenoh_endpoint_is_one_clear_error() -> None:
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        res = subprocess.run(
            [TOPOFUSION, "run", "--listen", f"tcp/127.0.0.1:{port}", "--http-port", "0"],
            capture_output=True,
            text=True,
            timeout=30,
        )
    assert res.returncode == 2
    assert "cannot open Zenoh session" in res.stderr and "Traceback" not in res.stderr


def test_a_taken_http_port_exits_1_as_the_contract_says() -> None:
    """The HTTP port held by another program: `run` ends with 1 (contract §3), not with
    uvicorn's own start-up failure status (3), and says why."""
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        res = subprocess.run(
            [TOPOFUSION, "run", "--listen", f"tcp/127.0.0.1:{free_port()}", "--http-port", str(port)],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert res.returncode == 1, res.stderr
    assert "address already in use" in res.stderr.lower() and "Traceback" not in res.stderr
    # ... and which setting to change
    assert f"HTTP side port did not open on 127.0.0.1:{port}: another port with --http-port" in res.stderr


def test_a_taken_zenoh_port_exits_2_naming_the_setting() -> None:
    """The listen endpoint's port held by another program: one line that says which flag or
    setting picks another, exit 2 (a configuration error, contract §3)."""
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        res = subprocess.run(
            [TOPOFUSION, "run", "--listen", f"tcp/127.0.0.1:{port}", "--http-port", str(free_port())],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert res.returncode == 2, res.stderr
    assert "cannot open Zenoh session" in res.stderr and "Traceback" not in res.stderr
    assert "(another endpoint with --listen or TOPOFUSION_ZENOH_LISTEN)" in res.stderr


def test_python_m_service_is_the_console_script() -> None:
    """`python -m service` equals `topofusion` (contract §3), the lab's commands included."""
    for args in (["--help"], ["demo", "--help"], ["nosuch"]):
        script = subprocess.run([TOPOFUSION, *args], capture_output=True, text=True, timeout=60)
        module = subprocess.run(
            [sys.executable, "-m", "service", *args], capture_output=True, text=True, timeout=60
        )
        assert (module.returncode, module.stdout, module.stderr) == (
            script.returncode,
            script.stdout,
            script.stderr,
        ), args
        assert script.returncode == (2 if args == ["nosuch"] else 0), script.stderr
        if args == ["--help"]:
            assert "demo, simulate, evaluate: from topofusion-lab" in " ".join(script.stdout.split())


def test_the_start_names_the_http_port_it_bound(tmp_path: Path) -> None:
    """``--http-port 0`` picks a free port: the service's line says which (it said 0)."""
    argv = [TOPOFUSION, "run", "--listen", f"tcp/127.0.0.1:{free_port()}", "--http-port", "0"]
    with started(argv, tmp_path) as svc:
        said = wait_for(
            lambda: re.search(r"HTTP side port on http://127\.0\.0\.1:(\d+) ", svc.output()),
            timeout=PROCESS_S,
        )
        port = int(said.group(1))
        assert port > 0
        assert httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=10).status_code == 200
        svc.popen.send_signal(signal.SIGTERM)
        assert svc.popen.wait(timeout=PROCESS_S) == 0, svc.output()


@pytest.mark.slow
def test_bad_settings_are_one_line_that_never_shows_a_secret(tmp_path: Path) -> None:
    """A settings error, whether ``config`` or ``run`` finds it: status 2, one line, no
    traceback, and the API token never in it (a rule over several settings used to quote every
    setting given, the token among them, into the container's log)."""
    secret = "s3cr3t-prod-token"
    bad_json5 = tmp_path / "bad.json5"
    bad_json5.write_text('{mode: "peer",, ')
    bad_yaml = tmp_path / "bad.yaml"  # (a parser's error quotes the line: the token in it)
    bad_yaml.write_text(f'api_token: "{secret}\nhttp_port: 8000\n')
    password = tmp_path / "password.json5"
    password.write_text(f'{{transport: {{auth: {{usrpwd: {{user: "u", password: "{secret}",, }}}}}}}}')
    cases = {
        "a YAML config file that does not parse": (
            {"TOPOFUSION_CONFIG": str(bad_yaml)},
            "cannot be read: found unexpected end of stream at line 3, column 1",
        ),
        "a Zenoh config file with a password that does not parse": (
            {"TOPOFUSION_ZENOH_CONFIG": str(password)},
            "invalid Zenoh configuration: --> 1:",
        ),
        "a connection cap below the requests": (
            {"TOPOFUSION_HTTP_MAX_REQUESTS": "400"},
            "TOPOFUSION_HTTP_MAX_CONNECTIONS (512) must be at least",
        ),
        "a stop grace of inf": (
            {"TOPOFUSION_STOP_GRACE_S": "inf"},
            "stop_grace_s (TOPOFUSION_STOP_GRACE_S): Input should be a finite number",
        ),
        "a stop grace beyond a day": ({"TOPOFUSION_STOP_GRACE_S": "1e10"}, "less than or equal to 86400"),
        "a connect endpoint Zenoh cannot read": (
            {"TOPOFUSION_ZENOH_CONNECT": "garbage"},
            "invalid Zenoh configuration",
        ),
        "a Zenoh config file that is not JSON5": (
            {"TOPOFUSION_ZENOH_CONFIG": str(bad_json5)},
            "invalid Zenoh configuration",
        ),
        "an unknown log level": ({"TOPOFUSION_LOG_LEVEL": "loud"}, "one of DEBUG, INFO, WARNING"),
    }
    for name, (settings, needle) in cases.items():
        for command in (["config"], ["run", "--http-port", "0", "--listen", f"tcp/127.0.0.1:{free_port()}"]):
            with process(command, {"TOPOFUSION_API_TOKEN": secret, **settings}) as proc:
                out, _ = proc.communicate(timeout=60)
            what = f"{name}, {command[0]}"
            assert proc.returncode == 2, f"{what}: exit {proc.returncode}\n{out}"
            assert needle in out and "Traceback" not in out, f"{what}:\n{out}"
            assert len(out.strip().splitlines()) == 1, f"{what}: not one line\n{out}"
            assert secret not in out, f"{what}: the token is shown\n{out}"


def _listening_addresses(port: int) -> set[str]:
    """The local addresses of the TCP sockets listening on ``port`` (``/proc/net/tcp*``, hex)."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as f:
            for line in f.readlines()[1:]:
                local, state = line.split()[1], line.split()[3]
                address, hex_port = local.split(":")
                if state == "0A" and int(hex_port, 16) == port:  # 0A: LISTEN
                    found.add(address)
    return found


def test_warn_level_a_token_from_a_file_and_an_empty_host_start_as_meant() -> None:
    """``TOPOFUSION_LOG_LEVEL=WARN`` (one of the levels taken) runs, where uvicorn knew no
    "warn"; a token that ends with a newline (read from a secret's file) is the token without
    it; an empty ``TOPOFUSION_HTTP_HOST`` is the loopback default, not every interface."""
    hport = free_port()
    url = f"http://127.0.0.1:{hport}"
    settings = {"TOPOFUSION_LOG_LEVEL": "WARN", "TOPOFUSION_API_TOKEN": "tok\n", "TOPOFUSION_HTTP_HOST": ""}
    args = ["run", "--listen", f"tcp/127.0.0.1:{free_port()}", "--http-port", str(hport)]
    with process(args, settings) as proc:
        wait_for(lambda: _http_ready(url) or proc.poll() is not None, timeout=30)
        assert proc.poll() is None, proc.stdout.read() if proc.stdout else ""
        assert httpx.get(url + "/status", timeout=2).status_code == 401
        token = {"Authorization": "Bearer tok"}
        assert httpx.get(url + "/status", headers=token, timeout=2).status_code == 200
        assert _listening_addresses(hport) == {"0100007F"}  # 127.0.0.1 only
        code, _, out = _stop(proc, signal.SIGTERM)
    assert code == 0 and "Traceback" not in out, out


def test_a_killed_service_leaves_no_traceback_and_no_correlation_process(tmp_path: Path) -> None:
    """SIGKILL of ``run`` (an out-of-memory kill, a node lost): its correlation process sees its
    pipe close and ends quietly (it printed an EOFError traceback into the service's log)."""
    from topofusion_lab.demo_workers import descendants, running

    hport = free_port()
    url = f"http://127.0.0.1:{hport}"
    args = ["run", "--listen", f"tcp/127.0.0.1:{free_port()}", "--http-port", str(hport)]
    log_path = tmp_path / "service.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    with log_path.open("w") as log_file:
        proc = subprocess.Popen([TOPOFUSION, *args], stdout=log_file, stderr=subprocess.STDOUT, env=env)
    try:
        wait_for(lambda: _http_ready(url) or proc.poll() is not None, timeout=30)
        children = descendants(proc.pid)
        assert proc.poll() is None and children, log_path.read_text()
        proc.kill()
        proc.wait(timeout=10)
        wait_for(lambda: not any(running(c) for c in children), timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    out = log_path.read_text()
    assert "Traceback" not in out and "EOFError" not in out, out


def test_a_demo_started_before_its_router_waits_for_it_then_runs() -> None:
    """``demo --mode client`` with its router not up yet: the node retries (contract 3.2) and
    the simulator waits for the session, then publishes (it failed at once: "node not
    started", and the demo ended)."""
    hport, zport = free_port(), free_port()
    url = f"http://127.0.0.1:{hport}"
    endpoint = f"tcp/127.0.0.1:{zport}"
    args = ["demo", "--mode", "client", "--connect", endpoint, "--http-port", str(hport), "--speed", "8"]
    with process(args) as proc:
        wait_for(lambda: _http_ok(url + "/healthz") or proc.poll() is not None, timeout=30)
        time.sleep(1.0)  # (the simulator's thread has started by now, without a session)
        assert proc.poll() is None, proc.stdout.read() if proc.stdout else ""
        assert httpx.get(url + "/readyz", timeout=2).json()["reason"] == "connecting to zenoh"
        router = open_session(ZenohOptions(mode="router", listen=(endpoint,)))
        try:
            wait_for(
                lambda: sum(r["batches"] for r in httpx.get(url + "/status", timeout=2).json()["radars"]) > 0,
                timeout=60,
                interval=0.5,
            )
            code, _, out = _stop(proc, signal.SIGINT)
        finally:
            router.close()
    assert code == 0 and "simulator failed" not in out and "Traceback" not in out, out


def _http_ok(url: str) -> bool:
    try:
        return httpx.get(url, timeout=1).status_code == 200
    except httpx.HTTPError:
        return False
