"""One configuration root: every parameter of the engine, validated at start.

:class:`EngineConfig` is a tree of frozen dataclasses, one section per stage and method, each
field documented where it is defined (``service/pipeline/``, ``service/tracking/params.py``,
``service/correlation/``).  Its values come from, later winning:

1. the defaults in the code;
2. a config file (``--config FILE`` or ``TOPOFUSION_CONFIG``; TOML or YAML by its suffix,
   ``.json`` too), whose keys are the field names of the tree, e.g.
   ``[correlation.svd] alpha_position = 0.01`` or ``cadence: {cadence_scans: 2}``;
3. the environment: ``TOPOFUSION_ENGINE__<SECTION>__<FIELD>=<value>`` (``__`` between levels,
   any case; the value is read as JSON when it parses, else as a string), e.g.
   ``TOPOFUSION_ENGINE__SEQUENCER__MAX_CLOCK_SKEW_S=120``;
4. the command-line flags and settings of the contract (``--method``, ``--window``,
   ``--initiator``, ``--sites``, ``--prefix``, ``--partition``).

An unknown key or a bad value stops the start with a message naming the key
(``correlation.svd.alpha_postion: unknown key``).  ``topofusion config --show`` prints the
effective tree with every default.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

from pydantic import TypeAdapter, ValidationError

from service.assessment import AssessmentParams
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

#: Environment variables of single parameters start with this (then ``SECTION__FIELD``).
ENV_PREFIX = "TOPOFUSION_ENGINE__"


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


class ConfigError(ValueError):
    """A configuration that cannot be used; the message names the key."""


_ADAPTER = TypeAdapter(EngineConfig)
_SITE_LIST = TypeAdapter(list[RadarSite])


def load_sites(path: str | Path) -> tuple[RadarSite, ...]:
    """Sites from a JSON file holding a list of ``RadarSite`` (setting ``TOPOFUSION_SITES``)."""
    p = Path(path)
    try:
        return tuple(_SITE_LIST.validate_json(p.read_bytes()))
    except FileNotFoundError:
        raise ValueError(f"sites file not found: {p}") from None
    except ValidationError as exc:
        raise ValueError(f"sites file {p} is not a JSON list of RadarSite: {exc}") from None


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
        raise ConfigError("; ".join(bad))
    try:
        return _ADAPTER.validate_python(dict(data))
    except ValidationError as exc:
        problems = [
            f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors(include_url=False)
        ]
        raise ConfigError("; ".join(problems)) from None


def load_file(path: str | Path) -> dict[str, Any]:
    """A config file's content (TOML, YAML or JSON by suffix)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {p}") from None
    try:
        if p.suffix.lower() == ".toml":
            if sys.version_info >= (3, 11):
                import tomllib
            else:  # the same parser, before it joined the standard library
                import tomli as tomllib

            data: Any = tomllib.loads(text)
        elif p.suffix.lower() in (".yaml", ".yml"):
            import yaml

            data = yaml.safe_load(text) or {}
        elif p.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            raise ConfigError(f"config file {p}: use a .toml, .yaml, .yml or .json file")
    except ConfigError:
        raise
    except Exception as exc:  # the parsers' own errors say where
        raise ConfigError(f"config file {p} cannot be read: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {p}: the top level must be a table of sections")
    return data


def from_environment(environ: Mapping[str, str] | None = None) -> dict[str, Any]:
    """``TOPOFUSION_ENGINE__A__B=value`` variables as a nested mapping ``{"a": {"b": value}}``."""
    env = os.environ if environ is None else environ
    out: dict[str, Any] = {}
    for name, raw in sorted(env.items()):
        if not name.upper().startswith(ENV_PREFIX):
            continue
        path = [part.lower() for part in name[len(ENV_PREFIX) :].split("__")]
        if not all(path):
            raise ConfigError(f"{name}: empty key in the variable's name")
        try:
            value: Any = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        node = out
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{name}: {part} is a value, not a section")
        node[path[-1]] = value
    return out


def merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` on top of ``base``, section by section."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge(out[key], value)
        else:
            out[key] = value
    return out


def as_dict(config: EngineConfig) -> dict[str, Any]:
    """The whole tree as plain data (``topofusion config --show``)."""
    data: dict[str, Any] = _ADAPTER.dump_python(config, mode="json")
    return data
