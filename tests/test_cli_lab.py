"""The command line with and without the lab (topofusion_lab: simulator, scenarios, evaluation).

The runtime does not depend on the lab: its commands (``demo``, ``simulate``, ``evaluate``) come
through the entry point group ``topofusion.commands`` (service/cli/groups.py).  Without the lab,
``run``, ``record``, ``replay``, ``schemas`` and ``healthcheck`` work and never try to import it
(nor matplotlib), and the lab's commands exit 2 with one line saying how to install it.
"Without it" is a child process in which ``importlib.metadata`` does not list the lab's
distribution and whose import system refuses the lab and matplotlib, reporting every attempt
to import them; "stale", the lab's metadata is there but its package is not (a checkout's lab
removed after an editable install).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest

from service.cli import build_parser, main
from service.recording.writer import RecordingWriter
from tests.scenario_helpers import scenario_messages
from tests.support import free_port
from topofusion_lab.scenarios.catalog import DEMO, SCENARIOS

ROOT = Path(__file__).resolve().parents[1]
#: What the lab's commands say where it is not installed: the command, then this.
NOT_INSTALLED = (
    "needs the TopoFusion lab (topofusion_lab: simulator, scenarios, evaluation), which is not "
    "installed; install it from a checkout with `pip install -e lab`"
)

#: The child: ``sys.argv[1]`` is the lab's state (absent, stale or installed); it runs
#: ``service.cli.main(sys.argv[2:])`` and reports the imports of the lab and matplotlib it
#: refused (absent, stale) or made (installed).
CHILD = """
import importlib.metadata, json, sys

LAB = sys.argv[1]
BLOCKED = ("topofusion_lab", "matplotlib")
attempts = []


class Refuse:
    @staticmethod
    def find_spec(name, path=None, target=None):
        if name.partition(".")[0] in BLOCKED:
            attempts.append(name)
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


if LAB == "absent":
    listed = importlib.metadata.distributions
    importlib.metadata.distributions = lambda **kw: (
        d for d in listed(**kw) if d.metadata["Name"] != "topofusion-lab"
    )
if LAB != "installed":
    sys.meta_path.insert(0, Refuse)
from service.cli import main

try:
    code = main(sys.argv[2:])
finally:
    if LAB == "installed":
        attempts = sorted(m for m in sys.modules if m.partition(".")[0] in BLOCKED)
    print("BLOCKED-IMPORTS " + json.dumps(attempts), file=sys.stderr)
sys.exit(code)
"""


def _without_lab(
    argv: list[str], env: dict[str, str] | None = None, lab: str = "absent"
) -> subprocess.Popen[str]:
    """``topofusion ARGV`` in the child, the lab ``absent`` (or ``stale``, or ``installed``)."""
    base = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    return subprocess.Popen(
        [sys.executable, "-c", CHILD, lab, *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**base, **(env or {})},
    )


def _finish(proc: subprocess.Popen[str]) -> tuple[int, str, list[str]]:
    """Exit status, stderr without the report line, and the lab's imports (refused or made)."""
    code, err, attempts, _ = _outcome(proc)
    return code, err, attempts


def _outcome(proc: subprocess.Popen[str]) -> tuple[int, str, list[str], str]:
    """:func:`_finish`'s, and stdout."""
    out, err = proc.communicate(timeout=60)
    report = re.search(r"^BLOCKED-IMPORTS (.*)$", err, flags=re.MULTILINE)
    assert report, err
    return proc.returncode, err.replace(report.group(0), "").strip(), json.loads(report.group(1)), out


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


@pytest.mark.parametrize("lab", ["absent", "stale"])
def test_lab_commands_without_the_lab_exit_2_saying_how_to_install_it(tmp_path: Path, lab: str) -> None:
    commands = [  # (what the message names, the command line)
        ("demo", ["demo", "--listen", f"tcp/127.0.0.1:{free_port()}", "--http-port", "0"]),
        ("simulate", ["simulate", "--scenario", "two-radar", "--connect", f"tcp/127.0.0.1:{free_port()}"]),
        ("simulate --list", ["simulate", "--list"]),
        ("evaluate", ["evaluate", "--out", str(tmp_path / "evaluation"), "--runs", "1"]),
        ("demo", ["demo", "--help"]),  # its flags are the lab's: without it, it has none
    ]
    procs = [(name, _without_lab(argv, lab=lab)) for name, argv in commands]
    for name, proc in procs:
        code, err, attempts, out = _outcome(proc)
        assert code == 2, f"{name}: exit {code}\n{err}"
        if lab == "absent":  # not listed: not looked for
            assert attempts == [], attempts
        else:  # listed: its entry point is loaded, and its package found missing
            assert attempts and all(a.startswith("topofusion_lab") for a in attempts), attempts
        assert err.splitlines() == [f"topofusion: `topofusion {name}` {NOT_INSTALLED}"], err
        assert out == ""
    assert not (tmp_path / "evaluation").exists()  # nothing written


@pytest.mark.parametrize("lab", ["absent", "stale"])
def test_help_without_the_lab_says_how_to_add_its_commands(lab: str) -> None:
    code, err, _, out = _outcome(_without_lab(["--help"], lab=lab))
    assert code == 0 and err == "", err
    listed = _listed(out)
    assert listed == [
        "run", "record", "replay", "assess", "asterix", "healthcheck", "config", "partition", "schemas"
    ]  # fmt: skip
    note = " ".join(out.split("\n\n")[-1].split())
    assert note == (
        "not installed: demo, simulate, evaluate; they need the TopoFusion lab (topofusion_lab: "
        "simulator, scenarios, evaluation); install it from a checkout with `pip install -e lab` "
        "(the runtime and the lab together, as `make install-demo` does: `pip install -e . -e lab`)"
    )
    assert "pip install --quiet -e . -e lab" in (ROOT / "Makefile").read_text()  # install-demo's


def test_help_with_the_lab_lists_its_commands_and_where_they_come_from() -> None:
    code, err, attempts, out = _outcome(_without_lab(["--help"], lab="installed"))
    assert code == 0 and err == "", err
    listed = _listed(out)
    assert set(listed) == set(_subcommands(build_parser()))
    assert {"demo", "simulate", "evaluate"} <= set(listed)
    version = metadata.version("topofusion-lab")
    note = " ".join(out.split("\n\n")[-1].split())
    assert note == (
        f"demo, simulate, evaluate: from topofusion-lab {version} (entry point 'lab' of topofusion.commands)"
    )
    # parsing every start of topofusion imports the lab's commands, not the simulator nor matplotlib
    assert attempts and all(
        a.startswith("topofusion_lab.commands") or a == "topofusion_lab" for a in attempts
    )


def test_the_lab_declares_its_command_group_as_an_entry_point() -> None:
    [ep] = metadata.entry_points(group="topofusion.commands", name="lab")
    assert ep.value == "topofusion_lab.commands:register"
    assert ep.dist is not None and ep.dist.name == "topofusion-lab"
    assert 'lab = "topofusion_lab.commands:register"' in (ROOT / "lab" / "pyproject.toml").read_text()


def _listed(help_text: str) -> list[str]:
    """The commands ``--help`` lists."""
    return re.findall(r"^ {4}(\S+)(?: |$)", help_text, flags=re.MULTILINE)


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _hello(commands: argparse._SubParsersAction) -> None:
    from service.cli.common import add_command

    hello = add_command(commands, "hello", lambda args: print(f"hello {args.name}") or 3, help="say hello")
    hello.add_argument("--name", default="world")


def _broken(commands: argparse._SubParsersAction) -> None:
    raise RuntimeError("no good")


def test_groups_of_other_distributions_add_their_commands(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    group = "topofusion.commands"
    eps = [
        metadata.EntryPoint("extra", f"{__name__}:_hello", group),
        metadata.EntryPoint("gone", "topofusion_gone.commands:register", group),  # a stale install
        metadata.EntryPoint("lab", f"{__name__}:_broken", group),
    ]
    monkeypatch.setattr(metadata, "entry_points", lambda group: [ep for ep in eps if ep.group == group])
    assert main(["hello", "--name", "radar"]) == 3
    assert capsys.readouterr().out == "hello radar\n"
    # a known group that cannot be loaded: its commands say so, as the help does
    assert main(["demo", "--speed", "2"]) == 2
    assert capsys.readouterr().err == (
        "topofusion: `topofusion demo` needs the TopoFusion lab (topofusion_lab: simulator, "
        "scenarios, evaluation), which is installed but cannot be loaded (RuntimeError: no good)\n"
    )
    with pytest.raises(SystemExit):
        main(["--help"])
    note = " ".join(capsys.readouterr().out.split("\n\n")[-1].split())
    assert note == (
        f"hello: from {__name__}:_hello (entry point 'extra' of topofusion.commands) "
        f"the command group 'lab' ({__name__}:_broken) is installed but cannot be loaded "
        "(RuntimeError: no good)"
    )


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
    """The parser keeps its own copy of the default (it must not import the simulator)."""
    from service.asterix.command import SITE_EVERY_S as BRIDGE_SITE_EVERY_S
    from topofusion_lab.commands.simulate import SITE_EVERY_S as SIMULATE_SITE_EVERY_S
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


def test_the_demo_s_right_pairs_count_the_pairs_with_adsb_too() -> None:
    """`demo --scenario assessment`'s line counts the confirmed pairs right by the simulator's
    truth: a radar track paired with an ADS-B track is right when that track's icao24 is its
    aircraft's (every one of them counted wrong before: 238 of 372 said right, all were)."""
    from tests.support import run_engine
    from topofusion_lab.commands.demo import _correct_by_truth

    engine, _ = run_engine(scenario_messages("assessment", duration_s=150.0))
    snap = engine.snapshot()
    sets = snap.pair_sets(status="confirmed")
    confirmed = sum(len(ps["pairs"]) for ps in sets)
    with_reference = sum(len(ps["pairs"]) for ps in sets if ps["radar_b"] not in snap.tracks)
    assert with_reference >= 50 and confirmed - with_reference >= 50
    assert _correct_by_truth(snap) >= 0.98 * confirmed
