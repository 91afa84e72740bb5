"""Building a Zenoh session configuration from the contract's flags."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

#: The contract's default listen endpoint for `peer` and `router` modes.
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
MODES = ("peer", "client", "router")


@dataclass(frozen=True)
class ZenohOptions:
    """The Zenoh part of every command's flags (CONTRACT.md §3)."""

    mode: str = "peer"
    listen: tuple[str, ...] | None = None  # None: the mode's default
    connect: tuple[str, ...] = ()
    config_file: Path | None = None
    extra: dict[str, str] = field(default_factory=dict)  # json5 path -> json5 value

    def effective_listen(self) -> list[str]:
        if self.listen is not None:
            return list(self.listen)
        return [] if self.mode == "client" else [DEFAULT_LISTEN]


def zenoh_config(options: ZenohOptions) -> zenoh.Config:
    """A ``zenoh.Config`` from a JSON5 file (optional) overridden by the flags.

    Multicast scouting is off unless the config file turns it on (contract §3).
    """
    if options.mode not in MODES:
        raise ValueError(f"zenoh mode must be one of {', '.join(MODES)}, got {options.mode!r}")
    if options.config_file is not None:
        if not Path(options.config_file).is_file():
            raise FileNotFoundError(f"zenoh config file not found: {options.config_file}")
        conf = zenoh.Config.from_file(str(options.config_file))
        multicast_from_file = _file_sets_multicast(Path(options.config_file))
    else:
        conf = zenoh.Config()
        multicast_from_file = False
    conf.insert_json5("mode", json.dumps(options.mode))
    conf.insert_json5("listen/endpoints", json.dumps(options.effective_listen()))
    conf.insert_json5("connect/endpoints", json.dumps(list(options.connect)))
    if not multicast_from_file:
        conf.insert_json5("scouting/multicast/enabled", "false")
    for path, value in options.extra.items():
        conf.insert_json5(path, value)
    return conf


def _file_sets_multicast(path: Path) -> bool:
    text = path.read_text(encoding="utf-8")
    return "multicast" in text


def open_session(options: ZenohOptions) -> zenoh.Session:
    """Open a session; raises a ``RuntimeError`` naming the endpoints when Zenoh refuses."""
    conf = zenoh_config(options)
    try:
        return zenoh.open(conf)
    except Exception as exc:  # zenoh raises ZError, a plain Exception subclass
        raise RuntimeError(
            f"cannot open Zenoh session (mode={options.mode}, listen={options.effective_listen()}, "
            f"connect={list(options.connect)}): {exc}"
        ) from exc


def options_from_lists(
    mode: str, listen: Sequence[str] | None, connect: Sequence[str] | None, config_file: str | Path | None
) -> ZenohOptions:
    return ZenohOptions(
        mode=mode,
        listen=tuple(listen) if listen else None,
        connect=tuple(connect or ()),
        config_file=Path(config_file) if config_file else None,
    )
