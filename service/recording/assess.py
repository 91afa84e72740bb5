"""``topofusion assess RECORDING.mcap --out DIR``: the radars' performance over a recording.

The recording's inputs go through an engine in this process exactly as ``replay --offline``
feeds them (:func:`~service.recording.offline.replay_offline`: data-time order, the running
service's code path), so its performance assessment (:mod:`service.assessment`, contract §5.3)
measures every radar against the ADS-B / AIS references paired with it.  Written:

* ``DIR/report.json``: per radar the ``RadarPerformance`` over the whole recording
  (``performance``) and over the last window as the live service would answer it
  (``last_window``), detection against range and azimuth, error histograms, the bias terms
  over time with their 1-sigma, and the Mode 3/A codes checked;
* ``DIR/report.html``: the same as one self-contained page (inline SVG charts drawn here, no
  script, nothing loaded from anywhere).
"""

from __future__ import annotations

import argparse
import html
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from service.recording.offline import replay_offline
from service.recording.replay import ReplayOptions


def add_assess_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "file", metavar="RECORDING.mcap", help="recording holding radar plots and ADS-B / AIS"
    )
    parser.add_argument(
        "--out", metavar="DIR", required=True, help="directory for report.html and report.json"
    )
    parser.add_argument("--sites", metavar="FILE", help="radar sites (JSON) when the recording lacks them")
    parser.add_argument("--config", metavar="FILE", help="engine configuration file (TOML, YAML, JSON)")


def assess_main(args: argparse.Namespace) -> int:
    """Run the assessment over ``args.file``; 2 with a clear message on an unusable file."""
    from service.engine import Engine
    from service.recording.reader import RecordingError
    from service.settings import Settings, engine_config

    overrides = {k: v for k, v in (("sites", args.sites), ("config", args.config)) if v is not None}
    settings = Settings(**overrides)
    prefix = str(getattr(args, "prefix", None) or settings.prefix)
    engine = Engine(replace(engine_config(settings), prefix=prefix))
    try:
        result = replay_offline(args.file, engine, prefix, ReplayOptions(speed=0))
    except RecordingError as exc:
        print(f"topofusion assess: {exc}", file=sys.stderr)
        return 2
    finally:
        engine.close()
    report = build_report(engine.assessment.assessment, str(args.file), _registration(engine))
    report["replay"] = {"messages": result.messages, "plots": result.plots, "rejected": result.rejected}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(report, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    (out / "report.html").write_text(render_html(report), encoding="utf-8")
    radars = report["radars"]
    print(
        f"assessed {len(radars)} radar(s) of {args.file} against "
        f"{', '.join(report['references']) or 'no reference'} -> {out}/report.html, {out}/report.json",
        file=sys.stderr,
    )
    for r in radars:
        p = r["performance"]
        print(f"  {p['radar_id']}: {_summary(p)}", file=sys.stderr)
    if result.damage:
        print(f"WARNING: {result.damage}; assessed what it holds up to there", file=sys.stderr)
    return 0


def _summary(p: dict[str, Any]) -> str:
    d, pos = p["detection"], p["position"]
    return (
        f"pd {_fmt(d['pd'], '.3f')} ({d['detected']}/{d['expected']}), rms {_fmt(pos['rms_m'], '.0f')} m, "
        f"Mode 3/A {_fmt(p['mode_3a']['rate'], '.3f')}, Mode C {_fmt(p['mode_c']['rate'], '.3f')}"
    )


def _fmt(x: float | None, spec: str) -> str:
    return "–" if x is None else format(x, spec)


# -- the report's data ----------------------------------------------------------------------
#: The registration model's terms charted per radar: (``BiasEstimate`` field, its sigma, title, unit).
REGISTRATION_TERMS = (
    ("range_bias_m", "range_bias_sigma_m", "Registration: range offset", "m"),
    ("range_gain_ppm", "range_gain_sigma_ppm", "Registration: range gain", "ppm"),
    ("azimuth_bias_deg", "azimuth_bias_sigma_deg", "Registration: azimuth offset", "deg"),
    ("time_bias_s", "time_bias_sigma_s", "Registration: time-stamp bias", "s"),
)


def _registration(engine: Any) -> dict[str, list[dict[str, Any]]]:
    """Each radar's joint bias estimates (contract §5.2) over the recording, oldest first: the
    correlation stage's history of solves (this process runs it in process)."""
    stage = getattr(engine.correlation, "stage", None)
    out: dict[str, list[dict[str, Any]]] = {}
    for time_s, biases in getattr(stage, "bias_history", ()):
        for b in biases:
            out.setdefault(b["radar_id"], []).append({**b, "time_s": time_s})
    return out


def build_report(
    assessment: Any, recording: str, registration: dict[str, list[dict[str, Any]]] | None = None
) -> dict[str, Any]:
    """The report of an :class:`~service.assessment.Assessment` that has seen a whole recording
    (``registration``: each radar's joint bias estimates over it, :func:`_registration`)."""
    p = assessment.params
    radars = []
    for radar_id, radar in sorted(assessment.assessments.items()):
        series = list(radar.bias_series)
        start = series[0][0] if series else None
        end = assessment.view.figures.get(radar_id, {}).get("time_s")
        span = (end - start) if (start is not None and end is not None) else 0.0
        codes = sorted(radar.mode_3a_codes.items(), key=lambda kv: (-kv[1][0], kv[0]))
        radars.append(
            {
                "performance": assessment.whole_run(radar_id, end, max(span, 0.0)),
                "last_window": assessment.view.of(radar_id),
                **radar.histograms(),
                "bias_series": [
                    {
                        "time_s": t,
                        "range_bias_m": round(br, 1),
                        "range_bias_sigma_m": round(sr, 1),
                        "azimuth_bias_deg": round(ba, 4),
                        "azimuth_bias_sigma_deg": round(sa, 4),
                    }
                    for t, br, sr, ba, sa in series
                ],
                "mode_3a_codes": [{"code": c, "checked": n, "correct": k} for c, (n, k) in codes[:50]],
                "registration": (registration or {}).get(radar_id, []),
            }
        )
    req = p.requirements
    return {
        "recording": recording,
        "window_s": p.window_s,
        "references": sorted({"ads-b" if k == "adsb" else k for k in assessment.kinds.values()}),
        "requirements": {"pd_min": req.pd_min, "mode_3a_min": req.mode_3a_min, "mode_c_min": req.mode_c_min},
        "radars": radars,
    }


# -- HTML -----------------------------------------------------------------------------------
_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:24px;color:#1d2733;
background:#fafbfc}
h1{font-size:22px;margin:0 0 4px} h2{font-size:18px;margin:28px 0 8px;border-bottom:1px solid #ccd}
h3{font-size:14px;margin:14px 0 4px;color:#44505c}
table{border-collapse:collapse;font-size:13px;margin:6px 0}
td,th{border:1px solid #d5dbe1;padding:3px 8px;text-align:right}
th{background:#eef1f4} td:first-child,th:first-child{text-align:left}
.pass{color:#0b7a2a;font-weight:600} .fail{color:#b3261e;font-weight:600} .none{color:#888}
.grid{display:flex;flex-wrap:wrap;gap:14px}
.card{background:#fff;border:1px solid #dde2e8;border-radius:6px;padding:8px}
.muted{color:#66707a;font-size:12px} svg text{font-size:10px;fill:#44505c}
"""


def _e(x: object) -> str:
    return html.escape(str(x))


def _verdict(v: bool | None) -> str:
    if v is None:
        return '<span class="none">no data</span>'
    return '<span class="pass">met</span>' if v else '<span class="fail">NOT met</span>'


def _bars(
    title: str,
    labels: Sequence[float],
    values: Sequence[float | None],
    counts: Sequence[int],
    unit: str,
    vmax: float | None = None,
    line: float | None = None,
) -> str:
    """A bar chart (inline SVG) of ``values`` per ``labels`` (None: no bar); ``counts`` in the
    tooltips; ``line`` a horizontal requirement line."""
    w, h, left, bottom, top = 460, 170, 40, 22, 8
    n = max(len(values), 1)
    vals = [v for v in values if v is not None]
    top_v: float = vmax if vmax is not None else (max(vals) if vals else 1.0) or 1.0
    bw = (w - left - 8) / n
    parts = [f'<svg width="{w}" height="{h}" viewBox="0 0 {w} {h}" role="img" aria-label="{_e(title)}">']
    y0 = h - bottom
    scale = (y0 - top) / top_v
    for k in range(5):
        tick = top_v * k / 4
        y = y0 - tick * scale
        parts.append(f'<line x1="{left}" x2="{w - 8}" y1="{y:.1f}" y2="{y:.1f}" stroke="#e3e7eb"/>')
        parts.append(f'<text x="{left - 4}" y="{y + 3:.1f}" text-anchor="end">{tick:.3g}</text>')
    for i, (lab, v, c) in enumerate(zip(labels, values, counts, strict=True)):
        x = left + i * bw
        if v is not None:
            y = y0 - min(v, top_v) * scale
            parts.append(
                f'<rect x="{x + 0.5:.1f}" y="{y:.1f}" width="{max(bw - 1, 0.5):.1f}" height="{y0 - y:.1f}" '
                f'fill="#4a78b5"><title>{lab:g} {unit}: {v:.3g} ({c})</title></rect>'
            )
        if _round_tick(lab, labels):
            parts.append(f'<text x="{x:.1f}" y="{h - 8}" text-anchor="middle">{lab:g}</text>')
    if line is not None and line <= top_v:
        y = y0 - line * scale
        parts.append(
            f'<line x1="{left}" x2="{w - 8}" y1="{y:.1f}" y2="{y:.1f}" '
            'stroke="#b3261e" stroke-dasharray="4 3"/>'
        )
    parts.append("</svg>")
    return f'<div class="card"><h3>{_e(title)} ({_e(unit)})</h3>{"".join(parts)}</div>'


def _round_tick(value: float, labels: Sequence[float]) -> bool:
    """Whether a bar's left edge ``value`` is on a round step that gives about six labels."""
    if len(labels) < 2:
        return True
    span = abs(labels[-1] - labels[0]) or 1.0
    raw = span / 6
    step = min(
        (m * 10 ** math.floor(math.log10(raw)) for m in (1, 2, 2.5, 5, 10)), key=lambda x: abs(x - raw)
    )
    return abs(value / step - round(value / step)) < 1e-6


def _series(
    title: str, times: Sequence[float], values: Sequence[float], sigmas: Sequence[float], unit: str
) -> str:
    """A line over time with its 1-sigma band (inline SVG)."""
    w, h, left, bottom, top = 460, 170, 48, 22, 8
    if not times:
        return f'<div class="card"><h3>{_e(title)}</h3><p class="muted">no estimate yet</p></div>'
    step = max(1, len(times) // 400)  # at most about 400 points drawn
    t, v, s = list(times[::step]), list(values[::step]), list(sigmas[::step])
    lo = min(a - b for a, b in zip(v, s, strict=True))
    hi = max(a + b for a, b in zip(v, s, strict=True))
    if hi - lo < 1e-9:
        lo, hi = lo - 1, hi + 1
    t0, t1 = t[0], max(t[-1], t[0] + 1e-9)

    def xy(tt: float, vv: float) -> str:
        x = left + (tt - t0) / (t1 - t0) * (w - left - 8)
        y = (h - bottom) - (vv - lo) / (hi - lo) * (h - bottom - top)
        return f"{x:.1f},{y:.1f}"

    band = [xy(a, b + c) for a, b, c in zip(t, v, s, strict=True)]
    band += [xy(a, b - c) for a, b, c in reversed(list(zip(t, v, s, strict=True)))]
    parts = [f'<svg width="{w}" height="{h}" viewBox="0 0 {w} {h}" role="img" aria-label="{_e(title)}">']
    for k in range(5):
        vv = lo + (hi - lo) * k / 4
        y = (h - bottom) - (vv - lo) / (hi - lo) * (h - bottom - top)
        parts.append(f'<line x1="{left}" x2="{w - 8}" y1="{y:.1f}" y2="{y:.1f}" stroke="#e3e7eb"/>')
        parts.append(f'<text x="{left - 4}" y="{y + 3:.1f}" text-anchor="end">{vv:.3g}</text>')
    parts.append(f'<polygon points="{" ".join(band)}" fill="#4a78b5" fill-opacity="0.2" stroke="none"/>')
    line = " ".join(xy(a, b) for a, b in zip(t, v, strict=True))
    parts.append(f'<polyline points="{line}" fill="none" stroke="#234d85" stroke-width="1.5"/>')
    parts.append(f'<text x="{left}" y="{h - 8}">+0 s</text>')
    parts.append(
        f'<text x="{w - 8}" y="{h - 8}" text-anchor="end">+{t1 - t0:.0f} s ({_e(unit)})</text></svg>'
    )
    return f'<div class="card"><h3>{_e(title)}</h3>{"".join(parts)}</div>'


def _ratios(expected: Sequence[int], detected: Sequence[int]) -> list[float | None]:
    return [d / e if e else None for e, d in zip(expected, detected, strict=True)]


def _trim(values: Sequence[Any]) -> int:
    """How many leading bins to draw: up to the last that has data (at least one)."""
    last = max((i for i, v in enumerate(values) if v), default=0)
    return last + 1


def _performance_table(p: dict[str, Any], title: str) -> str:
    d, pos, m3a, mc, req, ver = (
        p["detection"],
        p["position"],
        p["mode_3a"],
        p["mode_c"],
        p["requirements"],
        p["verdict"],
    )
    rows = [
        (
            "Detection probability",
            f"{_fmt(d['pd'], '.4f')} ± {_fmt(d['pd_sigma'], '.4f')}",
            f"{d['detected']} / {d['expected']} scans",
            f"≥ {req['pd_min']}",
            _verdict(ver["pd"]),
        ),
        (
            "Mode 3/A correct",
            _fmt(m3a["rate"], ".4f"),
            f"{m3a['correct']} / {m3a['checked']} plots",
            f"≥ {req['mode_3a_min']}",
            _verdict(ver["mode_3a"]),
        ),
        (
            "Mode C correct (200 ft)",
            _fmt(mc["rate"], ".4f"),
            f"{mc['correct']} / {mc['checked']} plots",
            f"≥ {req['mode_c_min']}",
            _verdict(ver["mode_c"]),
        ),
        (
            "Horizontal RMS, biases compensated",
            f"{_fmt(pos['rms_m'], '.1f')} m",
            f"{pos['plots']} plots",
            "",
            "",
        ),
        ("Horizontal median, compensated", f"{_fmt(pos['median_m'], '.1f')} m", "", "", ""),
        ("Horizontal RMS, uncorrected", f"{_fmt(pos['rms_uncorrected_m'], '.1f')} m", "", "", ""),
        ("Range error RMS (about its mean)", f"{_fmt(pos['range_rms_m'], '.1f')} m", "", "", ""),
        ("Azimuth error RMS (about its mean)", f"{_fmt(pos['azimuth_rms_deg'], '.4f')}°", "", "", ""),
    ]
    body = "".join(
        "<tr>" + "".join(f"<td>{c if i == 4 else _e(c)}</td>" for i, c in enumerate(r)) + "</tr>"
        for r in rows
    )
    return (
        f"<h3>{_e(title)}</h3><table><tr><th>figure</th><th>value</th><th>behind it</th>"
        f"<th>requirement</th><th>verdict</th></tr>{body}</table>"
    )


def _radar_section(r: dict[str, Any]) -> str:
    p = r["performance"]
    rid = p["radar_id"]
    out = [f'<h2 id="radar-{_e(rid)}">Radar {_e(rid)}</h2>']
    out.append(
        f'<p class="muted">{p["aircraft"]} reference aircraft ({_e(", ".join(p["references"]))}); '
        f"data time span {p['window_s']:.0f} s.</p>"
    )
    out.append(_performance_table(p, "Over the whole recording"))
    out.append(
        _performance_table(r["last_window"], f"Over the last window ({r['last_window']['window_s']:.0f} s)")
    )
    charts = []
    dr = r["detection_vs_range"]
    n = _trim(dr["expected"])
    req = p["requirements"]["pd_min"]
    charts.append(
        _bars(
            "Detection probability vs range",
            [dr["bin_m"] / 1000 * i for i in range(n)],
            _ratios(dr["expected"][:n], dr["detected"][:n]),
            dr["expected"][:n],
            "km",
            1.0,
            req,
        )
    )
    da = r["detection_vs_azimuth"]
    charts.append(
        _bars(
            "Detection probability vs azimuth",
            [da["bin_deg"] * i for i in range(len(da["expected"]))],
            _ratios(da["expected"], da["detected"]),
            da["expected"],
            "deg",
            1.0,
            req,
        )
    )
    for key, title, unit in (
        ("range_error_m", "Range error (uncorrected)", "m"),
        ("azimuth_error_deg", "Azimuth error (uncorrected)", "deg"),
        ("horizontal_error_compensated_m", "Horizontal error, biases compensated", "m"),
    ):
        hist = r[key]
        edges, counts = hist["edges"], hist["counts"]
        if key == "horizontal_error_compensated_m":  # 5 m bins: shown as 50 m bins
            k = 10
            counts = [sum(counts[i : i + k]) for i in range(0, len(counts), k)]
            edges = edges[::k]
        charts.append(_bars(title, edges[: len(counts)], counts, counts, unit))
    series = r["bias_series"]
    times = [s["time_s"] for s in series]
    for field, sigma, name, unit in (
        ("range_bias_m", "range_bias_sigma_m", "Range", "m"),
        ("azimuth_bias_deg", "azimuth_bias_sigma_deg", "Azimuth", "deg"),
    ):
        charts.append(
            _series(
                f"{name} bias against the references, window fit (band: 1 sigma)",
                times,
                [s[field] for s in series],
                [s[sigma] for s in series],
                unit,
            )
        )
    history = r.get("registration", [])
    for field, sigma, title, unit in REGISTRATION_TERMS:
        solved = [h for h in history if h.get(field) is not None]
        charts.append(
            _series(
                f"{title} (band: 1 sigma)",
                [h["time_s"] for h in solved],
                [h[field] for h in solved],
                [h.get(sigma) or 0.0 for h in solved],
                unit,
            )
        )
    out.append(f'<div class="grid">{"".join(charts)}</div>')
    codes = r["mode_3a_codes"]
    if codes:
        rows = "".join(
            f"<tr><td>{_e(c['code'])}</td><td>{c['checked']}</td><td>{c['correct']}</td>"
            f"<td>{c['correct'] / c['checked']:.3f}</td></tr>"
            for c in codes[:20]
        )
        out.append(
            "<h3>Mode 3/A by reference code (most checked first)</h3><table><tr><th>code</th>"
            f"<th>checked</th><th>correct</th><th>rate</th></tr>{rows}</table>"
        )
    mc = p["mode_c"]
    out.append(
        "<h3>Mode C</h3><table><tr><th>checked</th><th>within 200 ft</th><th>off by more</th>"
        "<th>rate</th></tr>"
        f"<tr><td>{mc['checked']}</td><td>{mc['correct']}</td><td>{mc['checked'] - mc['correct']}</td>"
        f"<td>{_fmt(mc['rate'], '.4f')}</td></tr></table>"
    )
    return "".join(out)


def render_html(report: dict[str, Any]) -> str:
    """The report as one self-contained HTML page (no script, no external resource)."""
    radars = report["radars"]
    summary_rows = "".join(
        f'<tr><td><a href="#radar-{_e(p["radar_id"])}">{_e(p["radar_id"])}</a></td><td>{p["aircraft"]}</td>'
        f"<td>{_fmt(p['detection']['pd'], '.3f')}</td><td>{_verdict(p['verdict']['pd'])}</td>"
        f"<td>{_fmt(p['position']['rms_m'], '.0f')} m</td>"
        f"<td>{_fmt(p['mode_3a']['rate'], '.3f')}</td><td>{_verdict(p['verdict']['mode_3a'])}</td>"
        f"<td>{_fmt(p['mode_c']['rate'], '.3f')}</td><td>{_verdict(p['verdict']['mode_c'])}</td></tr>"
        for p in (r["performance"] for r in radars)
    )
    req = report["requirements"]
    body = [
        "<h1>Radar performance assessment</h1>",
        f'<p class="muted">Recording {_e(report["recording"])}; references: '
        f"{_e(', '.join(report['references']) or 'none')}; requirements: pd ≥ {req['pd_min']}, "
        f"Mode 3/A ≥ {req['mode_3a_min']}, Mode C ≥ {req['mode_c_min']} (topofusion assess; "
        "docs/assessment.md says how each figure is measured).</p>",
    ]
    if not radars:
        body.append(
            "<p><b>No radar could be assessed</b>: the recording holds no reference paired with a radar.</p>"
        )
    else:
        body.append(
            "<table><tr><th>radar</th><th>aircraft</th><th>pd</th><th>verdict</th><th>RMS</th>"
            "<th>Mode 3/A</th><th>verdict</th><th>Mode C</th><th>verdict</th></tr>"
            f"{summary_rows}</table>"
        )
        body += [_radar_section(r) for r in radars]
    return (
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        '<meta http-equiv="Content-Security-Policy" '
        "content=\"default-src 'none'; style-src 'unsafe-inline'\">"
        f"<title>Radar performance</title><style>{_CSS}</style></head><body>{''.join(body)}</body></html>\n"
    )
