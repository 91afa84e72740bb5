"""docs/recording.md's recipes, run as written, every step started at once (one script): the
recording holds the run's tracks and pairs, its offline replay is identical to them, and its
replay into a fresh service over Zenoh gives them again.

The scripts get free ports instead of 7447, 8000 and 8001, and nothing else.  Each step waits
for what it needs (the recorder is the router; the simulator waits for the service and for
its outputs), which is what lets them start together; without those waits the simulator's
first sites and plots go out before anybody has subscribed.
"""

from __future__ import annotations

import json
import subprocess
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.recording.reader import RecordingReader
from tests.doc_commands import (
    PROCESS_S,
    ROOT,
    code_block,
    commands,
    environment,
    free_ports,
    started,
    with_ports,
)

RECORDING_DOC = ROOT / "docs" / "recording.md"
#: The record script runs 40 s of data at 50x; with the service's start-up and its stop it
#: takes a few seconds; this bounds it (s).
SCRIPT_TIMEOUT_S = 90.0
#: The recipe's run: 40 s of data, each radar scanning every 4 or 5 s in 8 or 10 sectors.
BATCHES_PER_RADAR = 80
#: Confirmed pairs the service's final outputs hold at least (the run confirms about 80 per
#: radar pair: a bound well below, the scenario being random).
MIN_CONFIRMED_PAIRS = 20


def run_script(block: str, cwd: Path, ports: dict[str, str]) -> tuple[int, str]:
    script = "set -e\n" + with_ports(block, ports)
    with started(["bash", "-c", script], cwd, environment()) as proc:
        try:
            code = proc.popen.wait(timeout=SCRIPT_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the script did not end within {SCRIPT_TIMEOUT_S:g} s:\n{proc.output()}")
    return code, proc.output()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, str]]:
    """The recipe "Record a demo run", run as one script."""
    cwd = tmp_path_factory.mktemp("recipe")
    code, out = run_script(code_block(RECORDING_DOC, "### Record a demo run"), cwd, free_ports())
    assert code == 0, out
    yield cwd / "demo.mcap", out


def test_the_record_recipe_started_at_once_records_tracks_and_pairs(recorded: tuple[Path, str]) -> None:
    path, out = recorded
    assert "the service's outputs are complete through data time" in out, out
    with RecordingReader(path) as reader:
        survey = reader.survey()
        keys = {c.topic for c in survey.channels.values()}
        messages = list(reader.messages(list(survey.channels.values())))
    by_key = Counter(m.key for m in messages)
    radars = ("A", "B", "C")
    for r in radars:
        assert (
            by_key[f"fusion/radar/{r}/site"] >= 1 and by_key[f"fusion/radar/{r}/plots"] == BATCHES_PER_RADAR
        ), by_key
        assert f"fusion/radar/{r}/tracks" in keys
    assert {"fusion/pairs/A/B", "fusion/pairs/A/C", "fusion/pairs/B/C"} <= keys
    # the service's final outputs (published at its stop) hold confirmed tracks and pairs
    last_pairs = {m.key: json.loads(m.payload) for m in messages if m.kind == "pairs"}
    confirmed = sum(p["status"] == "confirmed" for ps in last_pairs.values() for p in ps["pairs"])
    assert confirmed >= MIN_CONFIRMED_PAIRS, last_pairs.keys()
    rejections = [json.loads(m.payload) for m in messages if m.kind == "errors"]
    assert rejections == []  # every site came before its plots: nothing was unknown


def test_its_offline_replay_is_identical_to_the_recorded_outputs(
    recorded: tuple[Path, str], tmp_path: Path
) -> None:
    path, _ = recorded
    (tmp_path / "demo.mcap").symlink_to(path)
    [command] = commands(code_block(RECORDING_DOC, "### Replay offline and compare"))
    assert command.startswith("topofusion replay demo.mcap --offline")
    run = subprocess.run(
        command.split(), cwd=tmp_path, env=environment(), capture_output=True, text=True, timeout=PROCESS_S
    )
    assert run.returncode == 0, run.stderr
    assert "IDENTICAL" in run.stderr


def test_its_replay_into_a_fresh_service_started_at_once(recorded: tuple[Path, str], tmp_path: Path) -> None:
    path, _ = recorded
    (tmp_path / "demo.mcap").symlink_to(path)
    code, out = run_script(code_block(RECORDING_DOC, "### Replay it"), tmp_path, free_ports())
    assert code == 0, out
    assert "replay: the service answers" in out, out
    assert "the service's outputs are complete through data time" in out, out
    assert "rejected" not in out, out
