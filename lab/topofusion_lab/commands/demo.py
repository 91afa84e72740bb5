"""``topofusion demo``: ``run`` plus the simulator in the same process, on an embedded Zenoh
peer, with a one-line progress report."""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from typing import Any

from service.cli.common import Commands, add_command, settings_from, setup_logging
from service.cli.serve import serve, service_flags
from topofusion_lab.commands.simulate import SITE_EVERY_S, scenario_for, seed, speed

log = logging.getLogger("topofusion")


def register(commands: Commands) -> None:
    demo = add_command(
        commands,
        "demo",
        demo_main,
        own_logging=True,
        help="run plus a built-in simulator on an embedded Zenoh peer",
    )
    service_flags(demo)
    demo.add_argument("--scenario", default="demo", help="simulated scenario (default demo)")
    demo.add_argument(
        "--speed", type=speed, default=1.0, help="simulation speed (x real time; 0: as fast as possible)"
    )
    demo.add_argument("--seed", type=seed, default=0)
    demo.add_argument("--start-time", type=float, help="data time of the first scan (default: now)")
    demo.add_argument(
        "--workers",
        type=int,
        default=1,
        metavar="N",
        help="a Zenoh router and N partitioned `run` workers on this machine (default 1: one process)",
    )


def demo_main(args: argparse.Namespace) -> int:
    if args.workers != 1:
        from topofusion_lab.demo_workers import run_workers_demo

        return run_workers_demo(args)
    from topofusion_lab.demo_workers import check_state_dir

    settings = settings_from(args)
    setup_logging(settings.log_level)
    check_state_dir(settings.state_dir, 1)
    return serve(settings, hooks=lambda prefix: DemoSimulator(args, prefix))


class DemoSimulator:
    """The demo's simulator thread and its one-line progress report (the hooks of
    :func:`service.cli.serve.serve`)."""

    def __init__(self, args: argparse.Namespace, prefix: str) -> None:
        from topofusion_lab.publisher import publish_scenario

        self.publish_scenario = publish_scenario
        self.scenario = scenario_for(args)
        self.speed = args.speed
        self.seed = args.seed
        self.prefix = prefix
        self.stop_event = threading.Event()
        self.threads: list[threading.Thread] = []

    def start(self, node: Any) -> None:
        publish_scenario = self.publish_scenario

        def simulate() -> None:
            # a client whose router is not up yet connects later (the node retries): wait for it
            while node.connection.session is None:
                if self.stop_event.wait(0.2):
                    return
            try:
                publish_scenario(
                    node.session,
                    self.scenario,
                    self.prefix,
                    self.speed,
                    self.seed,
                    self.stop_event,
                    site_every_s=SITE_EVERY_S,  # a recorder joining later learns them too
                )
            except Exception:
                if not self.stop_event.is_set():
                    # a demo without its data is no demo: it ends (exit status 1)
                    log.exception("simulator failed; the demo stops")
                    if node.on_fatal is not None:
                        node.on_fatal("simulator failed")

        self.threads = [
            threading.Thread(target=simulate, name="demo-simulator", daemon=True),
            threading.Thread(target=self._progress, args=(node,), name="demo-progress", daemon=True),
        ]
        for t in self.threads:
            t.start()
        print(
            f"demo: scenario {self.scenario.name!r} ({self.scenario.description}) at {self.speed}x; "
            "Ctrl-C to stop",
            file=sys.stderr,
        )

    def _line(self, node: Any, rate: float) -> str:
        st = node.status()
        batches = sum(r["batches"] for r in st["radars"])
        plots = sum(r["plots"] for r in st["radars"])
        tracks = sum(r["tracks_confirmed"] for r in st["radars"])
        correct = _correct_by_truth(node.snapshot)
        return (
            f"batches {batches}  plots {plots} ({rate:,.0f}/s)  confirmed tracks {tracks}  "
            f"pairs {st['pairs_confirmed']} confirmed ({correct} right by simulator truth) / "
            f"{st['pairs_tentative']} tentative  "
            f"rejected {sum(st['rejected'].values())}  corr p50 {st['correlation']['p50_ms']:.1f} ms"
        )

    def _progress(self, node: Any) -> None:
        """One live line on a terminal (rewritten in place), a line every 5 s in a log."""
        tty = sys.stderr.isatty()
        last_plots, last_t = 0, time.monotonic()
        while not self.stop_event.wait(1.0 if tty else 5.0):
            plots = sum(r.status.plots for r in node.snapshot.radar_rows)
            now = time.monotonic()
            rate = (plots - last_plots) / max(now - last_t, 1e-6)
            last_plots, last_t = plots, now
            line = self._line(node, rate)
            print(
                ("\r" + line + "   ") if tty else line, end="" if tty else "\n", file=sys.stderr, flush=True
            )

    def stop(self, node: Any) -> None:
        self.stop_event.set()
        for t in self.threads:
            t.join(timeout=3.0)
        print(f"\ndemo: stopped; {self._line(node, 0.0)}", file=sys.stderr, flush=True)


def _correct_by_truth(snapshot: Any) -> int:
    """Confirmed pairs whose tracks follow the same simulated target (display only: the demo
    knows the simulator's truth; no algorithm ever reads it).  A reference source's track (an
    ADS-B or AIS one) is named by what its target transmits, its icao24 or MMSI."""
    from topofusion_lab.scenarios.simulator import identity_of, mmsi_of  # (not at `--help`)

    truth = {
        (rid, str(tid)): t
        for rid, (_, table) in snapshot.tracks.items()
        for tid, t in zip(table.track_id, table.truth_id, strict=True)
    }

    def right(a: tuple[str, str], b: tuple[str, str]) -> bool:
        """``a`` a radar's track; ``b`` another radar's or a reference source's."""
        target = truth.get(a)
        if target is None:
            return False
        if b[0] in snapshot.tracks:
            return bool(truth.get(b) == target)
        return b[1] in (identity_of(str(target))[1], mmsi_of(str(target)))

    return sum(
        right(a, b) if a[0] in snapshot.tracks else right(b, a)
        for ps in snapshot.pair_sets(status="confirmed")
        for p in ps["pairs"]
        for a, b in [((ps["radar_a"], p["track_a"]), (ps["radar_b"], p["track_b"]))]
    )
