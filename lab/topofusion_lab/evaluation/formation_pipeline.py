"""The ``formation`` scenario through the whole pipeline: plots -> trackers -> correlation.

Per seed, the scenario's messages (sites, then plot batches in data-time order, exactly the
bytes ``topofusion simulate`` publishes) are fed into a :class:`service.engine.Engine` in this
process, as ``topofusion replay --offline`` does (the engine code path of the running service;
no Zenoh), and ``flush`` at the end.  At a few data times during the run and at the end, the
engine's snapshot (what the service serves on ``/radars/{id}/tracks`` and ``/pairs``) is
scored with the simulator's truth: the ``truth_id`` each track carries for evaluation only
(the aircraft with the most plots in it), which no algorithm reads.

Per radar pair at a checkpoint:

* ``common``: aircraft that have a confirmed track on both radars;
* ``confirmed``: confirmed pairs in the pair set; ``gone``: those of them one of whose tracks
  is no longer in its radar's table (not judged);
* ``correct``: confirmed pairs whose two tracks follow the same aircraft; ``found``: aircraft
  of ``common`` with such a pair (``correct`` can exceed it only through duplicate tracks);
* ``false``: the other judged confirmed pairs (different aircraft, or a track on clutter).

Scores: every judged confirmed pair's published score (``PairSet`` ``score``) counted in the
bins of :data:`SCORE_BINS` with whether it is correct (``score_n``, ``score_right``), and the
sum of ``(score - correct)^2`` over them (``brier_sum``): the reliability of the scores through
the whole pipeline, trackers' mistakes included.

Rates: ``correct_pct = 100 found / common`` (the share of the common pairs the service has
confirmed right) and ``false_pct = 100 false / (confirmed - gone)``, each over all radar pairs
together (sums) and per radar pair.  Per radar, the tracking behind it: confirmed tracks,
aircraft with one, duplicate tracks and tracks on clutter.

Run: python -m topofusion_lab.evaluation.formation_pipeline --seeds 3 [--seed0 1]
     [--method svd-topology|gmm|nearest|...] [--spacing-m X] [--targets N] [--duration S]
     [--checkpoints K] [--json FILE]
Prints a table per method (a row per seed, then the mean) and per radar pair at the end;
progress on stderr.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from bisect import bisect_right
from collections import Counter
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from service.engine import Engine, EngineConfig, Snapshot
from service.pipeline.tracking_stage import TrackerFactory
from service.wire.keys import Keys
from service.wire.vocabulary import METHODS
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import Observer, Scenario, generate

SCENARIO = "formation"
#: Checkpoints during the run (besides the end), as fractions of the duration.
CHECKPOINTS = 4
#: Edges of the score bins of the reliability count (:func:`score_snapshot`); the last bin
#: holds 1.0 itself.
SCORE_BINS = (0.0, 0.5, 0.8, 0.9, 0.95, 0.99, 1.0)


def formation_scenario(
    targets: int | None = None, spacing_m: float | None = None, duration_s: float | None = None
) -> Scenario:
    """The catalog's ``formation`` with its size, lattice spacing or duration changed."""
    sc = get_scenario(SCENARIO)
    formation = sc.formation
    assert formation is not None
    if targets is not None:
        sc = replace(sc, targets=targets)
    if spacing_m is not None:
        sc = replace(sc, formation=replace(formation, spacing_m=spacing_m))
    if duration_s is not None:
        sc = replace(sc, duration_s=duration_s)
    return sc


# -- scoring (evaluation only: truth_id) ----------------------------------------------------------
def score_snapshot(snap: Snapshot, focus: Collection[str] | None = None) -> dict[str, Any]:
    """Pairs and tracks of one engine snapshot against the simulator's truth (see the module).
    ``focus``: only these aircraft are scored (a pair counts when either track is on one of
    them; None: every aircraft)."""
    truth_of: dict[str, dict[str, str | None]] = {}
    confirmed_truths: dict[str, set[str]] = {}
    radars: dict[str, dict[str, int]] = {}
    for rid, (_, table) in sorted(snap.tracks.items()):
        ids = [str(x) for x in table.track_id]
        truths = [None if x is None else str(x) for x in table.truth_id]
        truth_of[rid] = dict(zip(ids, truths, strict=True))
        conf = [t for t, c in zip(truths, table.confirmed, strict=True) if c]
        if focus is not None:
            conf = [t for t in conf if t is None or t in focus]
        per_aircraft = Counter(t for t in conf if t is not None)
        confirmed_truths[rid] = set(per_aircraft)
        radars[rid] = {
            "confirmed_tracks": len(conf),
            "aircraft": len(per_aircraft),
            "duplicates": sum(n - 1 for n in per_aircraft.values()),
            "clutter": conf.count(None),
        }
    pairs: dict[str, dict[str, int]] = {}
    score_n = [0] * (len(SCORE_BINS) - 1)
    score_right = [0] * (len(SCORE_BINS) - 1)
    brier = 0.0
    for view in snap.pair_views:
        a, b = view.radar_a, view.radar_b
        cols = view.columns
        common = confirmed_truths.get(a, set()) & confirmed_truths.get(b, set())
        confirmed = correct = false = gone = 0
        found: set[str] = set()
        for ta, tb, ok, score in zip(
            cols["track_a"], cols["track_b"], cols["confirmed"], cols["score"], strict=True
        ):
            if not ok:
                continue
            ka, kb = truth_of.get(a, {}), truth_of.get(b, {})
            there = str(ta) in ka and str(tb) in kb
            if there and focus is not None and ka[str(ta)] not in focus and kb[str(tb)] not in focus:
                continue
            confirmed += 1
            if not there:
                gone += 1
                continue
            wa, wb = ka[str(ta)], kb[str(tb)]
            right = wa is not None and wa == wb
            if right:
                correct += 1
                if wa in common:
                    found.add(wa)
            else:
                false += 1
            k = min(bisect_right(SCORE_BINS, float(score)) - 1, len(score_n) - 1)
            score_n[k] += 1
            score_right[k] += right
            brier += (float(score) - right) ** 2
        pairs[f"{a}-{b}"] = {
            "common": len(common),
            "confirmed": confirmed,
            "correct": correct,
            "found": len(found),
            "false": false,
            "gone": gone,
        }
    total = {
        k: sum(p[k] for p in pairs.values())
        for k in ("common", "confirmed", "correct", "found", "false", "gone")
    }
    scores = {"score_n": score_n, "score_right": score_right, "brier_sum": brier}
    return {"pairs": pairs, "total": total, "radars": radars, "scores": scores, **rates(total)}


def rates(counts: dict[str, int]) -> dict[str, float]:
    """``correct_pct`` and ``false_pct`` of a pair count (nan where undefined)."""
    judged = counts["confirmed"] - counts["gone"]
    return {
        "correct_pct": 100.0 * counts["found"] / counts["common"] if counts["common"] else float("nan"),
        "false_pct": 100.0 * counts["false"] / judged if judged else float("nan"),
    }


# -- the run ----------------------------------------------------------------------------------
def run_pipeline(
    sc: Scenario,
    seed: int,
    method: str = "svd-topology",
    at_s: Sequence[float] = (),
    config: EngineConfig | None = None,
    observe: Observer | None = None,
    tracker_factory: TrackerFactory | None = None,
    on_engine: Callable[[Engine], None] | None = None,
) -> Iterator[tuple[float, Snapshot, Engine]]:
    """Feed ``sc``'s messages (seed ``seed``) into a fresh engine; yields ``(data seconds since
    the start, snapshot, engine)`` once the stream has passed each of ``at_s`` and, last, after
    the whole stream and ``flush`` (at the scenario's duration).  ``observe`` is the
    simulator's truth observer (:func:`~topofusion_lab.scenarios.simulator.generate`);
    ``tracker_factory`` the engine's (None: the configuration's trackers); ``on_engine`` is
    given the engine before the first message."""
    engine = Engine(replace(config or EngineConfig(), method=method), tracker_factory)
    if on_engine is not None:
        on_engine(engine)
    keys = Keys(engine.config.prefix)
    pending = sorted(at_s)
    try:
        for m in generate(sc, seed, observe):
            elapsed = m.time_s - sc.start_time_s
            while pending and elapsed > pending[0]:
                yield pending.pop(0), engine.snapshot(), engine
            engine.ingest(keys.input(m.kind, m.radar_id), json.dumps(m.body).encode())
        engine.flush()
        yield (sc.duration_s or 0.0), engine.snapshot(), engine
    finally:
        engine.close()


def measure(
    seed: int,
    method: str = "svd-topology",
    targets: int | None = None,
    spacing_m: float | None = None,
    duration_s: float | None = None,
    checkpoints: int = CHECKPOINTS,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """One seeded run of the formation through the engine, scored at ``checkpoints`` data times
    spread over the run (the k-th at ``k / (checkpoints + 1)`` of it) and at the end.

    Returns the scenario's knobs, the wall time, and per checkpoint (``checkpoints``, the last
    one the end) the scores of :func:`score_snapshot` with its data time ``t_s``; ``final`` is
    the last of them."""
    sc = formation_scenario(targets, spacing_m, duration_s)
    assert sc.duration_s is not None and sc.formation is not None
    at = [sc.duration_s * k / (checkpoints + 1) for k in range(1, checkpoints + 1)]
    started = time.perf_counter()
    scored = []
    final: Snapshot | None = None
    for t, snap, _ in run_pipeline(sc, seed, method, at):
        s = {"t_s": t, **score_snapshot(snap)}
        scored.append(s)
        final = snap
        if progress:
            tot = s["total"]
            progress(
                f"  seed {seed} {method} t={t:4.0f}s: common {tot['common']}, confirmed {tot['confirmed']}, "
                f"correct {s['correct_pct']:.0f}%, false {s['false_pct']:.0f}% "
                f"({time.perf_counter() - started:.0f} s wall)"
            )
    assert final is not None
    truth = {r.radar_id: r for r in sc.radars}
    biases = {
        b["radar_id"]: {
            "range_error_m": b["range_bias_m"] - truth[b["radar_id"]].range_bias_m,
            "azimuth_error_deg": b["azimuth_bias_deg"] - truth[b["radar_id"]].azimuth_bias_deg,
        }
        for b in final.biases()
        if b["radar_id"] in truth
    }
    return {
        "seed": seed,
        "method": method,
        "targets": sc.targets,
        "spacing_m": sc.formation.spacing_m,
        "duration_s": sc.duration_s,
        "wall_s": time.perf_counter() - started,
        "checkpoints": scored,
        "final": scored[-1],
        "biases": biases,
    }


# -- the report ------------------------------------------------------------------------------
def _pct(x: float) -> str:
    return "  -" if np.isnan(x) else f"{x:3.0f}"


def _mean(xs: Sequence[float]) -> float:
    """Mean of the defined values (nan if none)."""
    defined = [x for x in xs if not np.isnan(x)]
    return float(np.mean(defined)) if defined else float("nan")


def _span(xs: Sequence[float]) -> str:
    defined = [x for x in xs if not np.isnan(x)]
    return f"{min(defined):.0f}-{max(defined):.0f}%" if defined else "-"


def report(results: list[dict[str, Any]], out: Callable[[str], None] = print) -> None:
    """A table per method: a row per seed, then the mean; then the final figures per radar pair."""
    for method in dict.fromkeys(r["method"] for r in results):
        rows = [r for r in results if r["method"] == method]
        first = rows[0]
        times = [c["t_s"] for c in first["checkpoints"]]
        out(
            f"\n{method}: formation of {first['targets']} aircraft, {first['spacing_m']:.0f} m lattice, "
            f"{first['duration_s']:.0f} s; correct % = common aircraft with a right confirmed pair, "
            "false % = wrong / judged confirmed pairs (all radar pairs together)"
        )
        head = "  seed  " + " ".join(f"t={t:4.0f}s cor/fal" for t in times)
        head += "  | end: common confirmed correct false gone | wall s"
        out(head)
        for r in rows:
            row = " ".join(f"      {_pct(c['correct_pct'])}/{_pct(c['false_pct'])}" for c in r["checkpoints"])
            tot = r["final"]["total"]
            out(
                f"  {r['seed']:4d}  {row}  | {tot['common']:10d} {tot['confirmed']:9d} {tot['correct']:7d} "
                f"{tot['false']:5d} {tot['gone']:4d} | {r['wall_s']:6.0f}"
            )
        means = [
            (
                _mean([r["checkpoints"][i]["correct_pct"] for r in rows]),
                _mean([r["checkpoints"][i]["false_pct"] for r in rows]),
            )
            for i in range(len(times))
        ]
        out("  mean  " + " ".join(f"      {_pct(c)}/{_pct(f)}" for c, f in means))
        finals = [r["final"] for r in rows]
        out(
            f"  end, over seeds: correct {_span([f['correct_pct'] for f in finals])} "
            f"(mean {means[-1][0]:.1f}%), false {_span([f['false_pct'] for f in finals])} "
            f"(mean {means[-1][1]:.1f}%)"
        )
        out("  per radar pair at the end (correct %/false %, common):")
        cells: list[str]
        for key in first["final"]["pairs"]:
            cells = []
            for r in rows:
                p = r["final"]["pairs"].get(key)
                if p is not None:
                    rr = rates(p)
                    cells.append(f"{_pct(rr['correct_pct'])}/{_pct(rr['false_pct'])} ({p['common']})")
            out(f"    {key:<8} " + "  ".join(cells))
        out("  tracking at the end per radar (aircraft with a confirmed track / duplicates / on clutter):")
        for rid in first["final"]["radars"]:
            cells = []
            for r in rows:
                x = r["final"]["radars"].get(rid)
                if x is not None:
                    cells.append(f"{x['aircraft']}/{x['duplicates']}/{x['clutter']}")
            out(f"    {rid:<8} " + "  ".join(cells) + f"   of {first['targets']} aircraft")
        out("  bias estimate errors at the end (range m, azimuth deg):")
        for rid in first["biases"]:
            cells = [
                f"{b['range_error_m']:+5.0f} {b['azimuth_error_deg']:+.3f}"
                for r in rows
                if (b := r["biases"].get(rid)) is not None
            ]
            out(f"    {rid:<8} " + "  ".join(cells))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=3, help="runs, seeds seed0 .. seed0+seeds-1 (default 3)")
    p.add_argument("--seed0", type=int, default=1, help="first seed (default 1)")
    p.add_argument(
        "--method",
        action="append",
        choices=METHODS,
        help="correlation method (repeatable; default svd-topology)",
    )
    p.add_argument("--spacing-m", type=float, help="lattice spacing (default the scenario's)")
    p.add_argument("--targets", type=int, help="aircraft in the formation (default the scenario's)")
    p.add_argument("--duration", type=float, help="data seconds (default the scenario's)")
    p.add_argument("--checkpoints", type=int, default=CHECKPOINTS, help="scorings before the end")
    p.add_argument("--json", type=Path, help="also write the results here")
    args = p.parse_args(argv)

    def progress(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    results = []
    for method in args.method or ["svd-topology"]:
        for seed in range(args.seed0, args.seed0 + args.seeds):
            progress(f"seed {seed} {method} ...")
            results.append(
                measure(seed, method, args.targets, args.spacing_m, args.duration, args.checkpoints, progress)
            )
    report(results)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
