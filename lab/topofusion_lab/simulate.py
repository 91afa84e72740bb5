"""``topofusion simulate``: a scenario over Zenoh or as ASTERIX, once, looped, or resumed.

The command line (the lab's command group, ``topofusion_lab/commands/simulate.py``) parses the
flags and calls :func:`check_arguments` (all that can be judged without Zenoh, so a mistake ends
the command at once with status 2) and then
:func:`run_simulation`.

**Resuming** (``--start-time resume``): the simulator asks the service for its data clock with
``get {prefix}/status`` over Zenoh (the same session it publishes on; partitioned workers each
answer, and the newest clock of all replies counts).  The clock is the newest of the radars'
``last_time_s`` and ``outputs_time_s``; the first scan starts at the next whole second after
it.  Every radar's first batch is then later than anything the service took from it, so the
service takes the new run as a publisher's restart (``seq`` back at 1 at a later data time:
docs/contract.md §3) instead of rejecting it as duplicates.  Zenoh, not HTTP: the simulator
reaches the service there already (with the Zenoh flags it publishes with), and the HTTP port
may be elsewhere or need a token.  A service that reports no data clock yet (nothing taken):
the run starts now.  No service answering within ``--wait-service`` (default
:data:`RESUME_WAIT_S` for a resume): exit status 2, saying so.
"""

from __future__ import annotations

import argparse
import datetime as dt
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from service.output_files import check_writable
from service.recording.completion import RecordingEnd, service_statuses, wait_for_outputs
from topofusion_lab.scenarios.simulator import AdsbSpec, Scenario, generate, generate_looped

#: ``--start-time resume`` waits this long (wall s) for a service to answer ``{prefix}/status``
#: unless ``--wait-service`` says otherwise: as long as a tool waits for its router, so that a
#: simulator and a service (re)started together find each other.
RESUME_WAIT_S = 30.0
#: The ASTERIX bridge judges a live UDP feed by the wall clock and drops records further ahead
#: of it than this (s; its ``--max-time-ahead`` default): a feed that will be (``--speed``
#: other than 1, or a start time away from now) is told to use the bridge's ``--date``.
BRIDGE_TIME_AHEAD_S = 30.0
#: What a run's batches rejected as duplicates mean, and what to do about them.
RESTART_DUPLICATES = (
    "the service has these radars' data up to a later time (a run before this one); start after "
    "it with --start-time resume, or restart the service"
)
#: Source id of the ADS-B receiver ``--adsb-every`` adds (the ASTERIX bridge's default id).
ADSB_SOURCE_ID = "adsb"


def say(line: str) -> None:
    print(f"simulate: {line}", file=sys.stderr, flush=True)


def _writable_file(path: Path, flag: str) -> None:
    """A file the command will create: refuse now, before any connection, if it cannot be."""
    check_writable(path, flag)


def check_arguments(args: argparse.Namespace) -> None:
    """Everything judged without Zenoh; raises ValueError saying what is wrong."""
    if args.speed < 0:
        raise ValueError("--speed must be >= 0")
    if args.duration is not None and not args.duration > 0:
        raise ValueError("--duration must be > 0")
    if not args.site_every >= 0:
        raise ValueError("--site-every must be >= 0 (0: the sites only at the start)")
    if args.wait_service is not None and not args.wait_service >= 0:
        raise ValueError("--wait-service must be >= 0")
    if not args.wait >= 0:
        raise ValueError("--wait must be >= 0")
    if args.adsb_every is not None and args.adsb_every < 1:
        raise ValueError("--adsb-every must be at least 1")
    if args.asterix_file is not None:
        _writable_file(args.asterix_file, "--asterix-file")
    if args.write_sites is not None:
        _writable_file(args.write_sites, "--write-sites")


def with_adsb(sc: Scenario, every: int | None) -> Scenario:
    """Every ``every``-th aircraft reports ADS-B (one receiver, :data:`ADSB_SOURCE_ID`)."""
    if every is None:
        return sc
    if any(r.radar_id == ADSB_SOURCE_ID for r in sc.radars):
        raise ValueError(f"scenario {sc.name!r} has a radar named {ADSB_SOURCE_ID!r}, the ADS-B source's id")
    return replace(sc, adsb=(*sc.adsb, AdsbSpec(ADSB_SOURCE_ID, stride=every)))


def _utc(t: float) -> str:
    return dt.datetime.fromtimestamp(t, dt.timezone.utc).isoformat(timespec="seconds").replace("+00:00", "Z")


def resume_time(statuses: list[dict[str, Any]]) -> tuple[float | None, str]:
    """The first scan's data time after the services' data clock (module docstring), and a
    sentence saying why; None when no service reports a clock."""
    clocks: list[tuple[float, str]] = []
    for status in statuses:
        for radar in status.get("radars") or []:
            t = radar.get("last_time_s")
            if isinstance(t, (int, float)) and math.isfinite(t):
                clocks.append((float(t), f"radar {radar.get('radar_id')}'s last batch"))
        t = status.get("outputs_time_s")
        if isinstance(t, (int, float)) and math.isfinite(t):
            clocks.append((float(t), "its outputs"))
    if not clocks:
        return None, "the service reports no data clock yet (it has taken no batch): starting now"
    clock, what = max(clocks)
    start = math.floor(clock) + 1.0
    return start, (
        f"resuming after the service's data clock {clock:.3f} ({_utc(clock)}, {what}): "
        f"the first scan starts at {start:.0f} ({_utc(start)})"
    )


def run_simulation(
    args: argparse.Namespace,
    scenario: Scenario,
    prefix: str,
    open_session: Callable[[], Any],
    stop: threading.Event,
) -> int:
    """The command after :func:`check_arguments`; ``scenario`` carries ``--start-time`` (now
    when it is ``resume``: replaced here) and ``--duration``."""
    asterix = args.asterix_file is not None or bool(args.asterix_udp)
    sc = with_adsb(scenario, args.adsb_every)
    if asterix:
        from topofusion_lab.asterix_feed import asterix_scenario

        sc = asterix_scenario(sc)
    if args.write_sites is not None:
        from topofusion_lab.asterix_feed import sites_document

        args.write_sites.write_text(sites_document(sc))
        say(f"wrote the sites ({', '.join(r.radar_id for r in sc.radars)}) to {args.write_sites}")
    resume = args.start_time == "resume"
    wait_s = args.wait_service if args.wait_service is not None else (RESUME_WAIT_S if resume else 0.0)
    from service.transport.session import OpenCancelledError

    try:
        session = open_session() if not asterix or resume or wait_s > 0 else None
    except OpenCancelledError:  # (a signal while waiting for the router)
        say("stopped while waiting for the Zenoh router; nothing published")
        return 0
    try:
        if session is not None and (resume or wait_s > 0):
            say(f"asking the service for {prefix}/status (up to {wait_s:g} s)")
            statuses = service_statuses(session, prefix, wait_s, stop)
            if stop.is_set():
                return 0
            if resume:
                if not statuses:
                    raise ValueError(
                        f"simulate: no service answered {prefix}/status within {wait_s:g} s: cannot resume "
                        "after its data clock (is it running, on this prefix? --wait-service S waits longer; "
                        "--start-time S gives the first scan's data time)"
                    )
                start, why = resume_time(statuses)
                say(why)
                if start is not None:
                    sc = replace(sc, start_time_s=start)
            elif statuses:
                say("the service answers: starting")
            else:
                say(f"no service answered {prefix}/status within {wait_s:g} s: starting anyway")
        if asterix:
            if session is not None:
                session.close()
                session = None
            return _send_asterix(args, sc, stop)
        from topofusion_lab.publisher import publish_scenario

        assert session is not None
        loop = " over and over (--loop)" if args.loop else ""
        say(f"publishing {sc.name!r} from data time {sc.start_time_s:.0f} ({_utc(sc.start_time_s)}){loop}")
        from service.recording.commands import RejectionWatch

        rejections = RejectionWatch(session, prefix, "this run", RESTART_DUPLICATES)
        t0 = time.monotonic()
        last: dict[str, float] = {}
        batches, plots = publish_scenario(
            session,
            sc,
            prefix,
            args.speed,
            args.seed,
            stop,
            site_every_s=args.site_every,
            loop=args.loop,
            last_times=last,
        )
        say(f"published {batches} batches, {plots} plots in {time.monotonic() - t0:.1f} s")
        rejections.settle()
        rejections.close()
        for line in rejections.lines():
            say(line)
        complete = True
        if args.wait > 0 and not args.loop and not stop.is_set():
            complete = wait_for_outputs(session, prefix, RecordingEnd(last), args.wait, "the run")
        if rejections.by_reason.get("duplicate_seq") or not complete:
            return 1
    finally:
        if session is not None:
            session.close()
    return 0


def _send_asterix(args: argparse.Namespace, sc: Scenario, stop: threading.Event) -> int:
    from topofusion_lab.asterix_feed import Sink, Sinks, UdpOut, describe, open_file, send_asterix

    sinks: list[Sink] = []
    try:
        if args.asterix_file is not None:
            sinks.append(open_file(args.asterix_file))
        for endpoint in args.asterix_udp:
            sinks.append(UdpOut(endpoint.host, endpoint.port))
    except OSError:
        for s in sinks:
            s.close()
        raise
    if args.asterix_udp:
        ahead = abs(sc.start_time_s - time.time())
        if args.speed != 1.0 or ahead > BRIDGE_TIME_AHEAD_S:
            say(
                "this feed's data time is not the wall clock (--speed other than 1, or a start time "
                "away from now): run the bridge with --date "
                f"{dt.datetime.fromtimestamp(sc.start_time_s, dt.timezone.utc).date().isoformat()} so that "
                "it judges the feed by the data's own clock"
            )
    where = [str(args.asterix_file)] if args.asterix_file is not None else []
    where += [f"udp {e.host}:{e.port}" for e in args.asterix_udp]
    loop = " over and over (--loop)" if args.loop else ""
    say(
        f"sending {sc.name!r} as ASTERIX to {', '.join(where)} from data time {sc.start_time_s:.0f} "
        f"({_utc(sc.start_time_s)}){loop}"
    )
    messages = generate_looped(sc, args.seed) if args.loop else generate(sc, args.seed)
    t0 = time.monotonic()
    with Sinks(sinks) as out:
        sent = send_asterix(sc, messages, out, args.speed, stop)
    say(f"sent {describe(sent, time.monotonic() - t0)}")
    return 0
