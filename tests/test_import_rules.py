"""The house's import rules (pyproject.toml [tool.importlinter]) hold, and fail when broken."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT = Path(sys.executable).with_name("lint-imports")


def lint(tree: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    return subprocess.run(
        [str(LINT), "--config", str(tree / "pyproject.toml"), "--no-cache"],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    shutil.copytree(ROOT / "service", tmp_path / "service", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def test_the_rules_hold(tree: Path) -> None:
    run = lint(tree)
    assert run.returncode == 0, run.stdout[-3000:]
    assert "5 kept, 0 broken" in run.stdout


@pytest.mark.parametrize(
    ("module", "line", "rule"),
    [
        ("tracking/base.py", "import service.wire.models", "numerics never import"),
        ("correlation/gls.py", "import zenoh", "numerics never import"),
        ("assessment/radar.py", "import fastapi", "numerics never import"),
        ("api/metrics.py", "import service.assessment.radar", "transport and HTTP leave the numerics"),
        ("api/metrics.py", "import service.correlation.umeyama", "transport and HTTP leave the numerics"),
        ("wire/keys.py", "import service.geo", "the wire imports no numerics"),
        ("engine.py", "import matplotlib", "nothing in the runtime imports the lab"),
        ("asterix/bridge.py", "import zenoh", "ASTERIX decoding, inputs and the bridge's rules"),
    ],
)
def test_a_broken_rule_fails(tree: Path, module: str, line: str, rule: str) -> None:
    path = tree / "service" / module
    path.write_text(path.read_text() + f"\n{line}  # noqa\n")
    run = lint(tree)
    assert run.returncode != 0
    assert f"{rule}" in run.stdout and "BROKEN" in run.stdout
