"""The Zenoh session: its configuration from the contract's flags and settings, opening it
(with back-off while a router cannot be reached), and the service's :class:`Connection`."""

from __future__ import annotations

import json
import logging
import math
import re
import socket
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import orjson
import zenoh

if TYPE_CHECKING:
    from service.settings import Settings

log = logging.getLogger(__name__)

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

    @classmethod
    def from_settings(cls, settings: Settings, default_mode: str = "peer") -> ZenohOptions:
        """The Zenoh options of the settings, checked (:meth:`checked`); ``default_mode`` where
        neither a flag, a setting nor the config file gives one (peer for the service, client
        for the tools)."""
        return cls(
            mode=settings.zenoh_mode,
            listen=tuple(settings.zenoh_listen) if settings.zenoh_listen is not None else None,
            connect=tuple(settings.zenoh_connect),
            config_file=settings.zenoh_config,
            default_mode=default_mode,
        ).checked()

    def checked(self) -> ZenohOptions:
        """These options, once Zenoh has taken their configuration (:func:`zenoh_config`:
        ``ValueError`` or ``FileNotFoundError`` saying what it refused)."""
        zenoh_config(self)
        return self

    def _file_config(self) -> zenoh.Config | None:
        if self.config_file is None:
            return None
        if not Path(self.config_file).is_file():
            raise FileNotFoundError(f"zenoh config file {self.config_file}: no such file (or not a file)")
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


#: The keys of a Zenoh config's TLS files (``transport/link/tls/...``), paths on this machine.
TLS_FILE_KEYS = (
    "root_ca_certificate",
    "listen_private_key",
    "listen_certificate",
    "connect_private_key",
    "connect_certificate",
)

#: Where Zenoh's messages name its own sources: `` at /path/to/file.rs:123.``
_RUST_LOCATION = re.compile(r"\s+at \S+\.rs:\d+\.?")


#: A line of a config file a JSON5 error quotes (``1 | {...}``, `` | ^---``): it may hold a
#: password, so it is left out.
_QUOTED_LINE = re.compile(r"^\s*\d*\s*\|.*$", re.MULTILINE)


def zenoh_error_text(exc: Exception) -> str:
    """Zenoh's error on one line, without the places in its own sources it names or the lines
    of the config file it quotes."""
    return " ".join(_QUOTED_LINE.sub("", _RUST_LOCATION.sub("", str(exc))).split())[:500]


def zenoh_config(options: ZenohOptions) -> zenoh.Config:
    """A ``zenoh.Config``: the JSON5 file (optional) with the resolved endpoints.

    Multicast scouting is off unless the config file sets it (contract §3).  Raises
    ``ValueError`` naming what Zenoh refused (a file it cannot parse, an unknown key, an
    endpoint of the wrong form) and ``FileNotFoundError`` naming a TLS file of the config that
    is not there, before any session is tried: a client would otherwise retry for ever, and
    the router be blamed for refusing it.
    """
    try:
        r = options.resolved
        conf = options._file_config() or zenoh.Config()
        conf.insert_json5("mode", json.dumps(r.mode))
        conf.insert_json5("listen/endpoints", json.dumps(list(r.listen)))
        conf.insert_json5("connect/endpoints", json.dumps(list(r.connect)))
        if not r.multicast_from_file:
            conf.insert_json5("scouting/multicast/enabled", "false")
        tls = {key: json.loads(conf.get_json(f"transport/link/tls/{key}")) for key in TLS_FILE_KEYS}
    except (ValueError, OSError):
        raise
    except Exception as exc:  # zenoh raises ZError, a plain Exception subclass
        raise ValueError(f"invalid Zenoh configuration: {zenoh_error_text(exc)}") from None
    for key, path in tls.items():
        if isinstance(path, str) and not Path(path).is_file():
            raise FileNotFoundError(f"zenoh config transport/link/tls/{key}: no such file {path}")
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


def json_replies(replies: Iterable[zenoh.Reply]) -> Iterator[dict[str, Any]]:
    """The JSON objects among the replies to a ``get`` (error replies, payloads that are not
    JSON and JSON that is not an object are passed over)."""
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            body = orjson.loads(reply.ok.payload.to_bytes())
        except orjson.JSONDecodeError:
            continue
        if isinstance(body, dict):
            yield body


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
                text = zenoh_error_text(exc)
                hint = (
                    " (another endpoint with --listen or TOPOFUSION_ZENOH_LISTEN)"
                    if "address already in use" in text.lower()
                    else ""
                )
                raise RuntimeError(
                    f"cannot open Zenoh session (mode={options.effective_mode}, "
                    f"listen={options.effective_listen()}, connect={options.effective_connect()}): "
                    f"{text}{hint}"
                ) from exc
            wait = min(wait, left)
            if on_retry is not None:
                on_retry(zenoh_error_text(exc), wait)
            if stop is None:
                time.sleep(wait)
            elif stop.wait(wait):
                raise OpenCancelledError from exc
            conf = zenoh_config(options)  # a config is consumed by an attempt
            wait = min(2 * wait, RETRY_MAX_S)


def open_tool_session(options: ZenohOptions, name: str, stop: threading.Event | None = None) -> zenoh.Session:
    """A tool's session (record, replay, simulate): a client waits for its router up to
    ``TOOL_CONNECT_RETRY_S``, saying so on stderr; other modes fail at once.  ``stop`` set (a
    signal) ends the waiting with :class:`OpenCancelledError`."""
    import sys

    def say(reason: str, wait_s: float) -> None:
        print(f"{name}: waiting for the Zenoh router ({reason}); retrying in {wait_s:.1f} s", file=sys.stderr)

    retry = TOOL_CONNECT_RETRY_S if options.effective_mode == "client" else 0.0
    return open_session(options, retry_for_s=retry, on_retry=say, stop=stop)


#: How often (s) the watcher looks at the Zenoh connection: a lost router shows within this.
CONNECTION_POLL_S = 0.25


class Connection:
    """The service's session: given, opened at once, or, while the router cannot be reached, by
    a connector thread with back-off (``connecting``); then watched (``linked``: ``/readyz``
    says ``no zenoh connection`` while a client or a peer with connect endpoints has lost them
    all; both changes are logged).

    ``stopping`` is the node's stop (it ends the connector and the watcher); ``life`` its lock
    of start and stop, under which the connector hands its session over (``on_open``).
    ``on_failure(reason)`` hears of a failure that is not "unreachable" (a configuration Zenoh
    refused once the router answered): ``failure`` says why.
    """

    def __init__(
        self,
        options: ZenohOptions,
        session: zenoh.Session | None,
        stopping: threading.Event,
        life: threading.Lock,
        on_failure: Callable[[str], None],
    ) -> None:
        self.options = options
        self.session = session
        self._own = session is None
        self._stopping = stopping
        self._life = life
        self._on_failure = on_failure
        #: Why the session could not be opened (a configuration Zenoh refused), or "".
        self.failure = ""
        self.connecting = False
        #: Whether the session reaches what it must (:meth:`linked_now`): the watcher's view.
        self.linked = True

    def open(self) -> bool:
        """Open the session (if not given one): True when open, False when the router cannot
        be reached yet; raises ``RuntimeError`` saying why for any other failure."""
        if self.session is None:
            try:
                self.session = open_session(self.options)
            except RuntimeError as exc:
                if not unreachable(exc):
                    raise
                log.warning("%s; retrying with back-off", exc)
                return False
        return True

    def connect_later(self, on_open: Callable[[], None]) -> None:
        """Start the connector: it opens the session with back-off until the router answers
        (or a stop), then calls ``on_open`` under ``life``."""
        self.connecting = True
        threading.Thread(
            target=self._connect, args=(on_open,), name="topofusion-connect", daemon=True
        ).start()

    def _connect(self, on_open: Callable[[], None]) -> None:
        def say(reason: str, wait_s: float) -> None:
            up = listening(self.options.effective_connect())
            if up:
                log.warning(
                    "zenoh router at %s accepts connections but refused the session (a TLS "
                    "certificate, user or password it does not take, or not a Zenoh router): %s; "
                    "retrying in %.1f s",
                    ", ".join(up),
                    reason,
                    wait_s,
                )
            else:
                log.warning("zenoh router not reachable (%s); retrying in %.1f s", reason, wait_s)

        try:
            session = open_session(
                self.options, math.inf, on_retry=say, retry_if=unreachable, stop=self._stopping
            )
        except OpenCancelledError:
            return
        except RuntimeError as exc:
            self.failure = str(exc)
            log.error("%s", exc)
            self._on_failure(self.failure)
            return
        finally:
            self.connecting = False
        with self._life:
            if self._stopping.is_set():
                session.close()  # a stop came while the last attempt was under way
                return
            self.session = session
            log.info("zenoh router reached")
            on_open()

    def describe(self) -> str:
        """``mode=..., listen=[...], connect=[...]`` (the log's)."""
        o = self.options
        return f"mode={o.effective_mode}, listen={o.effective_listen()}, connect={o.effective_connect()}"

    def linked_now(self) -> bool:
        """Whether the session reaches a router or peer, where it must: a client always, a
        peer or router only when told to connect somewhere (one with no connect endpoint
        stands alone, and its publishers connect to it)."""
        session = self.session
        if session is None:
            return False
        if self.options.effective_mode != "client" and not self.options.effective_connect():
            return True
        try:
            info = session.info
            return bool(info.routers_zid()) or bool(info.peers_zid())
        except Exception:  # the session is closing
            return False

    def watch(self) -> None:
        """Start the watcher (until the stop)."""
        self.linked = self.linked_now()
        threading.Thread(target=self._watch, name="topofusion-watch", daemon=True).start()

    def _watch(self) -> None:
        """Follow the connection (wall clock, operations); say when it is lost and back."""
        lost_at = 0.0
        while not self._stopping.wait(CONNECTION_POLL_S):
            linked = self.linked_now()
            if linked == self.linked:
                continue
            self.linked = linked
            if not linked:
                lost_at = time.monotonic()
                log.error(
                    "zenoh connection lost: no router or peer of %s reachable; /readyz is 503 "
                    "until it is back (inputs published meanwhile do not arrive: seq gaps count them)",
                    self.options.effective_connect() or "the session",
                )
            else:
                log.warning("zenoh connection back after %.1f s", time.monotonic() - lost_at)

    def close(self) -> None:
        """Close the session if this opened it; none is held after."""
        if self._own and self.session is not None:
            self.session.close()
        self.session = None
