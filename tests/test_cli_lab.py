"""The command line with and without the lab (topofusion_lab: simulator, scenarios, evaluation).

The runtime does not depend on the lab: ``run``, ``record``, ``replay``, ``schemas`` and
``healthcheck`` never import it (nor matplotlib), and ``demo``, ``simulate`` and ``evaluate``
without it exit 2 with one line saying how to install it.  "Without it" is a child process
whose import system refuses the lab and matplotlib and reports every attempt to import them.
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from service.cli import build_parser, main
from service.recording.writer import RecordingWriter
from tests.scenario_helpers import scenario_messages
from tests.support import free_port
from topofusion_lab.scenarios.catalog import DEMO, SCENARIOS

ROOT = Path(__file__).resolve().parents[1]

#: The child: refuse the lab and matplotlib, run ``service.cli.main(argv)``, report the attempts.
CHILD = """
import json, sys

BLOCKED = ("topofusion_lab", "matplotlib")
attempts = []


class Refuse:
    @staticmethod
    def find_spec(name, path=None, target=None):
        if name.partition(".")[0] in BLOCKED:
            attempts.append(name)
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


sys.meta_path.insert(0, Refuse)
from service.cli import main

try:
    code = main(sys.argv[1:])
finally:
    print("BLOCKED-IMPORTS " + json.dumps(attempts), file=sys.stderr)
sys.exit(code)
"""


def _without_lab(argv: list[str], env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    base = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    return subprocess.Popen(
        [sys.executable, "-c", CHILD, *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**base, **(env or {})},
    )


def _finish(proc: subprocess.Popen[str]) -> tuple[int, str, list[str]]:
    """Exit status, stderr without the report line, and the refused imports."""
    _, err = proc.communicate(timeout=60)
    report = re.search(r"^BLOCKED-IMPORTS (.*)$", err, flags=re.MULTILINE)
    assert report, err
    return proc.returncode, err.replace(report.group(0), "").strip(), json.loads(report.group(1))


def _recording(path: Path) -> Path:
    """A short two-radar recording (made with the lab here, in the test process)."""
    with RecordingWriter(path) as writer:
        for i, (key, payload) in enumerate(scenario_messages("two-radar", duration_s=20.0)):
            writer.write(key, payload, 1_000_000_000 + i * 1_000_000)
    return path


def test_runtime_commands_never_import_the_lab(tmp_path: Path) -> None:
    recording = _recording(tmp_path / "in.mcap")
    with socket.socket() as busy:  # `run` with a refused Zenoh endpoint: everything is imported, then exit 2
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        commands = {
            "run": (
                ["run", "--listen", f"tcp/127.0.0.1:{busy.getsockname()[1]}", "--http-port", "0"],
                {},
                2,
            ),
            "record": (
                [
                    "record",
                    "--out",
                    str(tmp_path / "rec.mcap"),
                    "--duration",
                    "0.3",
                    "--mode",
                    "peer",
                    "--listen",
                    f"tcp/127.0.0.1:{free_port()}",
                ],
                {},
                0,
            ),
            "replay": (
                ["replay", str(recording), "--offline", "--out", str(tmp_path / "out.json")],
                {},
                0,
            ),
            "schemas": (["schemas", "--out", str(tmp_path / "schemas")], {}, 0),
            # nothing listens on that port: exit 1
            "healthcheck": (["healthcheck"], {"TOPOFUSION_HTTP_PORT": str(free_port())}, 1),
        }
        procs = {name: (_without_lab(argv, env), want) for name, (argv, env, want) in commands.items()}
        results = {name: (*_finish(proc), want) for name, (proc, want) in procs.items()}
    for name, (code, err, attempts, want) in results.items():
        assert attempts == [], f"{name} tried to import {attempts}"
        assert code == want, f"{name}: exit {code}\n{err}"
        assert "Traceback" not in err, f"{name}: {err}"
    assert json.loads((tmp_path / "out.json").read_text())["tracks"]
    assert (tmp_path / "rec.mcap").is_file() and (tmp_path / "schemas").is_dir()


def test_lab_commands_without_the_lab_exit_2_saying_how_to_install_it(tmp_path: Path) -> None:
    commands = {
        "demo": ["demo", "--listen", f"tcp/127.0.0.1:{free_port()}", "--http-port", "0"],
        "simulate": ["simulate", "--scenario", "two-radar", "--connect", f"tcp/127.0.0.1:{free_port()}"],
        "simulate --list": ["simulate", "--list"],
        "evaluate": ["evaluate", "--out", str(tmp_path / "evaluation"), "--runs", "1"],
    }
    procs = {name: _without_lab(argv) for name, argv in commands.items()}
    for name, proc in procs.items():
        code, err, attempts = _finish(proc)
        assert code == 2, f"{name}: exit {code}\n{err}"
        assert attempts and all(a.startswith("topofusion_lab") for a in attempts), attempts
        assert err.splitlines() == [
            f"topofusion: `topofusion {name}` needs the TopoFusion lab (topofusion_lab: simulator, "
            "scenarios, evaluation), which is not installed; install it from a checkout with "
            "`pip install -e lab`"
        ], err
    assert not (tmp_path / "evaluation").exists()  # nothing written before the lab was found missing


def test_simulate_list_prints_every_scenario_and_exits_0(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--list"])
    assert exc.value.code == 0
    lines = capsys.readouterr().out.splitlines()
    scenarios = [DEMO, *SCENARIOS.values()]
    assert [ln.split()[0] for ln in lines] == [s.name for s in scenarios]
    for line, scenario in zip(lines, scenarios, strict=True):
        assert scenario.description in line
    assert {"coastal", "national"} <= set(SCENARIOS)


def test_list_is_its_own_flag_and_listen_still_works() -> None:
    """Before ``--list`` existed, argparse took it for an abbreviation of ``--listen``."""
    sim = build_parser().parse_args(["simulate", "--scenario", "demo", "--listen", "tcp/127.0.0.1:7447"])
    assert sim.listen == ["tcp/127.0.0.1:7447"] and not hasattr(sim, "list")
    with pytest.raises(SystemExit):  # --scenario stays required when --list is not given
        build_parser().parse_args(["simulate"])


def test_readme_names_every_scenario() -> None:
    readme = (ROOT / "README.md").read_text()
    row = next(ln for ln in readme.splitlines() if ln.startswith("| `topofusion simulate"))
    for name in [DEMO.name, *SCENARIOS]:
        assert f"`{name}`" in row, name


def test_simulate_s_site_period_is_the_lab_s_and_the_bridge_s() -> None:
    """The parser keeps its own copy of the default (it must not import the lab)."""
    from service.asterix.command import SITE_EVERY_S as BRIDGE_SITE_EVERY_S
    from service.cli import SIMULATE_SITE_EVERY_S
    from topofusion_lab.publisher import SITE_EVERY_S

    assert SIMULATE_SITE_EVERY_S == SITE_EVERY_S == BRIDGE_SITE_EVERY_S
    sim = build_parser().parse_args(["simulate", "--scenario", "demo"])
    assert sim.site_every == SITE_EVERY_S and sim.start_time is None and not sim.loop
    assert (
        build_parser().parse_args(["simulate", "--scenario", "demo", "--start-time", "resume"]).start_time
        == "resume"
    )
    with pytest.raises(SystemExit):
        build_parser().parse_args(["simulate", "--scenario", "demo", "--start-time", "yesterday"])
