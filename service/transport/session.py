"""Building a Zenoh session configuration from the contract's flags."""

from __future__ import annotations

import json
import re
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import zenoh

#: The contract's default listen endpoint for `peer` and `router` modes.
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
MODES = ("peer", "client", "router")


@dataclass(frozen=True)
class Resolved:
    """The endpoints in force: flags over the config file over the defaults."""

    mode: str
    listen: tuple[str, ...]
    connect: tuple[str, ...]
    multicast_from_file: bool


@dataclass(frozen=True)
class ZenohOptions:
    """The Zenoh part of every command's flags (docs/contract.md §3).

    Each of ``mode``, ``listen`` and ``connect`` left unset (None, or no connect endpoint) is
    taken from the config file when it sets it, else from the default: ``default_mode`` (peer
    for the service, client for the tools) and the contract's listen endpoint for peer and
    router.
    """

    mode: str | None = None
    listen: tuple[str, ...] | None = None
    connect: tuple[str, ...] = ()
    config_file: Path | None = None
    default_mode: str = "peer"

    def _file_config(self) -> zenoh.Config | None:
        if self.config_file is None:
            return None
        if not Path(self.config_file).is_file():
            raise FileNotFoundError(f"zenoh config file not found: {self.config_file}")
        return zenoh.Config.from_file(str(self.config_file))

    @cached_property
    def resolved(self) -> Resolved:
        file = self._file_config()

        def from_file(key: str) -> object:
            # An unset key reads as null; listen endpoints unset read as zenoh's per-mode table.
            return json.loads(file.get_json(key)) if file is not None else None

        mode = self.mode or from_file("mode") or self.default_mode
        if mode not in MODES:
            raise ValueError(f"zenoh mode must be one of {', '.join(MODES)}, got {mode!r}")
        file_listen = from_file("listen/endpoints")
        if self.listen is not None:
            listen = tuple(self.listen)
        elif isinstance(file_listen, list):
            listen = tuple(file_listen)
        else:
            listen = () if mode == "client" else (DEFAULT_LISTEN,)
        file_connect = from_file("connect/endpoints")
        connect = tuple(self.connect) or tuple(file_connect if isinstance(file_connect, list) else ())
        multicast = from_file("scouting/multicast/enabled")
        return Resolved(str(mode), listen, connect, multicast is not None)

    @property
    def effective_mode(self) -> str:
        return self.resolved.mode

    def effective_listen(self) -> list[str]:
        return list(self.resolved.listen)

    def effective_connect(self) -> list[str]:
        return list(self.resolved.connect)


def zenoh_config(options: ZenohOptions) -> zenoh.Config:
    """A ``zenoh.Config``: the JSON5 file (optional) with the resolved endpoints.

    Multicast scouting is off unless the config file sets it (contract §3).
    """
    r = options.resolved
    conf = options._file_config() or zenoh.Config()
    conf.insert_json5("mode", json.dumps(r.mode))
    conf.insert_json5("listen/endpoints", json.dumps(list(r.listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(r.connect)))
    if not r.multicast_from_file:
        conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


#: How long the tools (record, replay, simulate) keep trying to reach their router when it is
#: not there yet (s): long enough for a router started alongside, short enough to say why.
TOOL_CONNECT_RETRY_S = 30.0
#: First and longest wait between two attempts (s); the wait doubles each time.
RETRY_FIRST_S, RETRY_MAX_S = 0.2, 5.0


#: Zenoh's message when none of a client's connect endpoints answers (a router not up yet,
#: or one that refuses this client's credentials: Zenoh does not tell them apart).
UNREACHABLE = "Unable to connect"


class OpenCancelledError(Exception):
    """The ``stop`` event of :func:`open_session` was set while it waited to try again."""


def unreachable(exc: Exception) -> bool:
    """Whether an open failed only because no endpoint answered (worth trying again)."""
    return UNREACHABLE in str(exc)


#: ``tcp/`` and ``tls/`` endpoints (with an optional ``#...`` metadata tail): host and port.
_STREAM_ENDPOINT = re.compile(r"^(?:tcp|tls)/\[?([^\]#]+?)\]?:(\d+)(?:#.*)?$")


def listening(endpoints: list[str], timeout_s: float = 0.5) -> list[str]:
    """The TCP/TLS endpoints among ``endpoints`` that accept a TCP connection.  When Zenoh
    cannot open a session although one does, the router is up and refuses this client (its
    TLS certificate, user or password), or it is no Zenoh router: Zenoh says "unable to
    connect" either way, so the log says which it is."""
    found = []
    for endpoint in endpoints:
        m = _STREAM_ENDPOINT.match(endpoint)
        if m is None:
            continue
        try:
            with socket.create_connection((m.group(1), int(m.group(2))), timeout=timeout_s):
                found.append(endpoint)
        except OSError:
            continue
    return found


def open_session(
    options: ZenohOptions,
    retry_for_s: float = 0.0,
    on_retry: Callable[[str, float], None] | None = None,
    retry_if: Callable[[Exception], bool] = lambda exc: True,
    stop: threading.Event | None = None,
) -> zenoh.Session:
    """Open a session; raises a ``RuntimeError`` naming the endpoints when Zenoh refuses.

    ``retry_for_s``: keep trying that long (a router not up yet; ``math.inf``: until it is
    up), waiting ``RETRY_FIRST_S`` then twice as long each time, at most ``RETRY_MAX_S``;
    ``on_retry(reason, wait_s)`` hears of each failed attempt.  Only failures ``retry_if``
    accepts are tried again; an invalid configuration never is.  ``stop``: set, it ends the
    waiting with :class:`OpenCancelledError`.
    """
    conf = zenoh_config(options)
    deadline = time.monotonic() + retry_for_s
    wait = RETRY_FIRST_S
    while True:
        try:
            return zenoh.open(conf)
        except Exception as exc:  # zenoh raises ZError, a plain Exception subclass
            left = deadline - time.monotonic()
            if left <= 0 or not retry_if(exc):
                raise RuntimeError(
                    f"cannot open Zenoh session (mode={options.effective_mode}, "
                    f"listen={options.effective_listen()}, connect={options.effective_connect()}): {exc}"
                ) from exc
            wait = min(wait, left)
            if on_retry is not None:
                on_retry(str(exc).split("  at ")[0], wait)
            if stop is None:
                time.sleep(wait)
            elif stop.wait(wait):
                raise OpenCancelledError from exc
            conf = zenoh_config(options)  # a config is consumed by an attempt
            wait = min(2 * wait, RETRY_MAX_S)


def open_tool_session(options: ZenohOptions, name: str) -> zenoh.Session:
    """A tool's session (record, replay, simulate): a client waits for its router up to
    ``TOOL_CONNECT_RETRY_S``, saying so on stderr; other modes fail at once."""
    import sys

    def say(reason: str, wait_s: float) -> None:
        print(f"{name}: waiting for the Zenoh router ({reason}); retrying in {wait_s:.1f} s", file=sys.stderr)

    retry = TOOL_CONNECT_RETRY_S if options.effective_mode == "client" else 0.0
    return open_session(options, retry_for_s=retry, on_retry=say)
