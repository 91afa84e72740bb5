"""The engine's parameters: every parameter of the engine, validated at start.

:class:`EngineConfig` is a tree of frozen dataclasses, one section per stage and method, each
field documented where it is defined (``service/pipeline/``, ``service/tracking/params.py``,
``service/correlation/``).  It is the engine's part of the one settings root,
:class:`service.settings.Settings` (``Settings.engine``), whose module says where its values
come from, later winning:

1. the defaults in the code;
2. the config file (``--config FILE`` or ``TOPOFUSION_CONFIG``; TOML or YAML by its suffix,
   ``.json`` too), whose keys are the field names of the tree, e.g.
   ``[correlation.svd] alpha_position = 0.01`` or ``cadence: {cadence_scans: 2}``;
3. the environment: ``TOPOFUSION_ENGINE__<SECTION>__<FIELD>=<value>`` (``__`` between levels,
   any case; the value is read as JSON when it parses, else as a string), e.g.
   ``TOPOFUSION_ENGINE__SEQUENCER__MAX_CLOCK_SKEW_S=120``;
4. the settings that are engine parameters too (``--method``, ``--window``, ``--initiator``,
   ``--sites``, ``--prefix``, ``--partition``, ``TOPOFUSION_PERFORMANCE_*``), where given.

An unknown key or a bad value stops the start with a message naming the key
(``correlation.svd.alpha_postion: unknown key``).  ``topofusion config --show`` prints the
effective settings and tree with every default.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any

from pydantic import TypeAdapter, ValidationError

from service.assessment import AssessmentParams
from service.config_sources import ENV_PREFIX, ConfigError, from_environment, load_file, merge
from service.correlation import CorrelationParams
from service.pipeline.correlation_stage import CadenceParams
from service.pipeline.feed import FeedParams
from service.pipeline.partition import Partition
from service.pipeline.sequencer import SequencerParams
from service.pipeline.track_exchange import ExchangeParams
from service.pipeline.tracking_stage import SiteParams
from service.reference import ReferenceParams
from service.tracking.params import TrackerParams
from service.wire.models import RadarSite

__all__ = [
    "ENV_PREFIX",
    "ConfigError",
    "EngineConfig",
    "aid_problems",
    "as_dict",
    "engine_config_from",
    "from_environment",
    "load_file",
    "load_sites",
    "merge",
    "with_aid",
    "without_aid",
]


@dataclass(frozen=True)
class EngineConfig:
    """Everything that decides the engine's results (all in data time)."""

    prefix: str = "fusion"
    #: Correlation method (svd-topology, basic-topology, nearest, gmm, cfar).
    method: str = "svd-topology"
    #: Sliding window of unused plots per radar, data seconds; ``None``: the tracker's default.
    window_s: float | None = None
    #: Track initiator (``service.tracking.INITIATORS``).
    initiator: str = "logic"
    #: Sites known at start-up (setting ``TOPOFUSION_SITES``).
    sites: tuple[RadarSite, ...] = ()
    #: Data-time ordering and the policies on sources' ``seq`` and clocks.
    sequencer: SequencerParams = field(default_factory=SequencerParams)
    #: When pairs are correlated and biases solved.
    cadence: CadenceParams = field(default_factory=CadenceParams)
    #: How site messages are taken (what is a move).
    site: SiteParams = field(default_factory=SiteParams)
    #: How AIS reports become reference tracks.
    reference: ReferenceParams = field(default_factory=ReferenceParams)
    #: Every radar's tracker: measurement model, filter, life cycle, initiators, bounds.
    tracking: TrackerParams = field(default_factory=TrackerParams)
    #: Every pair correlator: prediction, each method, the pair book, registration.
    correlation: CorrelationParams = field(default_factory=CorrelationParams)
    #: This worker's share of a partitioned network (setting ``TOPOFUSION_PARTITION``, K/N).
    partition: Partition = field(default_factory=Partition)
    #: How partitioned workers send each other track states.
    exchange: ExchangeParams = field(default_factory=ExchangeParams)
    #: The feed on the wall clock (operations): stale outputs, sources silent in wall time.
    feed: FeedParams = field(default_factory=FeedParams)
    #: Each radar's live performance against the references (settings ``TOPOFUSION_PERFORMANCE_*``).
    assessment: AssessmentParams = field(default_factory=AssessmentParams)


#: The engine parameters that may be below zero: a calibration's offset and two margins on
#: log-likelihoods.  Every other number of the tree is a time, distance, rate, count, sigma,
#: probability or threshold, which no rule means below zero (some failed every batch there).
SIGNED_PARAMETERS = frozenset(
    {
        "correlation.evidence.calibration_offset",
        "correlation.evidence.keep_margin",
        "tracking.cluster.min_track_score",
    }
)

#: A configuration error names at most this many problems (a file of a million unknown keys
#: must not make a line of megabytes).
MAX_NAMED_PROBLEMS = 10

_ADAPTER = TypeAdapter(EngineConfig)
_SITE_LIST = TypeAdapter(list[RadarSite])


def load_sites(path: str | Path) -> tuple[RadarSite, ...]:
    """Sites from a JSON file holding a list of ``RadarSite`` (setting ``TOPOFUSION_SITES``)."""
    p = Path(path)
    try:
        return tuple(_SITE_LIST.validate_json(p.read_bytes()))
    except FileNotFoundError:
        raise ValueError(f"sites file not found: {p}") from None
    except OSError as exc:
        raise ValueError(f"sites file {p} cannot be read: {exc.strerror or exc}") from None
    except ValidationError as exc:
        raise ValueError(
            f"sites file {p} is not a JSON list of RadarSite: {_error(validation_problems(exc))}"
        ) from None


def _unknown_keys(cls: type, data: Mapping[str, Any], path: str = "") -> list[str]:
    known = {f.name: f for f in fields(cls)}
    bad = []
    for key, value in data.items():
        where = f"{path}{key}"
        f = known.get(key)
        if f is None:
            bad.append(f"{where}: unknown key (expected one of {', '.join(sorted(known))})")
            continue
        sub = f.default_factory if f.default_factory is not MISSING else None
        if isinstance(value, Mapping) and sub is not None and is_dataclass(sub):
            bad += _unknown_keys(sub, value, where + ".")
    return bad


def engine_config_from(data: Mapping[str, Any]) -> EngineConfig:
    """Validate a nested mapping (a config file's content) into an :class:`EngineConfig`."""
    bad = _unknown_keys(EngineConfig, data)
    if bad:
        raise _error(bad, "unknown keys")
    try:
        config = _ADAPTER.validate_python(dict(data))
    except ValidationError as exc:
        raise _error(validation_problems(exc)) from None
    problems = [f"{key}: must be a finite number, got {value}" for key, value in _non_finite(config)]
    problems += [
        f"{key}: must be >= 0, got {value}"
        for key, value in _numbers(config)
        if value < 0 and key not in SIGNED_PARAMETERS
    ]
    manager = config.tracking.manager
    if manager.confirm_m > manager.confirm_n:
        problems.append(
            f"tracking.manager.confirm_m: {manager.confirm_m} hits of {manager.confirm_n} looks "
            "(confirm_n) can never be had"
        )
    if manager.confirmed_misses_cap < manager.confirmed_max_misses:
        problems.append(
            f"tracking.manager.confirmed_misses_cap: {manager.confirmed_misses_cap} is below "
            f"confirmed_max_misses ({manager.confirmed_max_misses}), the fewest misses that delete"
        )
    problems += aid_problems(config)
    if problems:
        raise _error(problems)
    return config


def with_aid(config: EngineConfig, **changes: Any) -> EngineConfig:
    """``config`` with the aid of association on (``tracking.aid.enabled``), and ``changes`` to
    its other settings (``lag_s``, ``registration_sigma_m``)."""
    return _aid_set(config, enabled=True, **changes)


def without_aid(config: EngineConfig) -> EngineConfig:
    """``config`` with the aid of association off (``tracking.aid.enabled``; on by default)."""
    return _aid_set(config, enabled=False)


def _aid_set(config: EngineConfig, **changes: Any) -> EngineConfig:
    """``config`` with ``changes`` to its ``tracking.aid`` settings."""
    aid = replace(config.tracking.aid, **changes)
    return replace(config, tracking=replace(config.tracking, aid=aid))


def aid_problems(config: EngineConfig) -> list[str]:
    """What makes ``tracking.aid`` impossible in ``config`` (none while it is off): the aid is
    every pair's links a lag back, which a batch waits for."""
    aid = config.tracking.aid
    if not aid.enabled:
        return []
    problems = []
    if not aid.lag_s > 0.0:
        problems.append(
            f"tracking.aid.lag_s: {aid.lag_s} s; the aid needs a lag above zero "
            "(a batch cannot wait for the answer to its own table)"
        )
    return problems


def validation_problems(exc: ValidationError) -> list[str]:
    """Each problem pydantic found, on one line: where, and what is wrong."""
    out = []
    for e in exc.errors(include_url=False):
        where, what = ".".join(str(p) for p in e["loc"]), " ".join(e["msg"].split())
        out.append(f"{where}: {what}" if where else what)
    return out


def _error(problems: list[str], what: str = "") -> ConfigError:
    """One error naming at most ``MAX_NAMED_PROBLEMS`` of ``problems``, and how many more."""
    more = len(problems) - MAX_NAMED_PROBLEMS
    rest = f"; and {more} more {what}".rstrip() if more > 0 else ""
    return ConfigError("; ".join(problems[:MAX_NAMED_PROBLEMS]) + rest)


def _non_finite(config: Any) -> list[tuple[str, float]]:
    """Every number of the tree that is NaN or infinite (no parameter has such a default: as
    a threshold or a time it would turn a rule off or stop the clocks unnoticed)."""
    return [(key, value) for key, value in _numbers(config) if not math.isfinite(value)]


def _numbers(config: Any, path: str = "") -> list[tuple[str, float]]:
    """Every number of the tree (not the booleans), by its dotted key."""
    out: list[tuple[str, float]] = []
    for f in fields(config):
        value = getattr(config, f.name)
        if is_dataclass(value) and not isinstance(value, type):
            out += _numbers(value, f"{path}{f.name}.")
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out.append((f"{path}{f.name}", value))
    return out


def as_dict(config: EngineConfig) -> dict[str, Any]:
    """The whole tree as plain data (``topofusion config --show``)."""
    data: dict[str, Any] = _ADAPTER.dump_python(config, mode="json")
    return data
