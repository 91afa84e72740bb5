"""Radar performance study: the live assessment (contract §5.3) against what was simulated.

``python -m topofusion_lab.evaluation.performance [--duration S] [--seeds N]`` runs scenarios of
radars with known detection probability, random errors, biases and Mode 3/A / Mode C error
rates, every aircraft reporting ADS-B with its Mode 3/A code and flight level, through the
service's :class:`~service.engine.Engine` (default configuration, in process), and prints per
radar the assessment's figures over the last window next to the simulated values:

* ``pd`` against the simulated ``pd`` (goal: within +-0.03);
* ``range_rms_m`` / ``azimuth_rms_deg`` against the simulated random sigmas, and ``rms_m``
  against the horizontal random error those sigmas give at the assessed plots' ranges,
  ``sqrt(s_r^2 + mean(rho^2) s_a^2)`` (goal: within 25 %);
* Mode 3/A and Mode C correctness against ``1 - error rate``.

Nothing of the service is tuned here; the assessment never reads the simulator's truth.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass, replace
from typing import Any

from service.engine import Engine
from service.wire.keys import Keys
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import AdsbSpec, RadarSpec, Scenario, generate

PREFIX = "fusion"
PD_GOAL = 0.03
RMS_GOAL = 0.25


def scenarios(duration_s: float) -> list[Scenario]:
    """The study's scenes: three radars of different quality; then a lone radar at low pd."""
    base = get_scenario("three-radar")
    a, b, c = base.radars
    mixed = replace(
        base,
        name="mixed-quality",
        radars=(
            replace(
                a,
                pd=0.90,
                identity=True,
                range_bias_m=300.0,
                azimuth_bias_deg=0.2,
                mode_3a_error=0.01,
                mode_c_error=0.02,
            ),
            replace(
                b,
                pd=0.97,
                identity=True,
                range_sigma_m=120.0,
                azimuth_sigma_deg=0.12,
                range_bias_m=-150.0,
                azimuth_bias_deg=-0.3,
                mode_3a_error=0.03,
                mode_c_error=0.05,
            ),
            replace(
                c,
                pd=0.99,
                identity=True,
                range_sigma_m=250.0,
                azimuth_sigma_deg=0.25,
                range_bias_m=500.0,
                azimuth_bias_deg=0.4,
            ),
        ),
        adsb=(AdsbSpec("ads-b", identity=True),),
        duration_s=duration_s,
    )
    lone = replace(
        base,
        name="lone-low-pd",
        radars=(
            replace(
                a,
                pd=0.80,
                identity=True,
                clutter_per_scan=40,
                range_bias_m=-400.0,
                azimuth_bias_deg=0.5,
                mode_c_error=0.1,
            ),
        ),
        adsb=(AdsbSpec("ads-b", identity=True, stride=2),),
        duration_s=duration_s,
    )
    return [mixed, lone]


def national(duration_s: float) -> Scenario:
    """The national network (12 radars of pd 0.90-0.95, 1 500 aircraft), every other aircraft
    equipped with ADS-B: the load the assessment is sized for."""
    base = get_scenario("national")
    return replace(
        base,
        name="national",
        duration_s=duration_s,
        adsb=(AdsbSpec("ads-b", identity=True, stride=2),),
    )


@dataclass
class Row:
    scenario: str
    seed: int
    radar: RadarSpec
    figures: dict[str, Any]
    horizontal_sigma_m: float | None


def run_one(sc: Scenario, seed: int) -> list[Row]:
    engine = Engine()
    keys = Keys(PREFIX)
    for m in generate(sc, seed):
        engine.ingest(keys.input(m.kind, m.radar_id), json.dumps(m.body).encode())
    engine.flush()
    view = engine.assessment.view
    rows = []
    for r in sc.radars:
        radar = engine.assessment.assessment.assessments.get(r.radar_id)
        sigma = None
        if radar is not None:
            w = radar.window_sums(engine.assessment.assessment.next_step - 1)  # type: ignore[operator]
            n = w[2]
            if n:
                mean_rho2 = w[8] / n
                sigma = math.sqrt(r.range_sigma_m**2 + mean_rho2 * math.radians(r.azimuth_sigma_deg) ** 2)
        rows.append(Row(sc.name, seed, r, view.of(r.radar_id), sigma))
    engine.close()
    return rows


def _ratio(est: float | None, sim: float) -> float | None:
    return None if est is None else est / sim - 1.0


def table(rows: list[Row]) -> tuple[str, bool]:
    head = (
        "| scene | seed | radar | aircraft | pd sim | pd est ± 1σ | Δpd | range σ sim / est | az σ sim / est"
        " | horiz. σ sim / rms est | median | uncorr. rms | Mode 3/A sim / est | Mode C sim / est | goals |"
    )
    lines = [head, "|" + "---|" * 15]
    all_ok = True
    for row in rows:
        f, r = row.figures, row.radar
        d, p = f["detection"], f["position"]
        dpd = None if d["pd"] is None else d["pd"] - r.pd
        rr = _ratio(p["range_rms_m"], r.range_sigma_m)
        ra = _ratio(p["azimuth_rms_deg"], r.azimuth_sigma_deg)
        rh = None if row.horizontal_sigma_m is None else _ratio(p["rms_m"], row.horizontal_sigma_m)
        ok = (
            dpd is not None
            and abs(dpd) <= PD_GOAL
            and all(x is not None and abs(x) <= RMS_GOAL for x in (rr, ra, rh))
        )
        all_ok &= ok

        def fmt(x: float | None, spec: str) -> str:
            return "–" if x is None else format(x, spec)

        lines.append(
            f"| {row.scenario} | {row.seed} | {r.radar_id} | {f['aircraft']} | {r.pd:.2f} "
            f"| {fmt(d['pd'], '.3f')} ± {fmt(d['pd_sigma'], '.3f')} | {fmt(dpd, '+.3f')} "
            f"| {r.range_sigma_m:.0f} / {fmt(p['range_rms_m'], '.0f')} m "
            f"| {r.azimuth_sigma_deg:.2f} / {fmt(p['azimuth_rms_deg'], '.3f')}° "
            f"| {fmt(row.horizontal_sigma_m, '.0f')} / {fmt(p['rms_m'], '.0f')} m "
            f"| {fmt(p['median_m'], '.0f')} m | {fmt(p['rms_uncorrected_m'], '.0f')} m "
            f"| {1 - r.mode_3a_error:.3f} / {fmt(f['mode_3a']['rate'], '.3f')} "
            f"| {1 - r.mode_c_error:.3f} / {fmt(f['mode_c']['rate'], '.3f')} | {'met' if ok else 'MISSED'} |"
        )
    return "\n".join(lines), all_ok


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=900.0, help="data seconds per run (default 900)")
    ap.add_argument("--seeds", type=int, default=2, help="runs per scene (default 2)")
    ap.add_argument(
        "--national",
        type=float,
        default=0.0,
        metavar="S",
        help="also the national network for S data seconds, one seed (default 0: not)",
    )
    args = ap.parse_args(argv)
    rows: list[Row] = []
    start = time.perf_counter()
    for sc in scenarios(args.duration):
        for seed in range(1, args.seeds + 1):
            rows += run_one(sc, seed)
    if args.national > 0:
        rows += run_one(national(args.national), 1)
    text, ok = table(rows)
    print(text)
    print(
        f"\n{len(rows)} radar runs in {time.perf_counter() - start:.0f} s; "
        f"goals (|Δpd| <= {PD_GOAL}, RMS within {RMS_GOAL:.0%}): {'all met' if ok else 'NOT all met'}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
