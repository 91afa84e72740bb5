"""The HTTP side port's limits (``TOPOFUSION_HTTP_*``, docs/operations/http.md), in one value.

Kept apart from the server (service/api/server.py) so that the app and the picture's feed take
them without importing uvicorn's protocol classes.
"""

from __future__ import annotations

from dataclasses import dataclass

from service.settings import PROBE_ROOM, Settings

#: The limits that must be above zero.
POSITIVE = (
    "header_timeout_s",
    "keep_alive_s",
    "max_requests",
    "backlog",
    "picture_max_clients",
    "picture_backlog",
)


@dataclass(frozen=True)
class HttpLimits:
    """What the HTTP side port allows; the defaults are the settings' (service/settings.py)."""

    #: A connection must deliver a whole request head (request line and headers) within this
    #: many seconds of being opened, and of its previous response ending; else it is closed.
    header_timeout_s: float = 10.0
    #: A kept-alive connection on which nothing arrives for this many seconds is closed.
    keep_alive_s: float = 5.0
    #: Open connections at most; at the cap a new one closes the connection that has waited
    #: longest for a request head, or is refused (503) when none is waiting.
    max_connections: int = 512
    #: Requests in progress at most, probes and picture streams aside; beyond: 503.
    max_requests: int = 64
    #: The listening socket's backlog (connections the kernel holds before they are accepted),
    #: and so the most the server accepts in one go.
    backlog: int = 128
    #: Picture feed clients (``GET /picture/events``) at most; beyond: 503.
    picture_max_clients: int = 256
    #: A picture client that has not taken an event within this many of its intervals (events
    #: it is behind) is dropped.
    picture_backlog: int = 3
    #: The kernel send buffer of a picture viewer's connection (bytes): with one event in the
    #: server, all a viewer that does not read can hold.
    picture_send_buffer: int = 256 * 1024
    #: Bytes per second the picture's viewers get together at most: beyond, every viewer's
    #: interval is stretched by the same power of two (up to 16).
    picture_max_bytes_s: int = 16 * 1024 * 1024

    def __post_init__(self) -> None:
        problems = [f"{name} must be positive" for name in POSITIVE if getattr(self, name) <= 0]
        if self.max_connections < self.busy_at_most + PROBE_ROOM:
            problems.append(
                f"max_connections ({self.max_connections}) must be at least max_requests "
                f"({self.max_requests}) + picture_max_clients ({self.picture_max_clients}) + "
                f"{PROBE_ROOM}, so that some connections are always free for probes"
            )
        if problems:
            raise ValueError("; ".join(problems))

    @property
    def busy_at_most(self) -> int:
        """Connections that may be in the middle of a request at once (probes aside)."""
        return self.max_requests + self.picture_max_clients


def http_limits(settings: Settings) -> HttpLimits:
    """The HTTP side port's limits of the settings."""
    return HttpLimits(
        header_timeout_s=settings.http_header_timeout_s,
        keep_alive_s=settings.http_keep_alive_s,
        max_connections=settings.http_max_connections,
        max_requests=settings.http_max_requests,
        backlog=settings.http_backlog,
        picture_max_clients=settings.http_picture_max_clients,
        picture_backlog=settings.http_picture_backlog,
        picture_max_bytes_s=settings.http_picture_max_bytes_s,
        picture_send_buffer=settings.http_picture_send_buffer,
    )
