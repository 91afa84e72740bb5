"""The node's own parameters (:class:`NodeOptions`)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from service.settings import Settings


def _setting(name: str) -> Any:
    """A setting's default (one set of defaults: the settings')."""
    return Settings.model_fields[name].default


@dataclass(frozen=True)
class NodeOptions:
    """The node's own parameters: those named as a setting are that setting
    (:meth:`from_settings`, ``service.settings``), the others the node's alone."""

    queue_size: int = _setting("queue_size")
    queue_bytes: int = _setting("queue_bytes")
    queue_wait_s: float = _setting("queue_wait_s")
    radars: tuple[str, ...] = ()
    peer_grace_s: float = _setting("peer_grace_s")
    stop_grace_s: float = _setting("stop_grace_s")
    stall_s: float = _setting("stall_s")
    #: Outputs handed to the publisher thread and not put yet, at most (then the worker waits).
    outbox_size: int = 65536
    #: Partitioned: how often (s, wall clock) this worker puts its status for the others.
    status_interval_s: float = 1.0
    #: Partitioned: how long ``GET /pairs`` waits for the other workers' pair sets (s).
    peer_query_timeout_s: float = 10.0

    @classmethod
    def from_settings(cls, settings: Settings) -> NodeOptions:
        """Every option of the same name as a setting, from the settings."""
        given: dict[str, Any] = {}
        for f in fields(cls):
            if f.name in Settings.model_fields:
                value = getattr(settings, f.name)
                given[f.name] = tuple(value) if isinstance(value, list) else value
        return cls(**given)
