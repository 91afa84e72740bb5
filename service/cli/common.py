"""What the command groups share: how a subcommand is added, the Zenoh flags, the settings.

A group module has ``register(commands)``, which adds its subcommands to the ``topofusion``
parser's subparsers with :func:`add_command`; :func:`service.cli.main` parses the command line
and calls the chosen subcommand's handler with the parsed arguments.  Other distributions add
groups the same way (:mod:`service.cli.groups`).
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any

from pydantic import ValidationError

from service.settings import REDACTED, SECRET_SETTINGS, Settings, flag_overrides, normal_log_level
from service.transport.session import MODES, ZenohOptions

#: A subcommand's handler: the parsed arguments in, the exit status out.
Handler = Callable[[argparse.Namespace], int]
#: What ``ArgumentParser.add_subparsers()`` returns: where a group adds its subcommands.
Commands = argparse._SubParsersAction  # (argparse names no public type for it)


def add_command(
    commands: Commands, name: str, handler: Handler, *, own_logging: bool = False, **kwargs: Any
) -> argparse.ArgumentParser:
    """Add subcommand ``name`` (``kwargs`` as for ``add_parser``, e.g. its ``help``), run by
    ``handler``.  :func:`service.cli.main` sets logging up from ``TOPOFUSION_LOG_LEVEL`` before
    the handler runs, unless ``own_logging`` (the handler does, from its settings)."""
    parser: argparse.ArgumentParser = commands.add_parser(name, **kwargs)
    parser.set_defaults(handler=handler, own_logging=own_logging)
    return parser


def zenoh_flags(p: argparse.ArgumentParser, default_mode: str) -> None:
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


def settings_from(args: argparse.Namespace) -> Settings:
    """The settings: defaults, the config file, the environment, then the flags on top (flags
    win; :meth:`Settings.load`)."""
    return Settings.load(overrides=flag_overrides(args))


def zenoh_options(settings: Settings, default_mode: str = "peer") -> ZenohOptions:
    """The Zenoh options of the settings (:meth:`ZenohOptions.from_settings`)."""
    return ZenohOptions.from_settings(settings, default_mode)


def setup_logging(level: str) -> None:
    try:
        name = normal_log_level(level)  # (as the setting takes it)
    except ValueError as exc:
        raise ValueError(f"log level (--log-level, TOPOFUSION_LOG_LEVEL) {level.strip()!r}: {exc}") from None
    logging.basicConfig(
        level=name,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM (the tools stop cleanly on either)."""
    stop = threading.Event()

    def handler(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


def invalid_settings(exc: ValidationError) -> str:
    """A settings error on one line: each setting with its variable, what it must be, what it
    was (pydantic's own text spans several lines and a link)."""
    parts = []
    for e in exc.errors(include_url=False):
        loc = ".".join(str(p) for p in e["loc"])
        name = f"{loc} (TOPOFUSION_{loc.upper()})" if exc.title == "Settings" and loc else loc or exc.title
        # A rule over several settings names them itself, and its input is every setting
        # given, secrets among them: only one setting's own value is quoted, never a secret's.
        value = REDACTED if loc in SECRET_SETTINGS else repr(e.get("input"))
        got = f", got {value}" if loc else ""
        parts.append(f"{name}: {' '.join(e['msg'].split())}{got}")
    return "invalid setting " + "; ".join(parts)
