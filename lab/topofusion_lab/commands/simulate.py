"""``topofusion simulate``: a scenario's sites and plot batches over Zenoh, or as ASTERIX
(:mod:`topofusion_lab.simulate`).  The arguments are judged before any Zenoh connection, so
that a mistake ends the command at once."""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

from service.cli.common import (
    Commands,
    add_command,
    settings_from,
    stop_on_signals,
    zenoh_flags,
    zenoh_options,
)

#: ``--site-every`` default (wall s; ``demo``'s simulator too): the publisher's ``SITE_EVERY_S``,
#: kept here so that parsing (every start of ``topofusion``) does not import the simulator.
SITE_EVERY_S = 5.0


class _ListScenarios(argparse.Action):
    """``--list``: print the scenarios and their descriptions, then exit 0 (like ``--help``,
    so that the required ``--scenario`` is not asked for)."""

    def __init__(self, option_strings: Sequence[str], dest: str, help: str | None = None) -> None:
        super().__init__(
            option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, nargs=0, help=help
        )

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> NoReturn:
        from topofusion_lab.scenarios.catalog import DEMO, SCENARIOS

        for scenario in (DEMO, *SCENARIOS.values()):
            until = " (runs until stopped)" if scenario.duration_s is None else ""
            print(f"{scenario.name:<12} {scenario.description}{until}")
        parser.exit(0)


def _start_time(text: str) -> float | str:
    if text == "resume":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: a data time (s since the Unix epoch) or 'resume'"
        ) from None


def speed(text: str) -> float:
    """``--speed``: x real time, a finite number >= 0 (0: as fast as possible)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r}: a finite number >= 0 (0: as fast as possible)")
    return value


def seed(text: str) -> int:
    """``--seed``: the random generator's seed, an integer >= 0."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: an integer >= 0")
    return value


def _udp_endpoint(text: str) -> Any:
    from service.asterix.udp import parse_endpoint

    try:
        return parse_endpoint(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def register(commands: Commands) -> None:
    sim = add_command(
        commands, "simulate", simulate_main, help="publish a scenario's sites and plot batches over Zenoh"
    )
    zenoh_flags(sim, default_mode="client")
    sim.add_argument("--scenario", required=True, help="scenario name (see --list)")
    sim.add_argument(
        "--list", action=_ListScenarios, help="list the scenarios with their descriptions and exit"
    )
    sim.add_argument("--speed", type=speed, default=1.0, help="x real time; 0 = as fast as possible")
    sim.add_argument("--seed", type=seed, default=0)
    sim.add_argument("--duration", type=float, help="data seconds to simulate (default: the scenario's)")
    sim.add_argument(
        "--start-time",
        type=_start_time,
        metavar="S|resume",
        help="data time of the first scan (default: now); resume: just after the data clock the service "
        "reports (get {prefix}/status)",
    )
    sim.add_argument(
        "--loop", action="store_true", help="repeat the scenario without end, data time and seq running on"
    )
    sim.add_argument(
        "--site-every",
        type=float,
        default=SITE_EVERY_S,
        metavar="S",
        help=f"put the sites again every S wall seconds, for late joiners (0: only at the start; "
        f"default {SITE_EVERY_S:g})",
    )
    sim.add_argument(
        "--wait-service",
        type=float,
        metavar="S",
        help="before publishing, wait up to S s for a service to answer {prefix}/status (default 0; "
        "30 with --start-time resume)",
    )
    sim.add_argument(
        "--wait",
        type=float,
        default=120.0,
        metavar="S",
        help="after the last message, wait up to S s until the service reports its outputs complete "
        "through the run's end (as replay does; no service answering: no wait); 0: do not wait "
        "(default 120)",
    )
    sim.add_argument(
        "--adsb-every", type=int, metavar="N", help="every N-th aircraft reports ADS-B (source id adsb)"
    )
    sim.add_argument(
        "--asterix-file",
        type=Path,
        metavar="PATH",
        help="write the scenario as ASTERIX CAT048/034/021 instead of publishing it (.pcap: a pcap "
        "capture; else raw data blocks)",
    )
    sim.add_argument(
        "--asterix-udp",
        action="append",
        type=_udp_endpoint,
        default=[],
        metavar="HOST:PORT",
        help="send the scenario as ASTERIX datagrams to HOST:PORT instead of publishing it (repeatable)",
    )
    sim.add_argument(
        "--write-sites",
        type=Path,
        metavar="FILE",
        help="write the scenario's sites (with the SAC/SIC of the ASTERIX output) as a sites file",
    )


def scenario_for(args: argparse.Namespace) -> Any:
    """The named scenario, starting at ``--start-time`` (default: now, whole seconds)."""
    from dataclasses import replace

    from topofusion_lab.scenarios.catalog import get_scenario

    scenario = get_scenario(args.scenario)
    start = args.start_time if args.start_time is not None else float(int(time.time()))
    scenario = replace(scenario, start_time_s=start)
    if getattr(args, "duration", None) is not None:
        scenario = replace(scenario, duration_s=args.duration)
    return scenario


def simulate_main(args: argparse.Namespace) -> int:
    from service.transport.session import open_tool_session
    from topofusion_lab.simulate import check_arguments, run_simulation

    # a resumed run's start comes from the service; until then the scenario starts now
    resume = args.start_time == "resume"
    scenario = scenario_for(
        argparse.Namespace(**{**vars(args), "start_time": None if resume else args.start_time})
    )
    settings = settings_from(args)
    check_arguments(args)
    options = zenoh_options(settings, default_mode="client")
    stop = stop_on_signals()
    return run_simulation(
        args, scenario, settings.prefix, lambda: open_tool_session(options, "simulate", stop), stop
    )
