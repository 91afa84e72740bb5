"""The two distributions as built: the runtime wheel holds the service only, the lab its own part.

The runtime (root pyproject.toml) is what the container image installs (`COPY service`,
`pip install .`): no simulator, no evaluation, no matplotlib.  The lab (lab/pyproject.toml)
holds those and requires the runtime.  Both wheels are built from a copy of the checkout's
sources (its package discovery sees tests/, bench/ and lab/ too) without earlier build output,
which setuptools would otherwise reuse.  About 10 s: pip sets up isolated build environments.
"""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
import sys
import zipfile
from collections.abc import Iterator
from email.message import Message
from email.parser import Parser
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAB_PACKAGE = "topofusion_lab"


def _metadata(wheel: zipfile.ZipFile) -> Message:
    name = next(n for n in wheel.namelist() if n.endswith(".dist-info/METADATA"))
    return Parser().parsestr(wheel.read(name).decode())


def _requirement_names(meta: Message) -> set[str]:
    return {re.split(r"[\s;<>=!~\[(]", r, maxsplit=1)[0].lower() for r in meta.get_all("Requires-Dist") or []}


def _text(wheel: zipfile.ZipFile, name: str) -> str:
    return wheel.read(name).decode() if name.endswith(".py") else ""


def _top_level(wheel: zipfile.ZipFile) -> set[str]:
    return {n.split("/", 1)[0] for n in wheel.namelist() if not n.split("/", 1)[0].endswith(".dist-info")}


#: Not part of a checkout's sources: virtual environments, caches and earlier build output.
_NOT_SOURCES = shutil.ignore_patterns(
    ".git", "build", "dist", "*.egg-info", "__pycache__", "*.pyc", ".*_cache", ".hypothesis", ".benchmarks"
)


def _copy_ignore(folder: str, names: list[str]) -> set[str]:
    venvs = {n for n in names if (Path(folder) / n / "pyvenv.cfg").is_file()}
    return set(_NOT_SOURCES(folder, names)) | venvs


@pytest.fixture(scope="module")
def wheels(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[dict[str, zipfile.ZipFile], str]]:
    """``{distribution: wheel}`` for the runtime and the lab, and pip's verbose build output."""
    tmp = tmp_path_factory.mktemp("wheels")
    checkout = tmp / "checkout"
    shutil.copytree(ROOT, checkout, ignore=_copy_ignore)
    out = tmp / "dist"
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "-v",
            "--no-deps",
            "-w",
            str(out),
            str(checkout),
            str(checkout / "lab"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-4000:]
    built = {w.name.split("-", 1)[0]: zipfile.ZipFile(w) for w in out.glob("*.whl")}
    try:
        assert set(built) == {"topofusion", "topofusion_lab"}, sorted(built)
        yield built, res.stdout + res.stderr
    finally:
        for wheel in built.values():
            wheel.close()


def test_runtime_wheel_has_no_lab_and_no_matplotlib(wheels: tuple[dict[str, zipfile.ZipFile], str]) -> None:
    wheel = wheels[0]["topofusion"]
    assert _top_level(wheel) == {"service"}
    names = wheel.namelist()
    # no lab module under the runtime's name (the lab's modules were the runtime's once: its
    # scenarios, its evaluation studies, its scenario publisher)
    lab_modules = {
        n.partition("/")[2]
        for n in wheels[0]["topofusion_lab"].namelist()
        if n.endswith(".py") and not n.endswith("__init__.py")
    }
    lab_like = [
        n
        for n in names
        if n.partition("/")[2] in lab_modules or "/scenarios/" in n or "publish_scenario" in _text(wheel, n)
    ]
    assert not lab_like, lab_like
    meta = _metadata(wheel)
    assert "matplotlib" not in _requirement_names(meta)
    assert meta["License-Expression"] == "Apache-2.0"
    # no runtime module refers to matplotlib; only the CLI's command groups name the lab (the
    # line its commands print where it is not installed)
    for name in names:
        if name.endswith(".py"):
            text = wheel.read(name).decode()
            assert "matplotlib" not in text, name
            if LAB_PACKAGE in text:
                assert name == "service/cli/groups.py", name
    # the console script, and no entry point of the group the lab adds its commands to
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert wheel.read(entry_points).decode().split() == [
        "[console_scripts]",
        "topofusion",
        "=",
        "service.cli:main",
    ]


def test_lab_wheel_holds_the_lab_and_requires_the_runtime(
    wheels: tuple[dict[str, zipfile.ZipFile], str],
) -> None:
    wheel = wheels[0]["topofusion_lab"]
    assert _top_level(wheel) == {LAB_PACKAGE}
    names = set(wheel.namelist())
    for module in (
        "scenarios/simulator.py",
        "scenarios/catalog.py",
        "publisher.py",
        "evaluation/correlation.py",
    ):
        assert f"{LAB_PACKAGE}/{module}" in names, module
    # its commands (demo, simulate, evaluate), for the runtime's command line to find
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert wheel.read(entry_points).decode().split() == [
        "[topofusion.commands]",
        "lab",
        "=",
        "topofusion_lab.commands:register",
    ]
    meta = _metadata(wheel)
    assert {"topofusion", "matplotlib"} <= _requirement_names(meta)
    assert meta["License-Expression"] == "Apache-2.0"


def test_builds_are_free_of_setuptools_deprecations(wheels: tuple[dict[str, zipfile.ZipFile], str]) -> None:
    """E.g. the licence as a TOML table, which setuptools deprecates in favour of an SPDX string."""
    warnings = [ln for ln in wheels[1].splitlines() if re.search(r"(Deprecation|BuildBackend)Warning", ln)]
    assert not warnings, warnings


def test_the_runtime_never_imports_the_lab() -> None:
    """Nothing in the runtime imports the lab (its commands come through an entry point) or
    matplotlib."""
    for path in sorted((ROOT / "service").rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                modules = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                modules = [node.module]
            else:
                continue
            for module in modules:
                where = f"{path.relative_to(ROOT)}:{node.lineno}"
                assert module.partition(".")[0] not in ("matplotlib", LAB_PACKAGE), where
