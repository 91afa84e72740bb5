"""The committed evaluation pages say how to make them again, with a command a reader can run
here: `topofusion evaluate` writing to `docs/evaluation`, not to a folder of the machine that
ran it."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted((ROOT / "docs" / "evaluation").glob("*.md"))
MADE_BY = re.compile(r"_Made by `(topofusion evaluate[^`]*)`")


def test_every_study_page_names_the_command_that_makes_it_into_docs_evaluation() -> None:
    studies = [p for p in PAGES if p.name != "REPORT.md" and MADE_BY.search(p.read_text())]
    assert len(studies) >= 5, "the study pages carry their command"
    for page in studies:
        for command in MADE_BY.findall(page.read_text()):
            assert "--out docs/evaluation" in command, f"{page.name}: {command}"


def test_the_report_is_the_study_pages_put_together() -> None:
    report = (ROOT / "docs" / "evaluation" / "REPORT.md").read_text()
    for page in PAGES:
        if page.name != "REPORT.md" and MADE_BY.search(page.read_text()):
            assert page.read_text().strip() in report, f"REPORT.md lacks the current {page.name}"


def test_no_page_names_a_scratch_folder() -> None:
    for page in [*sorted((ROOT / "docs").rglob("*.md")), ROOT / "README.md"]:
        assert "/tmp/" not in page.read_text(), page.relative_to(ROOT)
