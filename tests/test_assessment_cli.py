"""``topofusion assess RECORDING.mcap --out DIR`` on a small recording: the JSON, a page that
loads nothing from anywhere, and the page in headless Chromium with no network (a screenshot).

Set ``ASSESS_SCREENSHOT=PATH.png`` to keep the screenshot."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from service.recording.writer import RecordingWriter
from service.wire.keys import Keys
from service.wire.models import RadarPerformance
from tests import browser

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    lab = pytest.importorskip("topofusion_lab.scenarios.simulator")
    from topofusion_lab.scenarios.catalog import get_scenario

    base = get_scenario("two-radar")
    a, b = base.radars
    sc = replace(
        base,
        duration_s=120.0,
        targets=20,
        radars=(replace(a, identity=True, pd=0.9, mode_c_error=0.05), replace(b, identity=True)),
        adsb=(lab.AdsbSpec("ads-b", identity=True),),
    )
    tmp = tmp_path_factory.mktemp("assess")
    rec = tmp / "small.mcap"
    keys = Keys("fusion")
    with RecordingWriter(rec, "fusion") as w:
        for m in lab.generate(sc, 2):
            w.write(keys.input(m.kind, m.radar_id), json.dumps(m.body).encode(), int(m.time_s * 1e9))
    out = tmp / "report"
    done = subprocess.run(
        [sys.executable, "-m", "service", "assess", str(rec), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert done.returncode == 0, done.stderr
    assert "assessed 2 radar(s)" in done.stderr
    return out


def test_the_json_holds_each_radar_s_performance_and_its_charts(report_dir: Path) -> None:
    report = json.loads((report_dir / "report.json").read_text())
    assert report["references"] == ["ads-b"]
    assert [r["performance"]["radar_id"] for r in report["radars"]] == ["A", "B"]
    a = report["radars"][0]
    perf = RadarPerformance.model_validate(a["performance"])
    RadarPerformance.model_validate(a["last_window"])
    assert perf.detection.pd is not None and abs(perf.detection.pd - 0.9) < 0.05
    assert perf.mode_c.rate is not None and abs(perf.mode_c.rate - 0.95) < 0.03
    assert perf.mode_3a.rate == 1.0
    dr = a["detection_vs_range"]
    assert sum(dr["expected"]) == perf.detection.expected and sum(dr["detected"]) == perf.detection.detected
    assert sum(a["range_error_m"]["counts"]) <= perf.position.plots
    assert a["bias_series"] and {"range_bias_m", "range_bias_sigma_m"} <= set(a["bias_series"][-1])
    # the registration model's terms over the recording (a joint solve every 30 s of data time)
    times = [h["time_s"] for h in a["registration"]]
    assert len(times) >= 2 and times == sorted(times)
    assert {"range_gain_ppm", "time_bias_s", "time_bias_sigma_s"} <= set(a["registration"][-1])
    assert "Registration: time-stamp bias" in (report_dir / "report.html").read_text()


def test_the_page_is_self_contained(report_dir: Path) -> None:
    page = (report_dir / "report.html").read_text()
    assert "<script" not in page and not re.search(r"(src|href)=\"(https?:)?//", page)
    assert page.count("<svg") >= 2 * 7 and "Radar A" in page and "NOT met" in page


@pytest.mark.skipif(not browser.available(), reason=f"{browser.CHROMIUM} is absent (.ci/run installs it)")
def test_the_page_renders_in_chromium_without_network(report_dir: Path, tmp_path: Path) -> None:
    with browser.Browser(width=1280, height=1000) as chromium:
        page = chromium.page()
        url = (report_dir / "report.html").as_uri()
        page.goto(url)
        assert page.requested_urls() == [url]
        assert page.console_errors() == []
        bars = page.evaluate("document.querySelectorAll('svg rect').length")
        assert bars > 50
        width = page.evaluate("document.querySelector('svg').getBoundingClientRect().width")
        assert width > 300
        shot = page.screenshot()
    assert shot[:8] == b"\x89PNG\r\n\x1a\n" and len(shot) > 20_000
    keep = os.environ.get("ASSESS_SCREENSHOT")
    (Path(keep) if keep else tmp_path / "report.png").write_bytes(shot)


def test_an_unusable_file_exits_2_saying_why(tmp_path: Path) -> None:
    bad = tmp_path / "not.mcap"
    bad.write_bytes(b"not an mcap file")
    done = subprocess.run(
        [sys.executable, "-m", "service", "assess", str(bad), "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert done.returncode == 2 and "assess" in done.stderr


def test_assess_runs_without_the_lab(report_dir: Path, tmp_path: Path) -> None:
    """``make demo``'s runtime is enough: the command never imports the lab (nor matplotlib)."""
    from tests.test_cli_lab import _finish, _without_lab

    proc = _without_lab(["assess", str(report_dir.parent / "small.mcap"), "--out", str(tmp_path / "r")])
    code, err, attempts = _finish(proc)
    assert (code, attempts) == (0, []), err
    assert json.loads((tmp_path / "r" / "report.json").read_text())["radars"]
