"""Fixed cost per input message: what one one-plot ``PlotBatch`` costs ``Engine.ingest``.

Question: does a one-plot batch cost about what its one plot is worth (target: at most 1 ms
per one-plot batch), and where does the rest go?  Prints figures, never asserts.

Input (generated before any clock starts; the simulator's cost is excluded): the
``three-radar`` scenario of the lab simulator for ``--duration`` data seconds (radars A, B, C,
built as ``tests/scenario_helpers.py``'s ``scenario_messages`` builds it), and a radar F whose
site is A's moved 0.5 deg north (as in ``tests/test_flood.py``) that sends one-plot batches
(seq 1, 2, ...) at ``--flood-rate`` per data second over the last ``--flood-s`` data seconds of
the stream, its site message just before its first batch.  F floods the end of the stream, not
all of it: the honest radars settle first (confirmed tracks and pairs after about 30 data
seconds), so F meets a working engine with correlation partners; and the run stays short, for
F's messages cost milliseconds each, more the longer F floods (below).  F's plots
(``--pattern``): ``flood``, the publisher of ``tests/test_flood.py`` (range 50 km, azimuth 7 deg
further at each plot, elevation 1 deg: the same 360 places every 0.72 s, which become a few
hundred stationary tracks after about 8 data seconds of flood, longer than the default), or
``clutter`` (uniformly random places).

Cases, side by side in one run, interleaved (1, 2, 3, 1p, 2p, 3p, 1, 2, ... with ``--repeat``)
because the machine is noisy; min and median over the repeats:

1. the honest stream through ``Engine()`` in this process: ms per message and per plot;
2. the same stream with F's messages interleaved in data-time order: ms per F message, the
   time with F minus the time without, over F's message count.  F's own calls are cheap (F's
   clock runs ahead of the honest ones, so the sequencer holds its batches): F's batches are
   processed by the honest call that moves the watermark past them, 250 at a time;
3. F's messages alone through an engine that holds only F (no correlation partners): each F
   call processes its own batch.  Also per data second of the flood: ms per F message, F's
   window plots and tracks; and the median time of F's calls by F's window plots after them
   (bins 0-100, 100-250, ...): the first bin, a nearly empty window, is the fixed cost of a
   one-plot message, the others show how it grows with the window;
1p-3p. the same with ``Engine(correlation_process=True)``, as the service runs it: correlation
   in a child process.  The clock starts once the child answers (its start-up is excluded)
   and stops once ``engine.answers_pending`` is false (``engine.poll()`` until then); the engine
   is closed after the clock.

No case calls ``flush`` or ``snapshot``: the clock covers ``ingest`` calls (and, 1p-3p, the wait
for the last answers).  Outputs are built as ``Outgoing`` objects whose payloads are encoded only
when a transport reads them; nobody reads them here (with subscribers on F's tracks the service
would also encode one ``TrackBatch`` of all of F's tracks per F message).

With ``--profile`` (the default), case 2 in process once more, its messages reordered so that
the profile holds F's work only: each F message comes after the honest batches of the 0.5 s
period it falls in (the honest clocks are then ahead, so each F call releases and processes its
own batch), and the profiler is on during F's ``ingest`` calls only.  The sequencer releases the
same batches in the same data-time order as in case 2, and every call makes the same release
pass, so this is F's work in case 2 (the run prints its wall time, unprofiled, next to case
2's).  What else falls into F's calls: the honest batches of the flood's data seconds, which F's
calls release; their whole cost is case 1's over those seconds, printed as a share.  Printed:
the top ``--top`` functions by cumulative time, and a breakdown per F message in groups: decode
(pydantic parse, numpy columns), sequencer (check, accept, release), tracking
(``TrackingStage.update``), correlation (``Engine._correlate``: the merger's release, the
runner, the stage), publication (``Engine._results``: the outputs built), snapshot
(``Engine.snapshot``; none here) and the rest (the engine's own code, the profiler), each with
the functions inside it that matter; and the share that grows with the window.  The shares are
the profile's (cProfile slows small calls more than big ones); the conclusion applies them to
the unprofiled case-2 time.

Run (about 75 s on 2 cores with the defaults):
    PYTHONPATH=. .venv/bin/python bench/bench_message_cost.py [--duration 40] [--flood-s 3]
        [--flood-rate 500] [--pattern flood|clutter] [--repeat 3] [--profile|--no-profile]
        [--top 25] [--seed 1]
"""

from __future__ import annotations

import argparse
import cProfile
import gc
import itertools
import json
import pstats
import sys
import time
from dataclasses import dataclass, field, replace

import numpy as np

from service.engine import Engine
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import wire_messages

Stream = list[tuple[str, bytes]]

SCENARIO = "three-radar"
#: The flooding radar, its keys, and how far north of radar A its site is (as tests/test_flood.py).
FLOODER = "F"
F_SITE_KEY = f"fusion/radar/{FLOODER}/site"
F_PLOTS_KEY = f"fusion/radar/{FLOODER}/plots"
F_NORTH_DEG = 0.5
#: The per-message target (ms).
TARGET_MS = 1.0
#: Sleep between two polls while waiting for the correlation process's last answers (s).
POLL_S = 0.0002


# -- the input -----------------------------------------------------------------------------
def honest_stream(duration_s: float, seed: int) -> Stream:
    """The scenario's sites and batches in data-time order (as tests/scenario_helpers.py)."""
    sc = replace(get_scenario(SCENARIO), duration_s=duration_s)
    return list(wire_messages(sc, seed))


def batch_time(key: str, payload: bytes) -> float | None:
    return float(json.loads(payload)["time_s"]) if key.endswith("/plots") else None


def f_site(honest: Stream) -> bytes:
    site_a = json.loads(next(p for k, p in honest if k == "fusion/radar/A/site"))
    site = {**site_a, "radar_id": FLOODER, "latitude_deg": site_a["latitude_deg"] + F_NORTH_DEG}
    return json.dumps(site).encode()


def f_batches(start_s: float, n: int, rate: float, pattern: str, seed: int) -> list[tuple[float, bytes]]:
    """F's one-plot batches: ``(data time, payload)``, ``n`` of them from ``start_s`` on."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        t = round(start_s + i / rate, 4)
        if pattern == "flood":  # tests/test_flood.py's publisher
            r, az, el = 5e4, (i * 7.0) % 360.0, 1.0
        else:
            r, az, el = rng.uniform(5e3, 2e5), rng.uniform(0.0, 360.0), rng.uniform(0.2, 6.0)
        plots = {
            "time_s": [t],
            "range_m": [round(float(r), 2)],
            "azimuth_deg": [round(float(az), 5)],
            "elevation_deg": [round(float(el), 5)],
        }
        body = {"radar_id": FLOODER, "seq": i + 1, "time_s": t, "plots": plots}
        out.append((t, json.dumps(body).encode()))
    return out


@dataclass
class Streams:
    honest: Stream
    with_f: Stream
    f_alone: Stream
    honest_plots: int
    f_count: int
    flood_start_s: float
    end_s: float
    #: Index in ``honest`` of its first message after the flood's start.
    honest_flood_from: int = 0
    #: Indices in ``f_alone`` of F's last batch of each data second of the flood.
    f_seconds: list[int] = field(default_factory=list)
    #: ``with_f`` in the profile's order: F's messages after the honest ones of the same data time.
    f_after: Stream = field(default_factory=list)


def build(args: argparse.Namespace) -> Streams:
    honest = honest_stream(args.duration, args.seed)
    times = [batch_time(k, p) for k, p in honest]
    end_s = max(t for t in times if t is not None)
    n = round(args.flood_s * args.flood_rate)
    start_s = end_s - n / args.flood_rate
    flood = f_batches(start_s, n, args.flood_rate, args.pattern, args.seed)
    site = f_site(honest)
    # data-time order; at equal times the honest batch first (a site stays before what follows it)
    entries = []
    last = -np.inf
    for i, ((key, payload), t) in enumerate(zip(honest, times, strict=True)):
        last = t if t is not None else last
        entries.append((last, 0, i, key, payload))
    entries += [(t, 1, i, F_PLOTS_KEY, payload) for i, (t, payload) in enumerate(flood)]
    entries.sort(key=lambda e: e[:3])
    first_f = next(j for j, e in enumerate(entries) if e[1] == 1)
    with_f = [(key, payload) for *_, key, payload in entries]
    with_f.insert(first_f, (F_SITE_KEY, site))  # F's site just before its first batch
    f_alone = [(F_SITE_KEY, site)] + [(F_PLOTS_KEY, p) for _, p in flood]
    per_s = max(1, round(args.flood_rate))
    seconds = list(range(per_s, len(f_alone), per_s))  # index of the F message ending each second
    if not seconds or seconds[-1] != len(f_alone) - 1:
        seconds.append(len(f_alone) - 1)
    plots = sum(len(json.loads(p)["plots"]["time_s"]) for k, p in honest if k.endswith("/plots"))
    flood_from = next(i for i, t in enumerate(times) if t is not None and t > start_s)
    return Streams(honest, with_f, f_alone, plots, n, start_s, end_s, flood_from, seconds, f_after(with_f))


def f_after(with_f: Stream) -> Stream:
    """``with_f`` with each F message moved after the honest batches of the data time that
    ends its honest batch period (the first honest batch time at or after its own), so that each
    F call releases F's own batch (the honest clocks are ahead) instead of the next honest
    call releasing a period's worth of them.  The sequencer releases the same batches in the
    same data-time order either way."""
    times = [batch_time(k, p) for k, p in with_f]
    is_f = [k.startswith(f"fusion/radar/{FLOODER}/") for k, _ in with_f]
    grid = np.unique([t for t, f in zip(times, is_f, strict=True) if t is not None and not f])
    order = []
    last = -np.inf
    for i, (t, f) in enumerate(zip(times, is_f, strict=True)):
        if not f:
            last = t if t is not None else last
            order.append((last, 0, i))
        else:
            t_f = t if t is not None else next(x for x in times[i:] if x is not None)  # (F's site)
            j = int(np.searchsorted(grid, t_f, side="left"))
            order.append((float(grid[j]) if j < len(grid) else np.inf, 1, i))
    return [with_f[i] for *_, i in sorted(order)]


# -- one run -------------------------------------------------------------------------------
@dataclass
class SecondRow:
    """At the end of one data second of F's flood (case 3, in process)."""

    wall_s: float
    messages: int
    window_plots: int
    tracks: int
    confirmed: int


@dataclass
class Run:
    wall_s: float
    f_calls_s: float  # inside F's ingest calls
    other_calls_s: float  # inside the other ingest calls
    tail_s: float  # waiting for the correlation process's last answers
    late_calls_s: float  # inside the other ingest calls from ``late_from`` on
    f_outputs: int  # outputs returned by F's ingest calls
    f_accepted: int
    rejected: int
    f_tracks: int
    f_window: int
    pairs: int
    seconds: list[SecondRow] = field(default_factory=list)
    #: Per F call (``trace``): ms, and F's window plots after it.
    trace: np.ndarray = field(default_factory=lambda: np.empty((0, 2)))


def f_state(engine: Engine) -> tuple[int, int, int]:
    """F's window plots, tracks and confirmed tracks (0 before F's first batch)."""
    radar = engine.tracking.tracked.get(FLOODER)
    if radar is None or radar.tracker is None:
        return 0, 0, 0
    return radar.tracker.window_plots, len(radar.table), int(np.count_nonzero(radar.table.confirmed))


def run(
    stream: Stream,
    process: bool,
    marks: list[int] | None = None,
    profiler: cProfile.Profile | None = None,
    late_from: int | None = None,
    trace: bool = False,
) -> Run:
    """``stream`` through a fresh engine; ``marks``: indices after which F's state is noted
    (:class:`SecondRow`); ``profiler``: on during F's ingest calls only; ``late_from``: the
    other calls from this index on are summed apart (``late_calls_s``); ``trace``: each F
    call's time and F's window plots after it are kept (``Run.trace``)."""
    late = len(stream) if late_from is None else late_from
    is_f = [key.startswith(f"fusion/radar/{FLOODER}/") for key, _ in stream]
    at = set(marks or ())
    seconds: list[SecondRow] = []
    gc.collect()
    engine = Engine(correlation_process=process)
    try:
        if process:
            engine.flush()  # an empty engine: waits until the child answers (start-up not timed)
        f_s = other_s = late_s = 0.0
        f_outputs = 0
        traced: list[tuple[float, int]] = []
        clock = time.perf_counter
        t0 = clock()
        for i, (key, payload) in enumerate(stream):
            if is_f[i]:
                if profiler is not None:
                    profiler.enable()
                a = clock()
                out = engine.ingest(key, payload)
                b = clock()
                if profiler is not None:
                    profiler.disable()
                f_s += b - a
                f_outputs += len(out)
                if trace and key == F_PLOTS_KEY:
                    tracker = engine.tracking.tracked[FLOODER].tracker
                    traced.append(((b - a) * 1e3, tracker.window_plots if tracker is not None else 0))
            else:
                a = clock()
                engine.ingest(key, payload)
                b = clock()
                other_s += b - a
                if i >= late:
                    late_s += b - a
            if i in at:
                window, tracks, confirmed = f_state(engine)
                seconds.append(SecondRow(b - t0, i, window, tracks, confirmed))
        ingested = clock()
        while engine.answers_pending:
            engine.poll()
            time.sleep(POLL_S)
        t1 = clock()
        source = engine.sequencer.sources.get(FLOODER)
        window, tracks, _ = f_state(engine)
        pairs = int(engine.snapshot().status_core()["pairs_confirmed"])  # after the clock
        return Run(
            t1 - t0,
            f_s,
            other_s,
            t1 - ingested,
            late_s,
            f_outputs,
            source.batches if source is not None else 0,
            sum(engine.rejected.values()),
            tracks,
            window,
            pairs,
            seconds,
            np.array(traced, dtype=float).reshape(-1, 2),
        )
    finally:
        engine.close()


# -- printing ------------------------------------------------------------------------------
#: Bins of F's window (plots after the call) for the per-call times of case 3; the first is
#: the fixed cost: a one-plot message while the window is (nearly) empty.
WINDOW_BINS = (0, 100, 250, 500, 1000, 2000, 4000, 8000)


def mm(values: list[float], fmt: str = ".3f") -> str:
    """min / median."""
    return f"{format(min(values), fmt)} / {format(float(np.median(values)), fmt)}"


def by_window(trace: np.ndarray) -> list[tuple[int, float]]:
    """Per bin of :data:`WINDOW_BINS`: the calls in it and their median ms (nan: none)."""
    edges = [*WINDOW_BINS, np.inf]
    out = []
    for lo, hi in itertools.pairwise(edges):
        ms = trace[(trace[:, 1] >= lo) & (trace[:, 1] < hi), 0] if len(trace) else np.empty(0)
        out.append((len(ms), float(np.median(ms)) if len(ms) else float("nan")))
    return out


Functions = list[tuple[str, str]]
#: A detail row: its label, its functions, and (optionally) functions whose time is taken off.
Detail = tuple[str, Functions] | tuple[str, Functions, Functions]
GroupSpec = tuple[str, str, Functions, list[Detail]]
MANAGER_UPDATE: Functions = [("service/tracking/manager.py", "update")]
#: What grows with the radar's window at every batch: initiation over the whole window, pruning.
INITIATION: Functions = [("service/tracking/manager.py", "_initiate_from_window")]
WINDOW_BOUND: Functions = [*INITIATION, ("service/tracking/window.py", "prune")]

#: (group, what it holds, its functions (file, name), detail rows).
GROUPS: list[GroupSpec] = [
    (
        "decode",
        "decode_input (pydantic parse, ids) + plot_columns",
        [("service/pipeline/decode.py", "decode_input"), ("service/pipeline/decode.py", "plot_columns")],
        [
            ("pydantic model_validate_json", [("service/pipeline/decode.py", "parse")]),
            ("plot_columns (numpy columns)", [("service/pipeline/decode.py", "plot_columns")]),
        ],
    ),
    (
        "sequencer",
        "Sequencer.check / accept / release",
        [
            ("service/pipeline/sequencer.py", "check"),
            ("service/pipeline/sequencer.py", "accept"),
            ("service/pipeline/sequencer.py", "release"),
        ],
        [("watermark", [("service/pipeline/sequencer.py", "watermark")])],
    ),
    (
        "tracking",
        "TrackingStage.update",
        [("service/pipeline/tracking_stage.py", "update")],
        [
            ("TrackManager.update", MANAGER_UPDATE),
            ("  _gate (association)", [("service/tracking/manager.py", "_gate")]),
            ("  PlotWindow.prune", [("service/tracking/window.py", "prune")]),
            ("  _initiate_from_window", INITIATION),
            ("    PlotWindow._join (window joined)", [("service/tracking/window.py", "_join")]),
            ("    logic_initiate (the initiator)", [("service/tracking/logic.py", "logic_initiate")]),
            ("      time_gated_pairs", [("service/tracking/pairs.py", "time_gated_pairs")]),
            ("    fit_groups (births)", [("service/tracking/groups.py", "fit_groups")]),
            ("TrackManager.tracks (table)", [("service/tracking/manager.py", "tracks")]),
            (
                "truth labels (wrapper, less that)",
                [("service/evaluation/truth.py", "update")],
                MANAGER_UPDATE,
            ),
        ],
    ),
    (
        "correlation",
        "Engine._correlate: merger release, runner, stage",
        [("service/engine.py", "_correlate")],
        [
            ("CorrelationStage.radar", [("service/pipeline/correlation_stage.py", "radar")]),
            ("  _newly_confirmed", [("service/pipeline/correlation_stage.py", "_newly_confirmed")]),
            ("  _prompt (decide_new)", [("service/pipeline/correlation_stage.py", "_prompt")]),
            ("  _system (system tracks)", [("service/pipeline/correlation_stage.py", "_system")]),
            ("PairSetView.of / SystemTrackView.of", [("service/pipeline/read_model.py", "of")]),
            ("TableMerger.release", [("service/pipeline/merger.py", "release")]),
        ],
    ),
    (
        "publication",
        "Engine._results: Publication.tracks / pairs / system_tracks",
        [("service/engine.py", "_results")],
        [
            ("Publication.tracks", [("service/pipeline/publication.py", "tracks")]),
            ("Publication.pairs", [("service/pipeline/publication.py", "pairs")]),
        ],
    ),
    ("snapshot", "Engine.snapshot", [("service/engine.py", "snapshot")], []),
]


def cumulative(stats: pstats.Stats, functions: list[tuple[str, str]]) -> float | None:
    """Cumulative seconds of the functions (None: none of them ran or exists)."""
    table = stats.stats  # type: ignore[attr-defined]
    total, found = 0.0, False
    for (filename, _line, name), (_cc, _nc, _tt, ct, _callers) in table.items():
        path = filename.replace("\\", "/")
        if any(name == fn and path.endswith("/" + f) for f, fn in functions):
            total += ct
            found = True
    return total if found else None


def profile_case2(
    streams: Streams, top: int, case2_s: float, honest_late_s: float
) -> tuple[dict[str, float], float]:
    """Case 2 in process, F's messages each after the honest batches of its period
    (:func:`f_after`), once without and once under cProfile (on during F's ingest calls);
    prints and returns each group's share of the F calls' profiled time, and the share that
    grows with F's window (:data:`WINDOW_BOUND`).  ``case2_s``: case 2's
    median wall; ``honest_late_s``: case 1's calls over the flood's data seconds."""
    n = streams.f_count
    plain = run(streams.f_after, False)
    profiler = cProfile.Profile()
    r = run(streams.f_after, False, profiler=profiler)
    print(
        f"\n=== profile: case 2 in process, each F message after the honest batches of its 0.5 s period, "
        f"the profiler on during F's {n} ingest calls only ===\n"
        f"in this order without the profiler: wall {plain.wall_s:.2f} s (case 2, interleaved: median "
        f"{case2_s:.2f} s), F calls {plain.f_calls_s:.2f} s = {plain.f_calls_s / n * 1e3:.3f} ms per F "
        f"message, honest calls {plain.other_calls_s:.3f} s\n"
        f"under the profiler: F calls {r.f_calls_s:.2f} s ({r.f_calls_s / n * 1e3:.3f} ms per F message); "
        f"they also release the honest batches of the flood's {streams.end_s - streams.flood_start_s:g} data "
        f"s, which cost {honest_late_s:.3f} s in case 1 ({100 * honest_late_s / plain.f_calls_s:.1f}% of "
        "the F calls without the profiler)"
    )
    print(f"--- top {top} by cumulative time ---")
    pstats.Stats(profiler, stream=sys.stdout).strip_dirs().sort_stats("cumulative").print_stats(top)
    full = pstats.Stats(profiler)
    total = cumulative(full, [("service/engine.py", "ingest")]) or r.f_calls_s
    print(
        f"--- grouped, per F message (under the profiler; Engine.ingest {total:.2f} s in all, "
        f"{total / n * 1e3:.3f} ms per message) ---"
    )
    print(f"{'group':12s} {'ms/msg':>7s} {'share':>6s}  what")
    shares: dict[str, float] = {}
    accounted = 0.0
    for name, what, functions, details in GROUPS:
        s = cumulative(full, functions) or 0.0
        accounted += s
        shares[name] = s / total
        print(f"{name:12s} {s / n * 1e3:7.3f} {100 * s / total:5.1f}%  {what}")
        for label, fns, *minus in details:
            d = cumulative(full, fns)
            if d is not None:
                d -= sum(cumulative(full, m) or 0.0 for m in minus)
                print(f"  {label:34s} {d / n * 1e3:7.3f} ms {100 * d / total:5.1f}%")
    rest = max(total - accounted, 0.0)
    shares["rest"] = rest / total
    print(
        f"{'rest':12s} {rest / n * 1e3:7.3f} {100 * rest / total:5.1f}%  the engine's own code "
        "(ingest, _admit, _process, _track, keys, feed, merger push) and the profiler"
    )
    bound = (cumulative(full, WINDOW_BOUND) or 0.0) / total
    print(
        f"of all this, what grows with F's window at every message (_initiate_from_window, "
        f"PlotWindow.prune): {100 * bound:.1f}%; the rest, fixed or growing with F's tracks (_gate, "
        f"tables, correlation): {(1 - bound) * total / n * 1e3:.3f} ms per message under the profiler"
    )
    return shares, bound


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--duration", type=float, default=40.0, help="data seconds of the stream (40)")
    parser.add_argument(
        "--flood-s", type=float, default=3.0, help="data seconds F floods, at the end of the stream (3)"
    )
    parser.add_argument("--flood-rate", type=float, default=500.0, help="F's batches per data second (500)")
    parser.add_argument("--pattern", choices=("flood", "clutter"), default="flood", help="F's plots")
    parser.add_argument("--repeat", type=int, default=3, help="rounds of the cases, interleaved (3)")
    parser.add_argument(
        "--profile", action=argparse.BooleanOptionalAction, default=True, help="profile case 2 (on)"
    )
    parser.add_argument("--top", type=int, default=25, help="functions listed by the profile (25)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    if not 0.0 < args.flood_s <= args.duration or args.flood_rate <= 0 or args.repeat < 1:
        parser.error("need 0 < --flood-s <= --duration, --flood-rate > 0, --repeat >= 1")

    started = time.perf_counter()
    streams = build(args)
    n_f = streams.f_count
    n_h = len(streams.honest)
    print(
        f"{SCENARIO}: {args.duration:g} data s, {n_h} messages, {streams.honest_plots} plots (seed "
        f"{args.seed}); radar {FLOODER}: {n_f} one-plot batches ({args.pattern}) at {args.flood_rate:g} "
        f"per data s over the last {args.flood_s:g} s; {args.repeat} interleaved rounds; min / median"
    )
    cases = [
        ("1", streams.honest, False),
        ("2", streams.with_f, False),
        ("3", streams.f_alone, False),
        ("1p", streams.honest, True),
        ("2p", streams.with_f, True),
        ("3p", streams.f_alone, True),
    ]
    runs: dict[str, list[Run]] = {name: [] for name, _, _ in cases}
    for rnd in range(args.repeat):
        for name, stream, process in cases:
            marks = streams.f_seconds if name == "3" else None
            late = streams.honest_flood_from if name.startswith("1") else None
            runs[name].append(run(stream, process, marks, late_from=late, trace=name.startswith("3")))
        print(
            f"# round {rnd + 1}: "
            + ", ".join(f"{name} {runs[name][-1].wall_s:.2f} s" for name, _, _ in cases),
            file=sys.stderr,
            flush=True,
        )

    def wall(name: str) -> list[float]:
        return [r.wall_s for r in runs[name]]

    def f_ms(name: str, base: str | None) -> list[float]:
        """ms per F message: the case's wall (less the base case's, round by round)."""
        if base is None:
            return [w / n_f * 1e3 for w in wall(name)]
        return [(w - b) / n_f * 1e3 for w, b in zip(wall(name), wall(base), strict=True)]

    print(f"\n{'case':64s} {'wall s':>15s} {'ms per msg':>15s} {'ms per plot':>15s}")
    for suffix, where in (("", "in process"), ("p", "correlation process")):
        h = wall("1" + suffix)
        print(
            f"{'1' + suffix:3s} {'honest, ' + where:60s} {mm(h, '.3f'):>15s} "
            f"{mm([w / n_h * 1e3 for w in h]):>15s} {mm([w / streams.honest_plots * 1e3 for w in h]):>15s}"
        )
        print(
            f"{'2' + suffix:3s} {'honest + F, ' + where + ': per F msg (with - without)':60s} "
            f"{mm(wall('2' + suffix)):>15s} {mm(f_ms('2' + suffix, '1' + suffix)):>15s}"
        )
        print(
            f"{'3' + suffix:3s} {'F alone, ' + where:60s} {mm(wall('3' + suffix)):>15s} "
            f"{mm(f_ms('3' + suffix, None)):>15s}"
        )
    print("\nper run (median round): F calls = time inside F's ingest calls; tail = wait for answers")
    print(
        f"{'case':4s} {'F calls ms/F msg':>16s} {'other calls s':>13s} {'tail s':>7s} {'F outs/msg':>10s} "
        f"{'F taken':>7s} {'rejected':>8s} {'F tracks':>8s} {'F window':>8s} {'pairs':>5s}"
    )
    for name, _, _ in cases:
        rs = sorted(runs[name], key=lambda r: r.wall_s)
        r = rs[len(rs) // 2]
        fmsg = f"{r.f_calls_s / n_f * 1e3:.3f}" if not name.startswith("1") else "-"
        outs = f"{r.f_outputs / n_f:.2f}" if not name.startswith("1") else "-"
        print(
            f"{name:4s} {fmsg:>16s} {r.other_calls_s:13.3f} {r.tail_s:7.3f} {outs:>10s} {r.f_accepted:7d} "
            f"{r.rejected:8d} {r.f_tracks:8d} {r.f_window:8d} {r.pairs:5d}"
        )

    # case 3 per data second of the flood (the round with the least wall time)
    best3 = min(runs["3"], key=lambda r: r.wall_s)
    print("\ncase 3 (F alone, in process) per data second of the flood, fastest round:")
    print(f"{'second':>6s} {'ms per F msg':>12s} {'F window plots':>14s} {'F tracks':>8s} {'confirmed':>9s}")
    prev_t, prev_i = 0.0, 0
    for k, row in enumerate(best3.seconds):
        ms = (row.wall_s - prev_t) / max(row.messages - prev_i, 1) * 1e3
        print(f"{k + 1:6d} {ms:12.3f} {row.window_plots:14d} {row.tracks:8d} {row.confirmed:9d}")
        prev_t, prev_i = row.wall_s, row.messages
    bins = {name: [by_window(r.trace) for r in runs[name]] for name in ("3", "3p")}

    def bin_ms(name: str, k: int) -> float:
        """Median over the rounds of the median ms of the calls in bin ``k``."""
        values = [b[k][1] for b in bins[name] if b[k][0]]
        return float(np.median(values)) if values else float("nan")

    print(
        "\nper F call by F's window plots after it (case 3, F alone: each F call processes its own "
        "batch); median ms of the calls in each bin, median over the rounds:"
    )
    print(f"{'window plots':>14s} {'calls':>6s} {'3 ms':>8s} {'3p ms':>8s}")
    edges = [*WINDOW_BINS, np.inf]
    for k, (lo, hi) in enumerate(itertools.pairwise(edges)):
        calls = bins["3"][0][k][0]
        if calls:
            print(f"{f'{lo}-{hi}':>14s} {calls:6d} {bin_ms('3', k):8.3f} {bin_ms('3p', k):8.3f}")

    shares: dict[str, float] = {}
    bound = float("nan")
    if args.profile:
        late = min(r.late_calls_s for r in runs["1"])
        shares, bound = profile_case2(streams, args.top, float(np.median(wall("2"))), late)

    # -- conclusion ---------------------------------------------------------------------------
    per_msg = min(f_ms("2", "1"))
    honest_plot = min(wall("1")) / streams.honest_plots * 1e3
    fixed, fixed_p = bin_ms("3", 0), bin_ms("3p", 0)

    def verdict(ms: float) -> str:
        return "met" if ms <= TARGET_MS else f"NOT met ({ms / TARGET_MS:.1f} x)"

    print(f"\n=== conclusion (min over the rounds; target <= {TARGET_MS:g} ms per one-plot batch) ===")
    print(
        f"one one-plot message of F, with the honest radars, in process: {per_msg:.3f} ms on average over "
        f"F's {args.flood_s:g} s flood (window up to {max(r.window_plots for r in best3.seconds)} plots): "
        f"{verdict(per_msg)}"
    )
    print(
        f"  with the correlation process: {min(f_ms('2p', '1p')):.3f} ms ({verdict(min(f_ms('2p', '1p')))}); "
        f"F alone: {min(f_ms('3', None)):.3f} ms in process, {min(f_ms('3p', None)):.3f} ms with the process"
    )
    print(
        f"  an honest plot costs {honest_plot:.4f} ms (case 1, "
        f"{streams.honest_plots / max(n_h, 1):.0f} plots per message): a one-plot batch costs what "
        f"{per_msg / honest_plot:.0f} honest plots cost"
    )
    if per_msg <= 0:
        print("  (below the noise of case 1's time: a longer --flood-s or more --repeat)")
    elif shares:
        print(
            "  where it goes (profile shares applied to it): "
            + ", ".join(f"{k} {per_msg * v:.3f} ms ({100 * v:.0f}%)" for k, v in shares.items())
        )
        print(
            f"  of which grows with F's window (tracker initiation over the whole window at every batch): "
            f"{per_msg * bound:.3f} ms ({100 * bound:.0f}%); the rest: {per_msg * (1 - bound):.3f} ms"
        )
    print(
        f"fixed cost of a one-plot message (F alone, its window under {WINDOW_BINS[1]} plots): "
        f"{fixed:.3f} ms in process ({verdict(fixed)}), {fixed_p:.3f} ms with the correlation process "
        f"({verdict(fixed_p)}); "
        "above it the cost grows with the radar's window (see the bins), whatever the batch holds"
    )
    print(f"# whole run {time.perf_counter() - started:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
