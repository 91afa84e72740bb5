"""What the engine keeps across a restart (contract §4.6 "State"), and its reading.

:class:`EngineState` is what :meth:`service.engine.Engine.export_state` gives and
:mod:`service.state` writes; :func:`read_state` checks one before the engine takes it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import ValidationError

from service.pipeline.sequencer import Sequencer
from service.wire.models import BiasSet, RadarSite


@dataclass(frozen=True)
class EngineState:
    """What the engine keeps across a restart (contract §4.6 "State"; :mod:`service.state`
    writes and reads it), in plain values and numpy arrays.

    ``sites``: every radar's ``RadarSite``; ``sources``: each source's latest ``seq`` and data
    clock (:meth:`Sequencer.export_state`); ``reference_kinds``: each reference source's input
    kind (``ais`` or ``adsb``); ``published_biases``: the ``BiasSet`` the bias worker last
    published (another partitioned worker's ``GET /biases``); ``correlation``: the registration
    memories and the joint bias solution (:meth:`CorrelationStage.export_state`);
    ``data_clock_s``: the newest data clock when taken (None: no data yet).  Tracks and pair
    books are not kept: the input that follows rebuilds them.
    """

    sites: list[dict[str, Any]]
    sources: list[dict[str, Any]]
    reference_kinds: dict[str, str]
    published_biases: dict[str, Any] | None
    correlation: dict[str, Any]
    data_clock_s: float | None

    def summary(self) -> str:
        """One line of what it holds (for the log)."""
        memories = self.correlation["memories"]
        rows = sum(len(m["rows"]["time"]) for m in memories)
        joint = self.correlation["joint"]
        if joint:
            biases = f"biases of {len(joint['radar_ids'])} radars"
        else:  # (a partitioned worker but the first keeps the bias set the first published)
            kept = (self.published_biases or {}).get("biases") or []
            biases = f"biases of {len(kept)} radars (as published)" if kept else "biases of 0 radars"
        return (
            f"{len(self.sites)} radar sites, {len(self.sources)} source clocks, "
            f"{len(memories)} registration memories ({rows} rows), {biases}"
        )


def own_state(
    tracking: Any,
    sequencer: Sequencer,
    reference_kinds: dict[str, str],
    published_biases: dict[str, Any] | None,
) -> dict[str, Any]:
    """The fields of :class:`EngineState` but the correlation's, as new objects (later input
    changes none of them): ``tracking`` is the engine's :class:`~.tracking_stage.TrackingStage`."""
    clock = sequencer.newest_s
    return {
        "sites": [r.site.model_dump(mode="json") for _, r in sorted(tracking.tracked.items())],
        "sources": sequencer.export_state(),
        "reference_kinds": dict(sorted(reference_kinds.items())),
        "published_biases": published_biases,
        "data_clock_s": float(clock) if np.isfinite(clock) else None,
    }


def state_when_answered(
    own: dict[str, Any], correlation: Callable[[], dict[str, Any] | None]
) -> Callable[[], EngineState | None]:
    """The state of one moment: the engine's part taken then (``own``), the correlation's once
    its process has answered (``correlation``: None until then).  The returned function gives
    it (None until then; ``RuntimeError`` if the process died meanwhile)."""

    def ready() -> EngineState | None:
        answered = correlation()
        return None if answered is None else EngineState(correlation=answered, **own)

    return ready


def read_state(
    state: EngineState | None, configured: set[str]
) -> tuple[list[RadarSite], list[tuple[float, str, int, int]], dict[str, str], dict[str, Any] | None]:
    """A kept state's parts, checked: the sites (but those of ``configured`` radars, whose
    configured site wins), the sources' clocks (:meth:`Sequencer.read_state`), the reference
    kinds and the published biases.  Raises ``KeyError``, ``TypeError`` or ``ValueError`` on a
    state that is not one."""
    if state is None:
        return [], [], {}, None
    sites = [
        site for site in (RadarSite.model_validate(s) for s in state.sites) if site.radar_id not in configured
    ]
    sources = Sequencer.read_state(state.sources)
    kinds = {str(k): str(v) for k, v in state.reference_kinds.items()}
    if not set(kinds.values()) <= {"ais", "adsb"}:
        raise ValueError(f"reference kinds {sorted(set(kinds.values()))}")
    published = None
    if state.published_biases is not None:
        try:
            published = BiasSet.model_validate(state.published_biases).model_dump()
        except ValidationError:  # of an older wire model: the bias worker's next one comes
            published = None
    return sites, sources, kinds, published
