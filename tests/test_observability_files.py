"""deploy/prometheus and deploy/grafana stay true to what the service exposes.

``promtool check rules`` runs when ``promtool`` is on the PATH; otherwise (and always) the
rule file is checked here: its structure, its durations, balanced brackets, and that every
metric an expression or a dashboard query names is one the service exposes (from its
collector, as tests/test_contract_docs.py gets them) or a standard one (``up``,
``process_*``, ``python_*``).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.test_contract_docs import exposed_metrics

ROOT = Path(__file__).resolve().parents[1]
PROMETHEUS = ROOT / "deploy" / "prometheus"
ALERTS = PROMETHEUS / "alerts.yml"
SCRAPE = PROMETHEUS / "prometheus.yml"
DASHBOARD = ROOT / "deploy" / "grafana" / "topofusion-dashboard.json"
RUNBOOK = ROOT / "docs" / "operations" / "metrics.md"

#: Prometheus's duration syntax (units in decreasing order, each at most once).
DURATION = re.compile(r"^(?:\d+y)?(?:\d+w)?(?:\d+d)?(?:\d+h)?(?:\d+m)?(?:\d+s)?(?:\d+ms)?$")
#: Words of PromQL that are not metric names (operators, modifiers, aggregation clauses).
KEYWORDS = {
    "and",
    "or",
    "unless",
    "by",
    "without",
    "on",
    "ignoring",
    "group_left",
    "group_right",
    "bool",
    "offset",
    "inf",
    "nan",
}
IDENT = re.compile(r"[A-Za-z_:][A-Za-z0-9_:]*")
STANDARD = re.compile(r"^(up|process_\w+|python_\w+)$")


def exposed_series() -> set[str]:
    """Every sample name the service exposes (a histogram's ``_bucket``, ``_sum``, ``_count``)."""
    names = set()
    for name, kind in exposed_metrics().items():
        names.add(name)
        if kind == "histogram":
            names |= {f"{name}_bucket", f"{name}_sum", f"{name}_count"}
    return names


def metric_names(expr: str) -> set[str]:
    """The metric names a PromQL expression selects."""
    text = re.sub(r'"(?:[^"\\]|\\.)*"', '""', expr)  # strings (label values, templates) out
    text = re.sub(r"\{[^{}]*\}", " ", text)  # label matchers
    text = re.sub(r"\[[^\]]*\]", " ", text)  # range and subquery durations
    # label lists of aggregations and vector matching
    text = re.sub(r"\b(by|without|on|ignoring|group_left|group_right)\s*\([^()]*\)", " ", text)
    text = re.sub(r"\$\w+", " ", text)  # Grafana variables ($__rate_interval, $instance)
    names = set()
    for m in IDENT.finditer(text):
        rest = text[m.end() :].lstrip()
        word = m.group()
        if rest.startswith("(") or word.lower() in KEYWORDS:
            continue  # a function or aggregation, or an operator
        if re.fullmatch(r"\d+(?:\.\d+)?(?:e\d+)?", word):
            continue
        names.add(word)
    return names


def balanced(expr: str) -> bool:
    pairs = {")": "(", "]": "[", "}": "{"}
    stack: list[str] = []
    for ch in re.sub(r'"(?:[^"\\]|\\.)*"', '""', expr):
        if ch in "([{":
            stack.append(ch)
        elif ch in pairs and (not stack or stack.pop() != pairs[ch]):
            return False
    return not stack


def unknown_metrics(exprs: list[str], exposed: set[str]) -> list[str]:
    return sorted({n for e in exprs for n in metric_names(e) if n not in exposed and not STANDARD.match(n)})


def dashboard_panels(panels: list[dict[str, Any]]) -> Iterator[dict[str, Any]]:
    for panel in panels:
        yield panel
        yield from dashboard_panels(panel.get("panels", []))


@pytest.fixture(scope="module")
def rules() -> dict[str, Any]:
    doc = yaml.safe_load(ALERTS.read_text(encoding="utf-8"))
    assert isinstance(doc, dict)
    return doc


@pytest.fixture(scope="module")
def dashboard() -> dict[str, Any]:
    doc = json.loads(DASHBOARD.read_text(encoding="utf-8"))
    assert isinstance(doc, dict)
    return doc


@pytest.fixture(scope="module")
def exposed() -> set[str]:
    return exposed_series()


def alert_rules(rules: dict[str, Any]) -> list[dict[str, Any]]:
    return [r for g in rules["groups"] for r in g["rules"]]


@pytest.mark.skipif(shutil.which("promtool") is None, reason="promtool is not installed")
def test_promtool_accepts_the_rules() -> None:
    out = subprocess.run(["promtool", "check", "rules", str(ALERTS)], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_every_rule_is_a_complete_alert(rules: dict[str, Any]) -> None:
    assert rules["groups"]
    names = [g["name"] for g in rules["groups"]]
    assert len(names) == len(set(names))
    for group in rules["groups"]:
        assert set(group) <= {"name", "rules", "interval", "limit"}, group["name"]
        assert group["rules"], group["name"]
        for rule in group["rules"]:
            assert set(rule) <= {"alert", "expr", "for", "keep_firing_for", "labels", "annotations"}, rule
            assert rule["alert"] and isinstance(rule["expr"], str) and rule["expr"].strip(), rule
            assert rule["labels"]["severity"] in {"critical", "warning", "info"}, rule["alert"]
            assert rule["annotations"]["summary"], rule["alert"]
            assert DURATION.match(str(rule.get("for", "0s"))), rule["alert"]
            assert balanced(rule["expr"]), rule["alert"]
    alerts = [r["alert"] for r in alert_rules(rules)]
    assert len(alerts) == len(set(alerts))


def test_rules_name_only_exposed_metrics(rules: dict[str, Any], exposed: set[str]) -> None:
    exprs = [r["expr"] for r in alert_rules(rules)]
    assert unknown_metrics(exprs, exposed) == []


def test_the_rules_cover_what_the_issue_asks(rules: dict[str, Any]) -> None:
    """Down and not ready, radar silent or lagging, rejections, queue drops and depth,
    correlation p99 from the histogram, bias sigma and bias jumps."""
    used = {n for r in alert_rules(rules) for n in metric_names(r["expr"])}
    assert {
        "up",
        "topofusion_ready",
        "topofusion_radar_update_rate_hz",
        "topofusion_radar_data_lag_seconds",
        "topofusion_rejected_total",
        "topofusion_queue_dropped_total",
        "topofusion_queue_depth",
        "topofusion_queue_capacity",
        "topofusion_correlation_duration_seconds_bucket",
        "topofusion_bias_range_sigma_m",
        "topofusion_bias_range_m",
    } <= used
    assert any("histogram_quantile(0.99" in r["expr"] for r in alert_rules(rules))


def test_every_alert_has_its_runbook_entry(rules: dict[str, Any]) -> None:
    runbook = RUNBOOK.read_text(encoding="utf-8")
    assert [r["alert"] for r in alert_rules(rules) if r["alert"] not in runbook] == []


def test_scrape_config_sends_the_token_from_a_file_and_loads_the_rules() -> None:
    doc = yaml.safe_load(SCRAPE.read_text(encoding="utf-8"))
    assert all(DURATION.match(str(v)) for k, v in doc["global"].items() if k.endswith("_interval"))
    assert [(PROMETHEUS / f).is_file() for f in doc["rule_files"]] == [True]
    (job,) = [j for j in doc["scrape_configs"] if j["job_name"] == "topofusion"]
    assert job["metrics_path"] == "/metrics"
    assert job["authorization"]["type"] == "Bearer"
    assert job["authorization"]["credentials_file"]  # never the token itself in the file
    assert "credentials" not in job["authorization"]
    # the alerts and the dashboard select this job
    assert all('job="topofusion"' in r["expr"] for r in alert_rules(yaml.safe_load(ALERTS.read_text())))


def test_dashboard_panels_query_exposed_metrics(dashboard: dict[str, Any], exposed: set[str]) -> None:
    panels = [p for p in dashboard_panels(dashboard["panels"]) if p["type"] != "row"]
    assert panels
    exprs = []
    for panel in panels:
        assert panel["datasource"], panel["title"]
        assert panel["targets"], panel["title"]
        for target in panel["targets"]:
            assert target["expr"] and balanced(target["expr"]), panel["title"]
            exprs.append(target["expr"])
    assert unknown_metrics(exprs, exposed) == []
    ids = [p["id"] for p in dashboard_panels(dashboard["panels"])]
    assert len(ids) == len(set(ids))


def test_dashboard_shows_every_metric_family(dashboard: dict[str, Any], exposed: set[str]) -> None:
    """A panel for every family the service exposes, and the process's CPU and memory."""
    shown = {
        n
        for p in dashboard_panels(dashboard["panels"])
        for t in p.get("targets", [])
        for n in metric_names(t["expr"])
    }
    families = {n for n in exposed_metrics() if n.startswith("topofusion_")}
    missing = {
        f for f in families if f not in shown and not {f"{f}_bucket", f"{f}_sum", f"{f}_count"} & shown
    }
    assert missing == set()
    assert {"process_cpu_seconds_total", "process_resident_memory_bytes"} <= shown
    heatmaps = [p for p in dashboard_panels(dashboard["panels"]) if p["type"] == "heatmap"]
    assert any("_bucket" in t["expr"] for p in heatmaps for t in p["targets"])


def test_the_checks_catch_a_wrong_name(exposed: set[str]) -> None:
    assert metric_names('sum by (radar) (rate(topofusion_batches_total{job="x"}[5m])) > 0') == {
        "topofusion_batches_total"
    }
    assert metric_names("a / on (instance) group_left (radar) b or c > bool 1") == {"a", "b", "c"}
    assert unknown_metrics(['rate(topofusion_batch_total{job="topofusion"}[5m])'], exposed) == [
        "topofusion_batch_total"
    ]
    assert unknown_metrics(["up == 0", "rate(process_cpu_seconds_total[1m])"], exposed) == []
    assert not balanced("sum(rate(x[5m])")
    assert balanced('x{a="(("}')
