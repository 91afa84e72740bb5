"""``topofusion`` command line (docs/contract.md §3).  Parsing stays here; entry points take config."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from pydantic import ValidationError

from service.settings import Settings, engine_config, http_limits
from service.transport.session import MODES, ZenohOptions
from service.wire.vocabulary import METHODS

log = logging.getLogger("topofusion")

#: The lab distribution (lab/ in a checkout): the simulator and its scenarios, their Zenoh
#: publisher and the evaluation.  The runtime does not depend on it and the container image does
#: not hold it, so only ``demo``, ``simulate`` and ``evaluate`` import it, and only when they run.
LAB_PACKAGE = "topofusion_lab"


class LabMissingError(RuntimeError):
    """A command that needs the lab ran where only the runtime is installed."""

    def __init__(self, command: str) -> None:
        super().__init__(
            f"`topofusion {command}` needs the TopoFusion lab ({LAB_PACKAGE}: simulator, scenarios, "
            "evaluation), which is not installed; install it from a checkout with `pip install -e lab`"
        )


@contextlib.contextmanager
def lab_imports(command: str) -> Iterator[None]:
    """Turn the lab's absence, inside the block, into :class:`LabMissingError` for ``command``."""
    try:
        yield
    except ModuleNotFoundError as exc:
        if (exc.name or "").partition(".")[0] != LAB_PACKAGE:
            raise  # something else is missing (e.g. a dependency of an installed lab): show it
        raise LabMissingError(command) from exc


class _ListScenarios(argparse.Action):
    """``simulate --list``: print the scenarios and their descriptions, then exit 0 (like ``--help``,
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
        try:
            with lab_imports("simulate --list"):
                from topofusion_lab.scenarios.catalog import DEMO, SCENARIOS
        except LabMissingError as exc:
            parser.exit(2, f"topofusion: {exc}\n")
        for scenario in (DEMO, *SCENARIOS.values()):
            until = " (runs until stopped)" if scenario.duration_s is None else ""
            print(f"{scenario.name:<12} {scenario.description}{until}")
        parser.exit(0)


#: ``simulate --site-every`` default (wall s; ``demo``'s simulator too); the lab's
#: ``SITE_EVERY_S``, kept here so that the parser (and ``--help``) does not import the lab.
SIMULATE_SITE_EVERY_S = 5.0


def _start_time(text: str) -> float | str:
    if text == "resume":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: a data time (s since the Unix epoch) or 'resume'"
        ) from None


def _udp_endpoint(text: str) -> Any:
    from service.asterix.udp import parse_endpoint

    try:
        return parse_endpoint(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _zenoh_flags(p: argparse.ArgumentParser, default_mode: str) -> None:
    g = p.add_argument_group("zenoh")
    g.add_argument(
        "--mode",
        choices=MODES,
        help=f"zenoh session mode (default: the config file's, else {default_mode})",
    )
    g.add_argument("--listen", action="append", metavar="ENDPOINT", help="listen endpoint (repeatable)")
    g.add_argument("--connect", action="append", metavar="ENDPOINT", help="connect endpoint (repeatable)")
    g.add_argument("--zenoh-config", metavar="FILE", help="JSON5 zenoh config; the flags above override it")
    g.add_argument("--prefix", help="key expression prefix (default: fusion)")


def _service_flags(p: argparse.ArgumentParser) -> None:
    _zenoh_flags(p, default_mode="peer")
    p.add_argument("--http-host", help="HTTP side port host (default 127.0.0.1)")
    p.add_argument("--http-port", type=int, help="HTTP side port (default 8000; 0 picks a free port)")
    p.add_argument("--sites", metavar="FILE", help="JSON file with a list of RadarSite")
    p.add_argument("--method", choices=METHODS, help="correlation method (default svd-topology)")
    p.add_argument("--window", type=float, metavar="S", help="sliding window, seconds of data time")
    p.add_argument("--initiator", help="track initiator (default logic)")
    p.add_argument(
        "--radars", action="append", metavar="ID", help="radars this worker owns (repeatable; default all)"
    )
    p.add_argument(
        "--partition",
        metavar="K/N",
        help="worker K of N on one prefix (default 1/1); see `topofusion partition` for who owns what",
    )
    p.add_argument("--log-level", help="logging level (default INFO)")
    p.add_argument("--config", metavar="FILE", help="engine parameters, TOML/YAML/JSON (see `config --show`)")
    p.add_argument(
        "--state-dir",
        metavar="DIR",
        help="keep sites, biases, registration memory, seq and the track-id epoch here across restarts",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="topofusion",
        description="Radar track correlation under unknown sensor bias, over Eclipse Zenoh.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _service_flags(sub.add_parser("run", help="the long-running service"))
    demo = sub.add_parser("demo", help="run plus a built-in simulator on an embedded Zenoh peer")
    _service_flags(demo)
    demo.add_argument("--scenario", default="demo", help="simulated scenario (default demo)")
    demo.add_argument("--speed", type=float, default=1.0, help="simulation speed (x real time)")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--start-time", type=float, help="data time of the first scan (default: now)")

    sim = sub.add_parser("simulate", help="publish a scenario's sites and plot batches over Zenoh")
    _zenoh_flags(sim, default_mode="client")
    sim.add_argument("--scenario", required=True, help="scenario name (see --list)")
    sim.add_argument(
        "--list", action=_ListScenarios, help="list the scenarios with their descriptions and exit"
    )
    sim.add_argument("--speed", type=float, default=1.0, help="x real time; 0 = as fast as possible")
    sim.add_argument("--seed", type=int, default=0)
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
        default=SIMULATE_SITE_EVERY_S,
        metavar="S",
        help=f"put the sites again every S wall seconds, for late joiners (0: only at the start; "
        f"default {SIMULATE_SITE_EVERY_S:g})",
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

    from service import recording

    rec = sub.add_parser("record", help="record samples under {prefix}/** into an MCAP file")
    _zenoh_flags(rec, default_mode="client")
    recording.add_record_arguments(rec)
    rep = sub.add_parser("replay", help="republish an MCAP recording")
    _zenoh_flags(rep, default_mode="client")
    recording.add_replay_arguments(rep)
    from service.recording.assess import add_assess_arguments

    add_assess_arguments(
        sub.add_parser("assess", help="radar performance against ADS-B / AIS over a recording")
    )

    from service.asterix import command as asterix

    ast = sub.add_parser(
        "asterix", help="bridge an ASTERIX feed (CAT048/034/021; UDP, pcap, raw) to the service"
    )
    _zenoh_flags(ast, default_mode="client")
    asterix.add_arguments(ast)

    ev = sub.add_parser("evaluate", help="Monte Carlo evaluation: tables and PNG figures")
    ev.add_argument("--out", default="evaluation", help="output folder (default ./evaluation)")
    ev.add_argument("--runs", type=int, help="Monte Carlo runs per point (default: each study's full count)")
    ev.add_argument("--seed", type=int, default=0)
    ev.add_argument(
        "--only",
        choices=("initiation", "correlation", "dense", "adsb", "system"),
        help="run one study only",
    )

    sub.add_parser(
        "healthcheck", help="exit 0 if the local service answers GET /healthz (container HEALTHCHECK)"
    )
    cfg = sub.add_parser("config", help="the engine's effective configuration, every parameter")
    cfg.add_argument("--show", action="store_true", help="print it (YAML) with its defaults")
    cfg.add_argument("--config", metavar="FILE", help="a config file to apply (TOML/YAML/JSON)")
    cfg.add_argument("--format", choices=("yaml", "json"), default="yaml")
    part = sub.add_parser("partition", help="which worker of N owns which radar and radar pair")
    part.add_argument("--count", type=int, required=True, metavar="N", help="number of workers")
    part.add_argument("--sites", metavar="FILE", help="the radars of a sites file (a JSON list of RadarSite)")
    part.add_argument("ids", nargs="*", metavar="ID", help="radar or reference source ids")
    sch = sub.add_parser("schemas", help="write JSON Schemas of every payload into schemas/")
    sch.add_argument("--out", default="schemas", help="output folder (default ./schemas)")
    return parser


def settings_from(args: argparse.Namespace) -> Settings:
    """Settings from the environment, then flags on top (flags win)."""
    overrides: dict[str, Any] = {}
    for flag, key in [
        ("mode", "zenoh_mode"),
        ("listen", "zenoh_listen"),
        ("connect", "zenoh_connect"),
        ("zenoh_config", "zenoh_config"),
        ("http_host", "http_host"),
        ("http_port", "http_port"),
        ("prefix", "prefix"),
        ("sites", "sites"),
        ("method", "method"),
        ("window", "window_s"),
        ("initiator", "initiator"),
        ("radars", "radars"),
        ("partition", "partition"),
        ("log_level", "log_level"),
        ("config", "config"),
        ("state_dir", "state_dir"),
    ]:
        value = getattr(args, flag, None)
        if value is not None:
            overrides[key] = value
    return Settings(**overrides)


def partition_main(args: argparse.Namespace) -> int:
    """``topofusion partition --count N``: each worker's radars and radar pairs (rendezvous
    hashing, docs/contract.md §4.6), with each worker's share."""
    import itertools

    from service.config import load_sites
    from service.pipeline.partition import Partition

    if args.count < 1:
        print("--count must be at least 1", file=sys.stderr)
        return 2
    ids = list(args.ids)
    if args.sites:
        ids += [s.radar_id for s in load_sites(args.sites)]
    ids = sorted(set(ids))
    if not ids:
        print("give radar ids or --sites FILE", file=sys.stderr)
        return 2
    pairs = list(itertools.combinations(ids, 2))
    for k in range(1, args.count + 1):
        p = Partition(k, args.count)
        radars = [i for i in ids if p.owns(i)]
        owned = [f"{a}/{b}" for a, b in pairs if p.owns_pair(a, b)]
        print(f"worker {k}/{args.count}: {len(radars)} radars, {len(owned)} of {len(pairs)} pairs")
        print(f"  radars: {' '.join(radars) or '-'}")
        print(f"  pairs:  {' '.join(owned) or '-'}")
    return 0


def config_main(args: argparse.Namespace) -> int:
    """``topofusion config --show``: the effective engine configuration (file, environment,
    settings and defaults), validated; exit 2 with the key named when it is not valid."""
    import json

    from service.config import as_dict

    data = as_dict(engine_config(settings_from(args)))
    if not args.show:
        print("configuration is valid (use --show to print it)", file=sys.stderr)
        return 0
    if args.format == "json":
        print(json.dumps(data, indent=2))
    else:
        import yaml

        print(yaml.safe_dump(data, sort_keys=False), end="")
    return 0


def zenoh_options(settings: Settings, default_mode: str = "peer") -> ZenohOptions:
    """The Zenoh options of the settings; ``default_mode`` where neither a flag, a setting nor
    the config file gives one (peer for the service, client for the tools)."""
    return ZenohOptions(
        mode=settings.zenoh_mode,
        listen=tuple(settings.zenoh_listen) if settings.zenoh_listen is not None else None,
        connect=tuple(settings.zenoh_connect),
        config_file=settings.zenoh_config,
        default_mode=default_mode,
    )


def _setup_logging(level: str) -> None:
    logging.basicConfig(
        level=level.upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def serve(settings: Settings, demo: argparse.Namespace | None = None) -> int:
    """Run the service (and for ``demo`` the simulator) until SIGINT/SIGTERM."""
    import uvicorn

    from service.api.app import create_app
    from service.api.server import fit_file_limit, server_config
    from service.transport.node import ServiceNode

    config = engine_config(settings)
    # before Zenoh and the worker open theirs: the limits must fit the open-file limit
    limits = fit_file_limit(http_limits(settings))
    options = zenoh_options(settings)
    extras = _DemoExtras(demo, settings.prefix) if demo is not None else None

    # Open Zenoh before the HTTP server, so that a configuration Zenoh refuses is one clear
    # error line; a router that cannot be reached yet is waited for (the node retries).
    try:
        node = ServiceNode(
            config,
            options,
            queue_size=settings.queue_size,
            queue_bytes=settings.queue_bytes,
            queue_wait_s=settings.queue_wait_s,
            radars=tuple(settings.radars),
            correlation_process=settings.correlation_process,
            peer_grace_s=settings.peer_grace_s,
            stop_grace_s=settings.stop_grace_s,
            stall_s=settings.stall_s,
            state=_state_keeper(settings, config),
        )
    except OSError as exc:  # the state directory (the only file the node itself opens)
        if settings.state_dir is None:
            raise
        why = exc.strerror or exc
        raise RuntimeError(f"state directory {settings.state_dir} cannot be used: {why}") from exc
    node.open()

    def node_factory() -> ServiceNode:
        return node

    app = create_app(
        node_factory,
        on_started=extras.start if extras else None,
        on_stopping=extras.stop if extras else None,
        api_token=settings.api_token.get_secret_value() if settings.api_token else None,
        limits=limits,
    )

    class Server(uvicorn.Server):
        def handle_exit(self, sig: int, frame: Any) -> None:
            # Take no more input the moment the signal comes: the HTTP server first closes
            # its connections, and only then does the lifespan stop the node.
            node.stop_input()
            super().handle_exit(sig, frame)

    def fatal(reason: str) -> None:
        server.should_exit = True  # (uvicorn's main loop looks at it every 0.1 s)

    node.on_fatal = fatal
    server = Server(
        # the request-head timeout, the connection cap, keep-alive and backlog (server.py)
        server_config(
            app,
            limits,
            host=settings.http_host,
            port=settings.http_port,
            log_level=settings.log_level.lower(),
            access_log=False,
            lifespan="on",
            timeout_graceful_shutdown=3,
        )
    )
    log.info("HTTP side port on http://%s:%d (docs at /docs)", settings.http_host, settings.http_port)
    # uvicorn handles SIGINT/SIGTERM itself, then re-raises the signal to the handlers it found:
    # make those no-ops so that a graceful shutdown ends with exit status 0.
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: None)
    try:
        server.run()
    finally:
        node.stop()  # idempotent: the lifespan stopped it unless uvicorn failed before it ran
    if node.failure:
        print(f"topofusion: {node.failure}", file=sys.stderr)
        return 2  # Zenoh refused the configuration once the router answered (contract §3)
    if not server.started:
        return 1  # start-up failed (e.g. port in use or Zenoh refused): uvicorn logged why
    return 0


def _state_keeper(settings: Settings, config: Any) -> Any:
    """The ``--state-dir`` keeper of this worker, or None."""
    if settings.state_dir is None:
        return None
    from service.state import StateKeeper

    return StateKeeper(settings.state_dir, config.prefix, str(config.partition), settings.state_interval_s)


class _DemoExtras:
    """The demo's simulator thread and its one-line progress report."""

    def __init__(self, args: argparse.Namespace, prefix: str) -> None:
        # The lab is imported here, before Zenoh and the HTTP server start, so that its absence
        # is one clear error rather than a failure inside the server's start-up hook.
        with lab_imports("demo"):
            from topofusion_lab.publisher import publish_scenario

        self.publish_scenario = publish_scenario
        self.scenario = scenario_for(args, "demo")
        self.speed = args.speed
        self.seed = args.seed
        self.prefix = prefix
        self.stop_event = threading.Event()
        self.threads: list[threading.Thread] = []

    def start(self, node: Any) -> None:
        publish_scenario = self.publish_scenario

        def simulate() -> None:
            try:
                publish_scenario(
                    node.session,
                    self.scenario,
                    self.prefix,
                    self.speed,
                    self.seed,
                    self.stop_event,
                    site_every_s=SIMULATE_SITE_EVERY_S,  # a recorder joining later learns them too
                )
            except Exception:
                if not self.stop_event.is_set():
                    log.exception("simulator failed")

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
    knows the simulator's truth; no algorithm ever reads it)."""
    truth = {
        (rid, str(tid)): t
        for rid, (_, table) in snapshot.tracks.items()
        for tid, t in zip(table.track_id, table.truth_id, strict=True)
    }
    return sum(
        truth.get((ps["radar_a"], p["track_a"])) is not None
        and truth.get((ps["radar_a"], p["track_a"])) == truth.get((ps["radar_b"], p["track_b"]))
        for ps in snapshot.pair_sets(status="confirmed")
        for p in ps["pairs"]
    )


def scenario_for(args: argparse.Namespace, command: str) -> Any:
    """The named scenario, starting at ``--start-time`` (default: now, whole seconds)."""
    from dataclasses import replace

    with lab_imports(command):
        from topofusion_lab.scenarios.catalog import get_scenario

    scenario = get_scenario(args.scenario)
    start = args.start_time if args.start_time is not None else float(int(time.time()))
    scenario = replace(scenario, start_time_s=start)
    if getattr(args, "duration", None) is not None:
        scenario = replace(scenario, duration_s=args.duration)
    return scenario


def simulate_main(args: argparse.Namespace) -> int:
    """``topofusion simulate`` (topofusion_lab.simulate): the arguments are judged before any
    Zenoh connection, so that a mistake ends the command at once."""
    from service.transport.session import open_tool_session

    with lab_imports("simulate"):
        from topofusion_lab.simulate import check_arguments, run_simulation
    # a resumed run's start comes from the service; until then the scenario starts now
    resume = args.start_time == "resume"
    scenario = scenario_for(
        argparse.Namespace(**{**vars(args), "start_time": None if resume else args.start_time}), "simulate"
    )
    settings = settings_from(args)
    check_arguments(args)
    options = zenoh_options(settings, default_mode="client")
    stop = _stop_on_signals()
    return run_simulation(
        args, scenario, settings.prefix, lambda: open_tool_session(options, "simulate"), stop
    )


def _stop_on_signals() -> threading.Event:
    stop = threading.Event()

    def handler(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


STUDIES = ("initiation", "correlation", "dense", "adsb", "system")


def evaluate_main(args: argparse.Namespace) -> int:
    """Run the studies; each writes ``{study}.md`` and its PNGs; ``REPORT.md`` joins them."""
    studies = [args.only] if args.only else list(STUDIES)
    with lab_imports("evaluate"):  # before anything is written
        modules = {name: importlib.import_module(f"{LAB_PACKAGE}.evaluation.{name}") for name in studies}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cmd = " ".join(["topofusion evaluate", *getattr(args, "argv", [])])
    for name, module in modules.items():
        print(f"evaluate: {name} ...", file=sys.stderr, flush=True)
        t0 = time.monotonic()
        section = module.run(
            out, runs=args.runs, seed=args.seed, progress=lambda m: print(m, file=sys.stderr)
        )
        took = time.monotonic() - t0
        (out / f"{name}.md").write_text(f"{section}\n\n_Made by `{cmd}` in {took:.0f} s._\n")
    parts = [(out / f"{n}.md").read_text() for n in STUDIES if (out / f"{n}.md").is_file()]
    report = out / "REPORT.md"
    report.write_text("# TopoFusion evaluation\n\n" + "\n\n".join(parts))
    print(f"evaluate: wrote {report}", file=sys.stderr)
    return 0


def schemas_main(args: argparse.Namespace) -> int:
    from service.schema_files import write_schemas

    written = write_schemas(Path(args.out))
    print(f"schemas: wrote {len(written)} files into {args.out}", file=sys.stderr)
    return 0


def healthcheck_main(settings: Settings) -> int:
    import urllib.request

    host = "127.0.0.1" if settings.http_host in ("0.0.0.0", "::", "") else settings.http_host
    try:
        with urllib.request.urlopen(f"http://{host}:{settings.http_port}/healthz", timeout=2) as resp:
            return 0 if resp.status == 200 else 1
    except OSError as exc:
        print(f"healthcheck: {exc}", file=sys.stderr)
        return 1


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    args.argv = argv[1:]  # the command's own arguments, e.g. quoted in the evaluation report
    try:
        if args.command in ("run", "demo"):
            settings = settings_from(args)
            _setup_logging(settings.log_level)
            return serve(settings, demo=args if args.command == "demo" else None)
        _setup_logging(os.environ.get("TOPOFUSION_LOG_LEVEL", "INFO"))
        if args.command == "simulate":
            return simulate_main(args)
        if args.command in ("record", "replay"):
            from service import recording

            settings = settings_from(args)
            args.prefix = settings.prefix
            fn = recording.record_main if args.command == "record" else recording.replay_main
            return int(fn(args, zenoh_options(settings, default_mode="client")))
        if args.command == "assess":
            from service.recording.assess import assess_main

            return assess_main(args)
        if args.command == "asterix":
            from service.asterix.command import asterix_main

            settings = settings_from(args)
            options = zenoh_options(settings, default_mode="client")
            return asterix_main(args, options, settings.prefix, settings.sites, _stop_on_signals())
        if args.command == "evaluate":
            return evaluate_main(args)
        if args.command == "schemas":
            return schemas_main(args)
        if args.command == "partition":
            return partition_main(args)
        if args.command == "config":
            return config_main(args)
        if args.command == "healthcheck":
            return healthcheck_main(Settings())
    except ValidationError as exc:
        print(f"topofusion: invalid setting: {exc}", file=sys.stderr)
        return 2
    except LabMissingError as exc:
        print(f"topofusion: {exc}", file=sys.stderr)
        return 2
    except (ValueError, OSError, RuntimeError) as exc:  # ConfigError is a ValueError
        print(f"topofusion: {exc}", file=sys.stderr)
        return 2
    parser.error(f"unknown command {args.command}")
    return 2
