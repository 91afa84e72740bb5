"""The house's import rules (pyproject.toml [tool.importlinter]) hold, and fail when broken."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # the same parser, before it joined the standard library
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
LINT = Path(sys.executable).with_name("lint-imports")
CONTRACTS = [
    c["name"]
    for c in tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
]
LAYERS = "the layers of the house"


def lint(tree: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    return subprocess.run(
        [str(LINT), str(tree / "pyproject.toml"), "--no-cache"],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )


def broken(run: subprocess.CompletedProcess[str]) -> list[str]:
    """The names of the contracts the run reports broken (its report wraps long lines)."""
    _, _, report = run.stdout.partition("Broken contracts")
    report = " ".join(report.split())
    return [name for name in CONTRACTS if name in report]


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    shutil.copytree(ROOT / "service", tmp_path / "service", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def test_the_rules_hold(tree: Path) -> None:
    run = lint(tree)
    assert run.returncode == 0, run.stdout[-3000:]
    assert f"{len(CONTRACTS)} kept, 0 broken" in run.stdout
    assert len(CONTRACTS) == 7 and sum(name.startswith(LAYERS) for name in CONTRACTS) == 1


@pytest.mark.parametrize(
    ("module", "line", "rules"),
    [
        ("tracking/base.py", "import service.wire.models", ["numerics never import"]),
        ("correlation/gls.py", "import zenoh", ["numerics never import", "the pipeline needs no"]),
        ("assessment/radar.py", "import fastapi", ["numerics never import", "the pipeline needs no"]),
        ("api/metrics.py", "import service.assessment.radar", ["transport and HTTP leave the numerics"]),
        ("api/metrics.py", "import service.correlation.umeyama", ["transport and HTTP leave the numerics"]),
        ("recording/assess.py", "import service.assessment.radar", ["transport and HTTP leave the numerics"]),
        ("cli/serve.py", "import service.tracking.base", ["transport and HTTP leave the numerics"]),
        ("wire/keys.py", "import service.geo", ["the wire imports no numerics", LAYERS]),
        ("engine.py", "import matplotlib", ["nothing in the runtime imports the lab"]),
        ("cli/serve.py", "import topofusion_lab.commands", ["nothing in the runtime imports the lab"]),
        ("asterix/bridge.py", "import zenoh", ["ASTERIX decoding, inputs and the bridge's rules"]),
        ("pipeline/decode.py", "import zenoh", ["the pipeline needs no Zenoh or HTTP"]),
        ("pipeline/feed.py", "import fastapi", ["the pipeline needs no Zenoh or HTTP"]),
        # each layer imports only from below (and siblings apart by `|` not from each other)
        ("pipeline/decode.py", "import service.engine", [LAYERS]),
        ("engine.py", "import service.state", [LAYERS]),
        ("engine.py", "import service.api.limits", [LAYERS]),
        ("state/content.py", "import service.transport.session", [LAYERS]),
        ("transport/session.py", "import service.api.limits", [LAYERS]),
        ("recording/keys.py", "import service.api.limits", [LAYERS]),
        ("api/limits.py", "import service.asterix.udp", [LAYERS]),
        ("asterix/udp.py", "import service.cli.common", [LAYERS, "ASTERIX decoding"]),
        ("tracking/base.py", "import service.correlation.base", [LAYERS]),
        ("correlation/gls.py", "import service.reference", [LAYERS]),
        ("fusion/members.py", "import service.pipeline.partition", [LAYERS]),
        ("config.py", "import service.engine", [LAYERS]),
        ("geo.py", "import service.wire.keys", [LAYERS, "numerics never import"]),
        ("columns.py", "import service.geo", [LAYERS]),
        ("evaluation/truth.py", "import service.correlation.base", [LAYERS]),
        # no algorithm may read the simulator's truth
        ("tracking/manager.py", "import service.evaluation.truth", ["numerics never import", LAYERS]),
        ("correlation/evidence.py", "import service.evaluation", ["numerics never import", LAYERS]),
    ],
)
def test_a_broken_rule_fails(tree: Path, module: str, line: str, rules: list[str]) -> None:
    path = tree / "service" / module
    path.write_text(path.read_text() + f"\n{line}  # noqa\n")
    run = lint(tree)
    assert run.returncode != 0
    # (a rule also breaks where the new import is one link of a chain: the pipeline imports the
    # numerics, the engine's stages import the engine's configuration, and so on)
    assert {next(n for n in CONTRACTS if n.startswith(r)) for r in rules} == set(broken(run)), run.stdout[
        -3000:
    ]


def test_a_module_without_a_layer_fails(tree: Path) -> None:
    (tree / "service" / "extra.py").write_text("import service.wire\n")
    run = lint(tree)
    assert run.returncode != 0
    assert broken(run) == [next(n for n in CONTRACTS if n.startswith(LAYERS))]
    assert "- service.extra" in run.stdout
