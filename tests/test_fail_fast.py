"""Commands refuse bad input at once, before any Zenoh connection is tried, naming what is wrong.

Every command here is given a router endpoint nobody listens on: a tool that got as far as
connecting would wait for it (``TOOL_CONNECT_RETRY_S``, 30 s), saying "waiting for the Zenoh
router".  They are started together and must all end with status 2 well before that.
"""

from __future__ import annotations

import os
from contextlib import ExitStack
from pathlib import Path

import pytest

from tests.doc_commands import PROCESS_S, TOPOFUSION, started
from tests.support import free_port, wait_for

#: What says a command was refused before connecting is its output (no "waiting for the Zenoh
#: router"), not how fast it came: the cases start together, a score of interpreters on two
#: loaded cores, and their imports alone took more than 15 s in a clean-clone CI run.  Each
#: ends within a started command's bound (:data:`~tests.doc_commands.PROCESS_S`); one that
#: tried to connect says so, and exits otherwise than 2, after the tools' 30 s wait.
FAIL_FAST_S = PROCESS_S


def _bad_inputs(tmp_path: Path) -> dict[str, tuple[list[str], list[str]]]:
    """name -> (arguments, what the message must say)."""
    capture = tmp_path / "capture.pcap"
    capture.write_bytes(bytes.fromhex("d4c3b2a1020004000000000000000000ffff000001000000"))
    (tmp_path / "notes.json").write_text('{"not": "a recording"}\n')
    (tmp_path / "empty.mcap").write_bytes(b"")
    (tmp_path / "sites.json").write_text(
        '[{"radar_id": "A", "latitude_deg": 1, "longitude_deg": 2, "sac": 0, "sic": 1}]'
    )
    missing = tmp_path / "no-such-dir"
    bad_json5 = tmp_path / "bad.json5"
    bad_json5.write_text('{mode: "peer",, ')
    unknown_key = tmp_path / "unknown.json5"
    unknown_key.write_text("{bogus_key: 1}")
    tls = tmp_path / "tls.json5"
    tls.write_text('{transport: {link: {tls: {root_ca_certificate: "%s"}}}}' % (missing / "ca.pem"))
    return {
        "replay a pcap": (
            ["replay", str(capture)],
            [f"{capture} is not an MCAP file", "it starts with b'\\xd4\\xc3\\xb2\\xa1", "pcap capture"],
        ),
        "replay JSON": (["replay", str(tmp_path / "notes.json")], ["is not an MCAP file", "JSON text"]),
        "replay an empty file": (
            ["replay", str(tmp_path / "empty.mcap")],
            ["empty.mcap is not an MCAP file (it is empty)"],
        ),
        "replay a missing file": (
            ["replay", str(tmp_path / "gone.mcap")],
            [f"{tmp_path / 'gone.mcap'}: no such file"],
        ),
        "replay a directory": (["replay", str(tmp_path)], ["is a directory"]),
        "record into a missing directory": (
            ["record", "--out", str(missing / "run.mcap")],
            [f"the directory {missing} does not exist"],
        ),
        "record into a directory": (["record", "--out", str(tmp_path)], [f"--out {tmp_path} is a directory"]),
        "replay --offline --out into a missing directory": (
            ["replay", str(tmp_path / "gone.mcap"), "--offline", "--out", str(missing / "result.json")],
            [f"--out {missing / 'result.json'}: the directory {missing} does not exist"],
        ),
        "run with a port beyond 65535": (
            ["run", "--http-port", "99999"],
            [
                "invalid setting http_port (TOPOFUSION_HTTP_PORT): Input should be less than",
                "65535, got 99999",
            ],
        ),
        "replay --compare without --offline": (
            ["replay", str(tmp_path / "gone.mcap"), "--compare"],
            ["--compare is for --offline"],
        ),
        "asterix --file missing": (
            ["asterix", "--sites", str(tmp_path / "sites.json"), "--file", str(tmp_path / "gone.pcap")],
            ["gone.pcap: cannot read the file: No such file or directory"],
        ),
        "asterix --out-file in a missing directory": (
            ["asterix", "--out-file", str(missing / "tracks.ast")],
            [f"--out-file {missing / 'tracks.ast'}: the directory {missing} does not exist"],
        ),
        "simulate --asterix-file in a missing directory": (
            ["simulate", "--scenario", "two-radar", "--asterix-file", str(missing / "feed.pcap")],
            [f"the directory {missing} does not exist"],
        ),
        "simulate --write-sites in a missing directory": (
            ["simulate", "--scenario", "two-radar", "--write-sites", str(missing / "sites.json")],
            [f"the directory {missing} does not exist"],
        ),
        "run with a listen endpoint Zenoh cannot read": (
            ["run", "--http-port", "0", "--listen", "garbage"],
            ["invalid Zenoh configuration", "Endpoints must be of the form", "garbage"],
        ),
        "record with a connect endpoint Zenoh cannot read": (
            ["record", "--out", str(tmp_path / "run.mcap"), "--connect", "garbage"],
            ["invalid Zenoh configuration", "garbage"],
        ),
        "run with a Zenoh config file that is not JSON5": (
            ["run", "--http-port", "0", "--zenoh-config", str(bad_json5)],
            ["invalid Zenoh configuration", "expected identifier or string"],
        ),
        "run with an unknown key in its Zenoh config": (
            ["run", "--http-port", "0", "--zenoh-config", str(unknown_key)],
            ["invalid Zenoh configuration", "unknown field `bogus_key`"],
        ),
        "run with a TLS file of its Zenoh config missing": (
            ["run", "--http-port", "0", "--zenoh-config", str(tls)],
            [f"zenoh config transport/link/tls/root_ca_certificate: no such file {missing / 'ca.pem'}"],
        ),
        "record with a key expression Zenoh refuses": (
            ["record", "--out", str(tmp_path / "run.mcap"), "--key", "a//b"],
            ["invalid key expression 'a//b'", "empty chunks are forbidden"],
        ),
        "run with a sites file that is not JSON": (
            ["run", "--http-port", "0", "--sites", str(tmp_path / "notes.json")],
            ["is not a JSON list of RadarSite: Input should be a valid array"],
        ),
        "demo at a negative speed": (["demo", "--http-port", "0", "--speed", "-1"], ["--speed: '-1'"]),
        "demo with a negative seed": (["demo", "--http-port", "0", "--seed", "-1"], ["--seed: '-1'"]),
        "simulate at a speed of nan": (
            ["simulate", "--scenario", "demo", "--speed", "nan"],
            ["--speed: 'nan'"],
        ),
        "asterix with an ADS-B id no source may have": (
            ["asterix", "--out-file", str(tmp_path / "t.ast"), "--adsb-id", "a b"],
            ["--adsb-id 'a b' must match"],
        ),
        "asterix for a duration of nan": (
            ["asterix", "--out-file", str(tmp_path / "t.ast"), "--duration", "nan"],
            ["--duration must be a finite number > 0"],
        ),
        "asterix with ADS-B batches of nan": (
            ["asterix", "--out-file", str(tmp_path / "t.ast"), "--adsb-batch", "nan"],
            ["--adsb-batch and --max-batch must be finite numbers > 0"],
        ),
        "asterix writing CAT062 to port 0": (
            ["asterix", "--out-udp", "127.0.0.1:0"],
            ["--out-udp needs a destination port (1-65535), not 0"],
        ),
    }


@pytest.mark.slow
def test_bad_input_is_refused_before_connecting(tmp_path: Path) -> None:
    nobody = f"tcp/127.0.0.1:{free_port()}"
    cases = _bad_inputs(tmp_path)
    with ExitStack() as stack:
        procs = {
            name: stack.enter_context(started([TOPOFUSION, *argv, "--connect", nobody], tmp_path))
            for name, (argv, _) in cases.items()
        }
        for name, proc in procs.items():
            code = proc.popen.wait(timeout=FAIL_FAST_S)
            out = proc.output()
            assert code == 2, f"{name}: exit {code}\n{out}"
            assert "waiting for the Zenoh router" not in out, f"{name} tried to connect:\n{out}"
            assert "Traceback" not in out, f"{name}:\n{out}"
            for needle in cases[name][1]:
                assert needle in out, f"{name}: {needle!r} not in\n{out}"


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads files whatever their permissions")
def test_an_unreadable_file_is_refused_before_connecting(tmp_path: Path) -> None:
    secret = tmp_path / "secret.mcap"
    secret.write_bytes(b"\x89MCAP0\r\n")
    secret.chmod(0)
    capture = tmp_path / "secret.pcap"
    capture.write_bytes(b"")
    capture.chmod(0)
    (tmp_path / "sites.json").write_text(
        '[{"radar_id": "A", "latitude_deg": 1, "longitude_deg": 2, "sac": 0, "sic": 1}]'
    )
    nobody = f"tcp/127.0.0.1:{free_port()}"
    argvs = {
        "replay": (["replay", str(secret)], "not readable (permission denied)"),
        "asterix": (
            ["asterix", "--sites", str(tmp_path / "sites.json"), "--file", str(capture)],
            "Permission denied",
        ),
    }
    for name, (argv, needle) in argvs.items():
        with started([TOPOFUSION, *argv, "--connect", nobody], tmp_path) as proc:
            assert proc.popen.wait(timeout=FAIL_FAST_S) == 2, name
            assert needle in proc.output(), proc.output()


def test_a_tool_waiting_for_its_router_stops_cleanly_on_a_signal(tmp_path: Path) -> None:
    """``record``, ``replay`` and ``simulate`` still waiting for their router (none there) end
    on SIGINT or SIGTERM with status 0 and a line saying nothing was done, not a traceback or
    the signal's own status."""
    import signal

    from service.recording.writer import RecordingWriter
    from tests.scenario_helpers import scenario_messages

    recording, replayed = tmp_path / "run.mcap", tmp_path / "in.mcap"
    with RecordingWriter(replayed, "fusion") as w:
        for n, (key, payload) in enumerate(scenario_messages("two-radar", duration_s=10.0)):
            w.write(key, payload, log_time_ns=n)
    nobody = f"tcp/127.0.0.1:{free_port()}"
    tools = {
        "record": (["record", "--out", str(recording)], "nothing recorded"),
        "replay": (["replay", str(replayed)], "nothing replayed"),
        "simulate": (["simulate", "--scenario", "two-radar"], "nothing published"),
    }
    signals = (signal.SIGINT, signal.SIGTERM, signal.SIGTERM)
    for (name, (argv, said)), sig in zip(tools.items(), signals, strict=True):
        with started([TOPOFUSION, *argv, "--connect", nobody], tmp_path) as proc:
            wait_for(lambda: "waiting for the Zenoh router" in proc.output(), timeout=FAIL_FAST_S)
            proc.popen.send_signal(sig)
            code = proc.popen.wait(timeout=FAIL_FAST_S)
            out = proc.output()
        assert code == 0, f"{name}, {sig.name}: exit {code}\n{out}"
        assert f"stopped while waiting for the Zenoh router; {said}" in out, out
        assert "Traceback" not in out, out
    assert not recording.exists()
