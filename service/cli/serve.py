"""``topofusion run``: the long-running service (Zenoh session, worker, HTTP side port) until
SIGINT/SIGTERM.  :func:`serve` also runs the lab's ``demo``, with its simulator as hooks."""

from __future__ import annotations

import argparse
import gc
import logging
import signal
import sys
from collections.abc import Callable
from typing import Any, Protocol

from service.cli.common import Commands, add_command, settings_from, setup_logging, zenoh_flags
from service.settings import Settings
from service.wire.vocabulary import METHODS

log = logging.getLogger("topofusion")


class ServeHooks(Protocol):
    """What runs beside the service (``demo``'s simulator): started once the HTTP server is up,
    stopped before the node is."""

    def start(self, node: Any) -> None: ...

    def stop(self, node: Any) -> None: ...


def register(commands: Commands) -> None:
    service_flags(add_command(commands, "run", run_main, own_logging=True, help="the long-running service"))


def service_flags(p: argparse.ArgumentParser) -> None:
    """The flags of ``run`` (``demo`` takes them too)."""
    zenoh_flags(p, default_mode="peer")
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
    p.add_argument(
        "--partition-salt",
        type=int,
        metavar="S",
        help="salt of the partition's hashing (default 0), the same on every worker: "
        "`topofusion partition --balance` finds a balanced one",
    )
    p.add_argument("--log-level", help="logging level (default INFO)")
    p.add_argument("--config", metavar="FILE", help="engine parameters, TOML/YAML/JSON (see `config --show`)")
    p.add_argument(
        "--state-dir",
        metavar="DIR",
        help="keep sites, biases, registration memory, seq and the track-id epoch here across restarts",
    )


def run_main(args: argparse.Namespace) -> int:
    settings = settings_from(args)
    setup_logging(settings.log_level)
    return serve(settings)


def serve(settings: Settings, hooks: Callable[[str], ServeHooks] | None = None) -> int:
    """Run the service until SIGINT/SIGTERM; ``hooks(prefix)`` (the demo's simulator) is made
    before Zenoh and the HTTP server start, so that a mistake there is one clear error."""
    import uvicorn

    from service.api.app import create_app
    from service.api.limits import http_limits
    from service.api.server import fit_file_limit, server_config
    from service.transport.node import ServiceNode

    # before Zenoh and the worker open theirs: the limits must fit the open-file limit
    limits = fit_file_limit(http_limits(settings))
    extras = hooks(settings.prefix) if hooks is not None else None

    # The engine is built and restored first (ConfigError naming a bad parameter, RuntimeError
    # naming a state directory that cannot be used); then Zenoh opens before the HTTP server,
    # so that a configuration Zenoh refuses is one clear error line; a router that cannot be
    # reached yet is waited for (the node retries).
    node = ServiceNode.from_settings(settings)
    node.open()

    def node_factory() -> ServiceNode:
        return node

    app = create_app(
        node_factory,
        on_started=extras.start if extras else None,
        on_stopping=extras.stop if extras else None,
        api_token=api_token(settings),
        limits=limits,
    )

    class Server(uvicorn.Server):
        async def startup(self, sockets: Any = None) -> None:
            await super().startup(sockets)
            bound = [s.getsockname() for server in self.servers for s in server.sockets]
            if bound:  # (the port bound: a port of 0 is a free one, chosen now)
                host, port = bound[0][:2]
                log.info("HTTP side port on http://%s:%d (docs at /docs)", host, port)

        def handle_exit(self, sig: int, frame: Any) -> None:
            # Take no more input the moment the signal comes: the HTTP server first closes
            # its connections, and only then does the lifespan stop the node.
            node.stop_input()
            super().handle_exit(sig, frame)

    fatal_reasons: list[str] = []

    def fatal(reason: str) -> None:
        fatal_reasons.append(reason)
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
    # uvicorn handles SIGINT/SIGTERM itself, then re-raises the signal to the handlers it found:
    # make those no-ops so that a graceful shutdown ends with exit status 0.
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: None)
    # Everything allocated so far (modules, schemas, the app) lives for the whole run: out of
    # the collector's full scans, which would otherwise walk it again and again.
    gc.collect()
    gc.freeze()
    try:
        server.run()
    except SystemExit:  # uvicorn's own exit when it cannot start (status 3 since 0.x): ours is 1
        if server.started:
            raise
    finally:
        node.stop()  # idempotent: the lifespan stopped it unless uvicorn failed before it ran
    if node.failure:
        print(f"topofusion: {node.failure}", file=sys.stderr)
        return 2  # Zenoh refused the configuration once the router answered (contract §3)
    if not server.started and not fatal_reasons:
        # (uvicorn logged why, e.g. the port in use, without saying which setting to change)
        print(
            f"topofusion: the HTTP side port did not open on {settings.http_host}:{settings.http_port}: "
            "another port with --http-port (TOPOFUSION_HTTP_PORT), another address with "
            "TOPOFUSION_HTTP_HOST",
            file=sys.stderr,
        )
    if not server.started or fatal_reasons:
        return 1  # start-up failed (e.g. port in use), or a part it needs failed (a hook's)
    return 0


def api_token(settings: Settings) -> str | None:
    """The HTTP port's token, None for none (an empty one too), said at start either way: a
    secret that failed to fill in must not open the port unnoticed."""
    token = settings.api_token.get_secret_value() if settings.api_token is not None else ""
    if token:
        log.info("HTTP side port: a bearer token is asked on every route but /healthz and /readyz")
        return token
    log.info("HTTP side port: no token asked (TOPOFUSION_API_TOKEN unset or empty)")
    return None
