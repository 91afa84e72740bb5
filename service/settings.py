"""The one settings root (pydantic-settings): every ``TOPOFUSION_*`` setting, and the engine's
parameters derived from it (docs/contract.md §3, docs/configuration.md).

Where a value comes from, each source over the ones before it:

1. the defaults in the code (here, and in the engine's tree, ``service.config``);
2. the config file (``--config FILE`` or ``TOPOFUSION_CONFIG``; TOML, YAML or JSON by its
   suffix): any setting by its field name (``http_port = 8080``) and any engine parameter by
   its place in the engine's tree (``[correlation.svd] alpha_position = 0.01``);
3. the ``TOPOFUSION_ENGINE__<SECTION>__<FIELD>`` variables (engine parameters one by one);
4. the ``TOPOFUSION_<SETTING>`` variables;
5. the command's flags (:meth:`Settings.load` ``overrides``).

A setting that is also an engine parameter (``prefix``, ``method``, ``window_s``,
``initiator``, ``partition``, ``sites``, the ``performance_*`` ones) is marked so where it is
declared (:class:`EngineKey`): it is read from every source above under either name, and the
engine's tree takes the setting's value (:attr:`Settings.engine`).  An unknown key or a bad
value stops the start with a message naming it.  :meth:`Settings.effective` is the whole
effective configuration (``topofusion config --show``; secrets redacted), itself a valid
config file.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, get_args

from pydantic import Field, PrivateAttr, SecretStr, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    NoDecode,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
)

from service.config_sources import ConfigError, from_environment, load_file, merge
from service.wire.vocabulary import Method, is_source_id

if TYPE_CHECKING:
    import argparse

    from pydantic.fields import FieldInfo

    from service.config import EngineConfig

#: Settings whose empty value means "not set" (a path or a token of length zero is never
#: meant); an empty variable leaves them to the config file or the default.
EMPTY_IS_UNSET = ("zenoh_config", "sites", "config", "state_dir", "api_token")

#: Connections the HTTP side port's cap always leaves beyond every request that may be in
#: progress (at most ``max_requests`` ordinary ones and ``picture_max_clients`` streams): those
#: are idle or still sending their request head, and such a connection gives way to a new one
#: when the cap is reached, so that a probe always finds room (docs/operations/http.md;
#: service/api/limits.py checks the limits against it).
PROBE_ROOM = 16
#: The longest wall-clock duration (s) a setting takes: a day (a timer far beyond overflows).
MAX_DURATION_S = 86_400.0
#: The levels ``--log-level`` / ``TOPOFUSION_LOG_LEVEL`` take (any case; WARN is WARNING).
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "WARN", "ERROR", "CRITICAL")


def normal_log_level(text: str) -> str:
    """A log level as logging and uvicorn name it (any case, blanks around it, WARN for
    WARNING); ``ValueError`` for one not in :data:`LOG_LEVELS`."""
    level = text.strip().upper()
    if level not in LOG_LEVELS:
        raise ValueError(f"one of {', '.join(LOG_LEVELS)}")
    return "WARNING" if level == "WARN" else level


def _blank(value: object) -> bool:
    """An empty (or all-blank) variable: it means "not set"."""
    return isinstance(value, str) and not value.strip()


#: How :meth:`Settings.effective` shows a secret (in a config file: not given).
REDACTED = "**********"


# -- settings that are engine parameters too -----------------------------------------------------


def _same(value: Any) -> Any:
    return value


def _partition_to_engine(value: str) -> dict[str, int]:
    from service.pipeline.partition import Partition

    p = Partition.parse(value)
    return {"index": p.index, "count": p.count}


def _partition_from_engine(value: Any) -> Any:
    """The engine's form (``{index, count, salt}``) as the setting's ``K/N`` (the salt is its
    own setting: the salt alone gives none); a ``K/N`` as it is."""
    if isinstance(value, Mapping) and {"index", "count"} <= set(value) <= {"index", "count", "salt"}:
        return f"{value['index']}/{value['count']}"
    if isinstance(value, Mapping) and set(value) <= {"salt"}:
        return None
    return value


def _sites_to_engine(value: Path) -> list[Any]:
    from service.config import load_sites

    return list(load_sites(value))


def _sites_from_engine(value: Any) -> Any:
    """A sites file's path is the setting; a list of sites stays the engine's own."""
    return value if isinstance(value, str) else None


@dataclass(frozen=True)
class EngineKey:
    """Marks a setting that is also the engine parameter at ``path`` (dotted) of its tree:
    ``to_engine`` makes the parameter of the setting's value, ``from_engine`` the setting of a
    parameter's (a config file's or a ``TOPOFUSION_ENGINE__*`` variable's; None: none)."""

    path: str
    to_engine: Callable[[Any], Any] = _same
    from_engine: Callable[[Any], Any] = _same


def _engine_key(info: FieldInfo) -> EngineKey | None:
    return next((m for m in info.metadata if isinstance(m, EngineKey)), None)


def _at(tree: Mapping[str, Any], path: str) -> Any:
    """The value at a dotted ``path`` of a nested mapping, or None."""
    node: Any = tree
    for part in path.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    return node


def _put(tree: dict[str, Any], path: str, value: Any) -> None:
    *parents, last = path.split(".")
    for part in parents:
        tree = tree.setdefault(part, {})
    tree[last] = value


def _split(value: object) -> object:
    if isinstance(value, str):
        return [v.strip() for v in value.split(",") if v.strip()]
    return value


# -- the settings --------------------------------------------------------------------------------


class Settings(BaseSettings):
    """Every ``TOPOFUSION_*`` setting; errors name the offending variable or key.

    Build it with :meth:`load` (a config file and the flags over the environment); ``Settings()``
    reads the environment (and ``TOPOFUSION_CONFIG``'s file) alone.
    """

    # (no setting takes an infinite or NaN number: a timer of inf seconds overflows)
    model_config = SettingsConfigDict(env_prefix="TOPOFUSION_", extra="ignore", allow_inf_nan=False)

    #: ``None``: the Zenoh config file's mode, else the command's default (peer for the service).
    zenoh_mode: Literal["peer", "client", "router"] | None = None
    #: ``None`` means the mode's default (none for client, the contract's endpoint otherwise).
    zenoh_listen: Annotated[list[str] | None, NoDecode] = None
    zenoh_connect: Annotated[list[str], NoDecode] = Field(default_factory=list)
    zenoh_config: Path | None = None
    http_host: str = "127.0.0.1"
    http_port: int = Field(default=8000, ge=0, le=65535)
    prefix: Annotated[str, EngineKey("prefix")] = Field(
        default="fusion", pattern=r"^[A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*$"
    )
    #: A JSON file holding a list of ``RadarSite`` (the engine's ``sites``: known at start-up).
    sites: Annotated[Path | None, EngineKey("sites", _sites_to_engine, _sites_from_engine)] = None
    method: Annotated[Method, EngineKey("method")] = "svd-topology"
    window_s: Annotated[float | None, EngineKey("window_s")] = Field(default=None, gt=0)
    initiator: Annotated[str, EngineKey("initiator")] = "logic"
    #: Radars this worker owns (comma separated ids); empty: every radar under the prefix.
    #: Partitioning several workers by radar is configuration: each subscribes to its own
    #: radars, and ``get {prefix}/pairs/**`` gathers every worker's pairs.
    radars: Annotated[list[str], NoDecode] = Field(default_factory=list)
    #: ``K/N``: worker K of N on one prefix; together the N workers give the results of one
    #: (``service.pipeline.partition``: which worker owns which radar and radar pair).
    partition: Annotated[str, EngineKey("partition", _partition_to_engine, _partition_from_engine)] = Field(
        default="1/1", pattern=r"^\s*\d+\s*/\s*\d+\s*$"
    )
    #: Mixed into the rendezvous weights of ``partition`` (0: none): a balanced assignment
    #: for a network's radars (``topofusion partition --balance``); every worker the same.
    #: Unset: the engine configuration's ``partition.salt`` (default 0).
    partition_salt: Annotated[int | None, EngineKey("partition.salt")] = Field(
        default=None, ge=0, le=2**31 - 1
    )
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
    stop_grace_s: float = Field(default=20.0, ge=0, le=MAX_DURATION_S)
    #: ``/readyz`` is 503 while input has waited in the queue this long (s, wall clock) with
    #: the worker taking none of it.
    stall_s: float = Field(default=30.0, gt=0, le=MAX_DURATION_S)
    #: Where what takes minutes to learn survives a restart (``service.state``); ``None``: nothing.
    state_dir: Path | None = None
    #: Data time (s) between two periodic state writes.
    state_interval_s: float = Field(default=30.0, gt=0)
    #: When set, every HTTP endpoint but ``/healthz`` and ``/readyz`` needs
    #: ``Authorization: Bearer <token>``.
    api_token: SecretStr | None = None
    log_level: str = "INFO"
    #: The config file (TOML, YAML or JSON): settings and engine parameters; ``None``: none.
    config: Path | None = None
    #: Run the correlation stage in its own process, so that tracking and correlation use two
    #: cores (same results; ``false``: one process, e.g. where processes cannot be started).
    #: Unset: a worker of the whole network does, a partitioned worker does not
    #: (:attr:`two_processes`).
    correlation_process: bool | None = None
    #: Partitioned: a worker whose Zenoh liveliness token left is still waited for this long
    #: (s, wall clock) before the others correlate without its radars: a session that loses
    #: its router for a moment (a lease missed under load) must not reorder anything.
    peer_grace_s: float = Field(default=15.0, ge=0, le=MAX_DURATION_S)
    # The HTTP side port's limits (service/api/limits.py, docs/operations/http.md).
    #: A connection must deliver a whole request head within this many seconds of opening,
    #: and of its previous response ending; else it is closed (uvicorn has no such timeout).
    http_header_timeout_s: float = Field(default=10.0, gt=0, le=MAX_DURATION_S)
    #: A kept-alive connection with nothing arriving for this many seconds is closed.
    http_keep_alive_s: float = Field(default=5.0, gt=0, le=MAX_DURATION_S)
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
    # Each radar's live performance against ADS-B / AIS (contract §5.3, docs/assessment.md):
    # the engine's ``assessment`` section; ``None``: its value there (defaults as below).
    #: The sliding window of data time the figures cover (s; default 600).
    performance_window_s: Annotated[float | None, EngineKey("assessment.window_s")] = Field(
        default=None, gt=0
    )
    #: Detection probability a radar must reach (default 0.97).
    performance_pd_min: Annotated[float | None, EngineKey("assessment.requirements.pd_min")] = Field(
        default=None, ge=0, le=1
    )
    #: Share of correct Mode 3/A codes a radar must reach (default 0.98).
    performance_mode_3a_min: Annotated[float | None, EngineKey("assessment.requirements.mode_3a_min")] = (
        Field(default=None, ge=0, le=1)
    )
    #: Share of correct Mode C (within 200 ft of the reference) a radar must reach (default 0.96).
    performance_mode_c_min: Annotated[float | None, EngineKey("assessment.requirements.mode_c_min")] = Field(
        default=None, ge=0, le=1
    )

    #: The engine parameters of the config file and the ``TOPOFUSION_ENGINE__*`` variables
    #: (read once, when the settings are made); :attr:`engine` puts the settings over them.
    _engine_tree: dict[str, Any] = PrivateAttr(default_factory=dict)

    _split_listen = field_validator("zenoh_listen", "zenoh_connect", "radars", mode="before")(_split)

    # -- building -------------------------------------------------------------------------------
    @classmethod
    def load(
        cls, config_file: str | Path | None = None, overrides: Mapping[str, Any] | None = None
    ) -> Settings:
        """The settings of a start: defaults < the config file (``config_file``, else
        ``overrides["config"]``, else ``TOPOFUSION_CONFIG``) < ``TOPOFUSION_ENGINE__*`` <
        ``TOPOFUSION_*`` < ``overrides`` (the flags, by field name; None: not given; see
        :func:`flag_overrides`).  Raises ``pydantic.ValidationError`` naming a bad setting and
        :class:`ConfigError` naming a bad or unknown key of the file."""
        given = {k: v for k, v in (overrides or {}).items() if v is not None}
        if config_file is not None:
            given["config"] = config_file
        return cls(**given)

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        return (
            init_settings,
            _SetVariables(settings_cls, env_settings),
            dotenv_settings,
            _EngineVariables(settings_cls),
            _ConfigFile(settings_cls, init_settings),
            file_secret_settings,
        )

    def model_post_init(self, context: Any, /) -> None:
        tree: dict[str, Any] = {}
        if self.config is not None:
            tree = {k: v for k, v in load_file(self.config).items() if k not in _SETTINGS_ONLY}
        self._engine_tree = merge(tree, from_environment())

    # -- validation -----------------------------------------------------------------------------
    @field_validator(*EMPTY_IS_UNSET, mode="before")
    @classmethod
    def _empty_is_none(cls, value: object) -> object:
        # An empty variable (e.g. compose's ``${TOPOFUSION_API_TOKEN:-}``) means "not set": not
        # the working directory, not a token of length zero.
        return None if _blank(value) else value

    @field_validator("http_host", mode="before")
    @classmethod
    def _empty_host_is_default(cls, value: object) -> object:
        # An empty variable means "not set" here too: the loopback default, never every
        # interface (which an empty host means to the server).
        return cls.model_fields["http_host"].default if _blank(value) else value

    @field_validator("api_token", mode="before")
    @classmethod
    def _token_without_blanks(cls, value: object) -> object:
        # A token read from a file (a Kubernetes or Docker secret) ends with a newline that no
        # client sends: whitespace around it is never part of it.
        return value.strip() if isinstance(value, str) else value

    @field_validator("log_level")
    @classmethod
    def _log_level(cls, value: str) -> str:
        return normal_log_level(value)

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
        least = self.http_max_requests + self.http_picture_max_clients + PROBE_ROOM
        if self.http_max_connections < least:
            raise ValueError(
                f"TOPOFUSION_HTTP_MAX_CONNECTIONS ({self.http_max_connections}) must be at least "
                f"TOPOFUSION_HTTP_MAX_REQUESTS + TOPOFUSION_HTTP_PICTURE_MAX_CLIENTS + {PROBE_ROOM} "
                f"({least}), so that some connections are always free for the probes"
            )
        return self

    # -- what is derived ------------------------------------------------------------------------
    @cached_property
    def engine(self) -> EngineConfig:
        """The engine's configuration: its defaults < the config file's and the
        ``TOPOFUSION_ENGINE__*`` parameters < every setting marked :class:`EngineKey` (where
        it has a value).  Raises :class:`ConfigError` naming the key of a bad value."""
        from service.config import engine_config_from

        given: dict[str, Any] = {}
        for name, info in type(self).model_fields.items():
            key = _engine_key(info)
            value = getattr(self, name)
            if key is not None and value is not None:
                _put(given, key.path, key.to_engine(value))
        data = merge(self._engine_tree, given)
        return engine_config_from(data)

    @property
    def two_processes(self) -> bool:
        """Whether the correlation stage runs in its own process: as set, else for a worker of
        the whole network only.  Partitioned, the workers are the parallelism: a worker in one
        process spends none of its CPU on the pipe to a second one (every radar's table down,
        the answers up: a tenth of its main process, docs/scale-out.md), and a pod of the
        partitioned deployment is given one core."""
        if self.correlation_process is not None:
            return self.correlation_process
        return bool(self.engine.partition.whole)

    def effective(self) -> dict[str, Any]:
        """The whole effective configuration as plain data (``topofusion config --show``):
        every setting but ``config``, then the engine's tree; a setting that is an engine
        parameter shows the engine's value, in the engine's form.  Secrets show as
        ``REDACTED``.  It is a valid config file itself."""
        from service.config import as_dict

        engine = as_dict(self.engine)
        out: dict[str, Any] = {}
        for name, value in self.model_dump(mode="json", exclude={"config"}).items():
            key = _engine_key(type(self).model_fields[name])
            out[name] = _at(engine, key.path) if key is not None else value
        out["correlation_process"] = self.two_processes  # (unset: as this worker runs)
        out.update((k, v) for k, v in engine.items() if k not in out)
        return out

    def render(self, fmt: Literal["yaml", "json"] = "yaml") -> str:
        """:meth:`effective` as YAML or JSON text (ends with a newline)."""
        data = self.effective()
        if fmt == "json":
            return json.dumps(data, indent=2) + "\n"
        import yaml

        return str(yaml.safe_dump(data, sort_keys=False))


#: Settings that are engine parameters of the same name (a config file's key is both).
_SHARED = frozenset(
    name for name, info in Settings.model_fields.items() if (key := _engine_key(info)) and key.path == name
)
#: Settings that are no top-level engine parameter: a config file's keys of them are settings only.
_SETTINGS_ONLY = frozenset(Settings.model_fields) - _SHARED
#: Settings whose values are secrets: never printed (``config --show`` and errors redact them).
SECRET_SETTINGS = frozenset(
    name
    for name, info in Settings.model_fields.items()
    if info.annotation is SecretStr or SecretStr in get_args(info.annotation)
)


def _settings_of_tree(tree: Mapping[str, Any]) -> dict[str, Any]:
    """The settings an engine tree gives (a config file's, the ``TOPOFUSION_ENGINE__*``
    variables'): each setting marked :class:`EngineKey` whose parameter it holds."""
    out: dict[str, Any] = {}
    for name, info in Settings.model_fields.items():
        key = _engine_key(info)
        if key is not None and (value := _at(tree, key.path)) is not None:
            setting = key.from_engine(value)
            if setting is not None:
                out[name] = setting
    return out


class _SetVariables(PydanticBaseSettingsSource):
    """The ``TOPOFUSION_*`` variables, less the empty ones of :data:`EMPTY_IS_UNSET`: such a
    variable is not set (compose passes ``${TOPOFUSION_API_TOKEN:-}``), so that the config
    file's value below it still applies (an empty token must not hide the file's one)."""

    def __init__(self, settings_cls: type[BaseSettings], env_settings: PydanticBaseSettingsSource) -> None:
        super().__init__(settings_cls)
        self._env = env_settings

    def get_field_value(self, field: FieldInfo, field_name: str) -> tuple[Any, str, bool]:
        return None, field_name, False  # (all is done in __call__)

    def __call__(self) -> dict[str, Any]:
        return {
            k: v
            for k, v in self._env().items()
            if not (k in EMPTY_IS_UNSET and isinstance(v, str) and not v.strip())
        }


class _EngineVariables(PydanticBaseSettingsSource):
    """The ``TOPOFUSION_ENGINE__*`` variables of parameters that are settings too (the old
    names of ``TOPOFUSION_METHOD`` and the like): under the ``TOPOFUSION_*`` variables."""

    def get_field_value(self, field: FieldInfo, field_name: str) -> tuple[Any, str, bool]:
        return None, field_name, False  # (all is done in __call__)

    def __call__(self) -> dict[str, Any]:
        return _settings_of_tree(from_environment())


class _ConfigFile(PydanticBaseSettingsSource):
    """The config file's settings (``--config FILE``, else ``TOPOFUSION_CONFIG``), under every
    variable: its keys are settings and the engine tree's sections; any other is refused."""

    def __init__(self, settings_cls: type[BaseSettings], init_settings: PydanticBaseSettingsSource) -> None:
        super().__init__(settings_cls)
        self._init = init_settings

    def get_field_value(self, field: FieldInfo, field_name: str) -> tuple[Any, str, bool]:
        return None, field_name, False  # (all is done in __call__)

    def _path(self) -> str | Path | None:
        given = getattr(self._init, "init_kwargs", {}).get("config")
        if given is None:
            name = "TOPOFUSION_CONFIG"
            given = next((v for k, v in os.environ.items() if k.upper() == name), None)
        return None if given is None or not str(given).strip() else given

    def __call__(self) -> dict[str, Any]:
        path = self._path()
        if path is None:
            return {}
        data = load_file(path)
        from service.config import EngineConfig

        engine_keys = set(EngineConfig.__dataclass_fields__)
        settings = set(Settings.model_fields) - {"config"}
        bad = sorted(k for k in data if k not in settings and k not in engine_keys)
        if "config" in data:
            bad.insert(0, "config")
        if bad:
            raise ConfigError(
                f"config file {path}: {', '.join(bad)}: unknown key (expected a setting or a section "
                "of the engine's tree, as `topofusion config --show` prints them)"
            )
        # A secret as `config --show` prints it is no value: the secret comes from elsewhere
        # (the environment), never the redaction itself.
        data = {k: v for k, v in data.items() if not (k in SECRET_SETTINGS and v == REDACTED)}
        direct = {k: v for k, v in data.items() if k in _SETTINGS_ONLY}
        return {**_settings_of_tree(data), **direct}


#: The command line's flags that are settings: the flag's name (argparse's ``dest``) -> the field.
FLAGS: dict[str, str] = {
    "mode": "zenoh_mode",
    "listen": "zenoh_listen",
    "connect": "zenoh_connect",
    "zenoh_config": "zenoh_config",
    "http_host": "http_host",
    "http_port": "http_port",
    "prefix": "prefix",
    "sites": "sites",
    "method": "method",
    "window": "window_s",
    "initiator": "initiator",
    "radars": "radars",
    "partition": "partition",
    "partition_salt": "partition_salt",
    "log_level": "log_level",
    "config": "config",
    "state_dir": "state_dir",
}


def flag_overrides(flags: Mapping[str, Any] | argparse.Namespace) -> dict[str, Any]:
    """The settings the command line's flags give (``args`` or ``vars(args)``: only the flags
    of :data:`FLAGS`, only those given), for :meth:`Settings.load`."""
    given = flags if isinstance(flags, Mapping) else vars(flags)
    return {field: given[flag] for flag, field in FLAGS.items() if given.get(flag) is not None}


def engine_config(settings: Settings) -> EngineConfig:
    """The engine's configuration of the settings (:attr:`Settings.engine`)."""
    return settings.engine
