"""State keeper benchmark (``--state-dir``): what a write costs the worker on a busy state.

Feeds the ``national`` scenario (12 radars, 1 500 aircraft; the stream is generated before any
clock starts, ``--cache FILE`` keeps it) through an ``Engine`` with a ``StateKeeper`` in a
temporary directory, ``maybe_save`` after every message as the service's worker calls it, and
prints one row per periodic write: the data time, the registration memories and rows in the
file, its size, the worker's longest pause in ``maybe_save`` since the write before (taking
the engine's part of the state; with ``--process`` asking the correlation process for its part
and, messages later, taking its answer) and the writer thread's time (encoding, ``fsync``,
rename).  Then the final write of a stop, and a start: reading the file
and restoring a fresh engine from it.  Prints figures, never asserts.

The registration memories fill for ``RegistrationParams.memory_s`` (600 s) plus
``keep_extra_s`` of data: the default duration fills them, so the last rows are the
steady-state size of a national network.

Run: .venv/bin/python bench/bench_state.py [--duration 660] [--seed 1] [--interval 30]
     [--process] [--cache FILE]
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from service.engine import Engine, EngineConfig
from service.state import StateKeeper
from service.state.fileformat import decode
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import wire_messages

Stream = list[tuple[str, bytes]]


def make_stream(duration_s: float, seed: int, cache: Path | None) -> Stream:
    if cache is not None and cache.exists():
        return [(k, p.encode()) for k, p in json.loads(cache.read_text())]
    stream = list(wire_messages(replace(get_scenario("national"), duration_s=duration_s), seed))
    if cache is not None:
        cache.write_text(json.dumps([(k, p.decode()) for k, p in stream]))
    return stream


def rows(path: Path) -> tuple[int, int]:
    """Registration memories and their rows in the file written."""
    memories = decode(path.read_bytes(), "fusion", "1/1")[1]["correlation"]["memories"]
    return len(memories), sum(len(m["rows"]["time"]) for m in memories)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=660.0, help="data seconds (default 660)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--interval", type=float, default=30.0, help="data seconds between writes")
    ap.add_argument("--process", action="store_true", help="correlation in its own process")
    ap.add_argument("--cache", type=Path, help="keep the generated stream in this file")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")  # the keeper's line at a start

    t0 = time.perf_counter()
    stream = make_stream(args.duration, args.seed, args.cache)
    print(
        f"national, {args.duration:.0f} s of data, {len(stream)} messages ({time.perf_counter() - t0:.0f} s)"
    )
    mode = "correlation process" if args.process else "one process"
    print(f"engine: {mode}; writes every {args.interval:g} s of data time")

    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        engine = Engine(EngineConfig(), correlation_process=args.process)
        try:
            keeper = StateKeeper(directory, "fusion", "1/1", args.interval)
            keeper.restore(engine)
            print(
                f"{'data s':>7s} {'memories':>8s} {'rows':>9s} {'MB':>7s} "
                f"{'worker pause ms':>15s} {'writer ms':>9s}"
            )
            start = engine.data_clock_s
            feed_s = stall_s = since_s = 0.0
            for key, payload in stream:
                t = time.perf_counter()
                engine.ingest(key, payload)
                t1 = time.perf_counter()
                writes = keeper.writes
                keeper.maybe_save(engine)
                t2 = time.perf_counter()
                feed_s += t1 - t
                stall_s = max(stall_s, t2 - t1)
                since_s = max(since_s, t2 - t1)
                if start == float("-inf"):
                    start = engine.data_clock_s
                if keeper.writes != writes:
                    keeper.wait()  # for the figures of this write (the service does not wait)
                    n_mem, n_rows = rows(keeper.path)
                    print(
                        f"{engine.data_clock_s - start:7.0f} {n_mem:8d} {n_rows:9d} "
                        f"{keeper.last_bytes / 1e6:7.1f} {since_s * 1e3:15.1f} "
                        f"{keeper.last_write_s * 1e3:9.0f}"
                    )
                    since_s = 0.0
            print(f"fed in {feed_s:.0f} s of engine time; longest maybe_save {stall_s * 1e3:.1f} ms")
            t = time.perf_counter()
            keeper.save(engine)
            print(
                f"final write (stop): {(time.perf_counter() - t) * 1e3:.0f} ms, "
                f"taking the state {keeper.last_export_s * 1e3:.1f} ms, {keeper.last_bytes / 1e6:.1f} MB"
            )
        finally:
            engine.close()

        fresh = Engine(EngineConfig(), correlation_process=args.process)
        try:
            t = time.perf_counter()
            StateKeeper(directory, "fusion", "1/1", args.interval).restore(fresh)
            print(f"start: read, restored and wrote again in {(time.perf_counter() - t) * 1e3:.0f} ms")
        finally:
            fresh.close()


if __name__ == "__main__":
    main()
