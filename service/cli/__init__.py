"""``topofusion`` command line (contract §3, "Command line"), one module per command group.

:mod:`~service.cli.serve` (``run``), :mod:`~service.cli.tools` (``record``, ``replay``,
``assess``, ``asterix``) and :mod:`~service.cli.admin` (``healthcheck``, ``config``,
``partition``, ``schemas``) are the runtime's; other distributions add theirs through entry
points (:mod:`~service.cli.groups`: the lab's ``demo``, ``simulate`` and ``evaluate``).  Each
group parses its own flags; :func:`main` runs the chosen command's handler.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

from pydantic import ValidationError

from service.cli import admin, groups, serve, tools
from service.cli.common import invalid_settings, settings_from, setup_logging, zenoh_options

__all__ = ["build_parser", "invalid_settings", "main", "settings_from", "zenoh_options"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="topofusion",
        description="Radar track correlation under unknown sensor bias, over Eclipse Zenoh.",
        formatter_class=argparse.RawDescriptionHelpFormatter,  # the groups' notes come wrapped
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    serve.register(commands)
    parser.epilog = groups.register(commands)
    tools.register(commands)
    admin.register(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    args.argv = argv[1:]  # the command's own arguments, e.g. quoted in the evaluation report
    if getattr(args, "handler", None) is None:  # a group's command not added by add_command
        parser.error(f"command {args.command} has no handler")
    try:
        if not args.own_logging:
            setup_logging(os.environ.get("TOPOFUSION_LOG_LEVEL", "INFO"))
        return int(args.handler(args))
    except ValidationError as exc:
        print(f"topofusion: {invalid_settings(exc)}", file=sys.stderr)
        return 2
    except (ValueError, OSError, RuntimeError) as exc:  # ConfigError is a ValueError
        print(f"topofusion: {exc}", file=sys.stderr)
        return 2
