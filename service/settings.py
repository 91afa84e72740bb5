"""One settings object (pydantic-settings); command-line flags override it (docs/contract.md §3)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from service.wire.vocabulary import Method, is_source_id

if TYPE_CHECKING:
    from service.api.limits import HttpLimits
    from service.engine import EngineConfig


def _split(value: object) -> object:
    if isinstance(value, str):
        return [v.strip() for v in value.split(",") if v.strip()]
    return value


class Settings(BaseSettings):
    """Every ``TOPOFUSION_*`` setting; errors name the offending variable."""

    model_config = SettingsConfigDict(env_prefix="TOPOFUSION_", extra="ignore")

    #: ``None``: the Zenoh config file's mode, else the command's default (peer for the service).
    zenoh_mode: Literal["peer", "client", "router"] | None = None
    #: ``None`` means the mode's default (none for client, the contract's endpoint otherwise).
    zenoh_listen: Annotated[list[str] | None, NoDecode] = None
    zenoh_connect: Annotated[list[str], NoDecode] = Field(default_factory=list)
    zenoh_config: Path | None = None
    http_host: str = "127.0.0.1"
    http_port: int = Field(default=8000, ge=0, le=65535)
    prefix: str = Field(default="fusion", pattern=r"^[A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*$")
    sites: Path | None = None
    method: Method = "svd-topology"
    window_s: float | None = Field(default=None, gt=0)
    initiator: str = "logic"
    #: Radars this worker owns (comma separated ids); empty: every radar under the prefix.
    #: Partitioning several workers by radar is configuration: each subscribes to its own
    #: radars, and ``get {prefix}/pairs/**`` gathers every worker's pairs.
    radars: Annotated[list[str], NoDecode] = Field(default_factory=list)
    #: ``K/N``: worker K of N on one prefix; together the N workers give the results of one
    #: (``service.pipeline.partition``: which worker owns which radar and radar pair).
    partition: str = Field(default="1/1", pattern=r"^\s*\d+\s*/\s*\d+\s*$")
    #: Capacity of the queue between Zenoh callbacks and the worker (samples).
    queue_size: int = Field(default=4096, ge=1)
    #: The same queue's capacity in payload bytes: one message of the largest size a payload
    #: may have (16 MiB, contract §3) always fits.
    queue_bytes: int = Field(default=256 * 1024 * 1024, ge=16 * 1024 * 1024)
    #: The longest a Zenoh callback waits for room in a full queue (s) before it drops the
    #: sample (counted by key): in router mode Zenoh's network thread carries everyone's
    #: traffic, and a longer wait would stall it.
    queue_wait_s: float = Field(default=0.5, ge=0, le=10)
    #: On SIGTERM/SIGINT: how long (s, wall clock) the worker may take to finish the queued
    #: input and publish its last outputs; what is left then is counted and logged.  Keep it
    #: under the container's stop timeout (the deploy files give 30 s for 20 s).
    stop_grace_s: float = Field(default=20.0, ge=0)
    #: ``/readyz`` is 503 while input has waited in the queue this long (s, wall clock) with
    #: the worker taking none of it.
    stall_s: float = Field(default=30.0, gt=0)
    #: Where what takes minutes to learn survives a restart (``service.state``); ``None``: nothing.
    state_dir: Path | None = None
    #: Data time (s) between two periodic state writes.
    state_interval_s: float = Field(default=30.0, gt=0)
    #: When set, every HTTP endpoint but ``/healthz`` and ``/readyz`` needs
    #: ``Authorization: Bearer <token>``.
    api_token: SecretStr | None = None
    log_level: str = "INFO"
    #: Engine parameter file (TOML, YAML or JSON; ``service.config``); ``None``: defaults.
    config: Path | None = None
    #: Run the correlation stage in its own process, so that tracking and correlation use two
    #: cores (same results; ``false``: one process, e.g. where processes cannot be started).
    correlation_process: bool = True
    #: Partitioned: a worker whose Zenoh liveliness token left is still waited for this long
    #: (s, wall clock) before the others correlate without its radars: a session that loses
    #: its router for a moment (a lease missed under load) must not reorder anything.
    peer_grace_s: float = Field(default=15.0, ge=0)
    # The HTTP side port's limits (service/api/limits.py, docs/operations/http.md).
    #: A connection must deliver a whole request head within this many seconds of opening,
    #: and of its previous response ending; else it is closed (uvicorn has no such timeout).
    http_header_timeout_s: float = Field(default=10.0, gt=0)
    #: A kept-alive connection with nothing arriving for this many seconds is closed.
    http_keep_alive_s: float = Field(default=5.0, gt=0)
    #: Open HTTP connections at most: at the cap a new connection closes the one that has
    #: waited longest for a request head, or is refused (503) when none is waiting.  At least
    #: ``http_max_requests + http_picture_max_clients + 16`` (so that probes always get in).
    http_max_connections: int = Field(default=512, ge=1)
    #: HTTP requests in progress at most, the probes and the picture's feed aside; beyond: 503.
    http_max_requests: int = Field(default=64, ge=1)
    #: The listening socket's backlog (connections the kernel holds before they are accepted).
    http_backlog: int = Field(default=128, ge=1)
    #: Viewers of ``/picture/events`` at most; beyond: 503.
    http_picture_max_clients: int = Field(default=256, ge=1)
    #: A picture viewer that has not taken an event within this many of its intervals is dropped.
    http_picture_backlog: int = Field(default=3, ge=1)
    #: The kernel send buffer of a picture viewer's connection (bytes): with one event in the
    #: server, all that a viewer that does not read holds until it is dropped.
    http_picture_send_buffer: int = Field(default=256 * 1024, ge=4096)
    #: Bytes per second the picture's viewers get together at most; beyond, every viewer's
    #: interval is stretched by the same power of two (up to 16), so that ingest goes first.
    http_picture_max_bytes_s: int = Field(default=16 * 1024 * 1024, ge=1)
    # Each radar's live performance against ADS-B / AIS (contract §5.3, docs/assessment.md);
    # ``None``: the engine configuration's ``assessment`` section (defaults as below).
    #: The sliding window of data time the figures cover (s; default 600).
    performance_window_s: float | None = Field(default=None, gt=0)
    #: Detection probability a radar must reach (default 0.97).
    performance_pd_min: float | None = Field(default=None, ge=0, le=1)
    #: Share of correct Mode 3/A codes a radar must reach (default 0.98).
    performance_mode_3a_min: float | None = Field(default=None, ge=0, le=1)
    #: Share of correct Mode C (within 200 ft of the reference) a radar must reach (default 0.96).
    performance_mode_c_min: float | None = Field(default=None, ge=0, le=1)

    _split_listen = field_validator("zenoh_listen", "zenoh_connect", "radars", mode="before")(_split)

    @field_validator("zenoh_config", "sites", "config", "state_dir", "api_token", mode="before")
    @classmethod
    def _empty_is_none(cls, value: object) -> object:
        # An empty variable (e.g. compose's ``${TOPOFUSION_API_TOKEN:-}``) means "not set": not
        # the working directory, not a token of length zero.
        return None if isinstance(value, str) and not value.strip() else value

    @field_validator("partition")
    @classmethod
    def _partition(cls, value: str) -> str:
        from service.pipeline.partition import Partition

        return str(Partition.parse(value))

    @field_validator("radars")
    @classmethod
    def _radar_ids(cls, value: list[str]) -> list[str]:
        bad = [r for r in value if not is_source_id(r)]
        if bad:
            raise ValueError(f"radar ids must match [A-Za-z0-9_-]{{1,64}}: {bad}")
        return value

    @model_validator(mode="after")
    def _http_connections_leave_room_for_probes(self) -> Settings:
        from service.api.limits import PROBE_ROOM

        least = self.http_max_requests + self.http_picture_max_clients + PROBE_ROOM
        if self.http_max_connections < least:
            raise ValueError(
                f"TOPOFUSION_HTTP_MAX_CONNECTIONS ({self.http_max_connections}) must be at least "
                f"TOPOFUSION_HTTP_MAX_REQUESTS + TOPOFUSION_HTTP_PICTURE_MAX_CLIENTS + {PROBE_ROOM} "
                f"({least}), so that some connections are always free for the probes"
            )
        return self


def http_limits(settings: Settings) -> HttpLimits:
    """The HTTP side port's limits of the settings."""
    from service.api.limits import HttpLimits

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


def engine_config(settings: Settings) -> EngineConfig:
    """The engine's configuration: defaults < config file < ``TOPOFUSION_ENGINE__*`` < the
    contract's flags and settings (method, window, initiator, sites, prefix, partition) where
    given.

    Raises :class:`service.config.ConfigError` naming the key of a bad value.
    """
    from service.config import engine_config_from, from_environment, load_file, load_sites, merge

    data: dict[str, object] = load_file(settings.config) if settings.config is not None else {}
    data = merge(data, from_environment())
    given = settings.model_fields_set
    for name, key in (
        ("prefix", "prefix"),
        ("method", "method"),
        ("window_s", "window_s"),
        ("initiator", "initiator"),
    ):
        if name in given or key not in data:
            data[key] = getattr(settings, name)
    if "partition" in given or "partition" not in data:
        from service.pipeline.partition import Partition

        p = Partition.parse(settings.partition)
        data["partition"] = {"index": p.index, "count": p.count}
    if settings.sites is not None:
        data["sites"] = load_sites(settings.sites)
    data = merge(data, performance_config(settings))
    return engine_config_from(data)


def performance_config(settings: Settings) -> dict[str, object]:
    """The ``assessment`` section the ``TOPOFUSION_PERFORMANCE_*`` settings give (only those set)."""
    section: dict[str, object] = {}
    if settings.performance_window_s is not None:
        section["window_s"] = settings.performance_window_s
    names = ("pd_min", "mode_3a_min", "mode_c_min")
    req = {n: v for n in names if (v := getattr(settings, f"performance_{n}")) is not None}
    if req:
        section["requirements"] = req
    return {"assessment": section} if section else {}
