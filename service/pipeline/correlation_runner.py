"""How the engine runs its correlation stage: here, or in a child process, behind one protocol.

The engine feeds the :class:`~.correlation_stage.CorrelationStage` in release order (a radar's
tracks after each batch, reference reports, site moves, departures) and takes back what each
call changed as an :class:`Answer`: the views of the pairs it updated, the biases when it
re-solved them, the system-track pictures it took, a failure.  The pictures are drawn here, as
the answers are taken (:class:`~.system_stage.SystemDrawer`): with the stage in a child process
the rebuilds run beside its next pair updates.  :class:`InProcessRunner`
answers every call at once; :class:`~.correlation_process.ChildProcessRunner` sends each to a
child process (tracking and correlation on two cores at once) and its answers come later.
Both keep the answers in one :class:`Answers` book, so the engine reads them alike
(:class:`CorrelationRunner`): the results are the same bit for bit, only their time differs.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

from service.correlation import PairCorrelator
from service.correlation.prediction import PredictionParams
from service.correlation.registration import RegistrationRowsData
from service.geo import Site
from service.pipeline.correlation_stage import CorrelationStage, SharedRows
from service.pipeline.read_model import PairSetView, SystemTrackView
from service.pipeline.shared_links import Crossing, SharedLinks
from service.pipeline.system_stage import Drawing, SystemDrawer
from service.tracking.base import TrackTable

Key = tuple[str, str]


@dataclass(frozen=True)
class Answer:
    """What one call of the stage changed."""

    op: str  # the call: "radar" (a radar's tracks), "reference", ...
    updated: list[tuple[Key, PairSetView]]
    biases: list[dict[str, Any]] | None  # None: unchanged
    timings: dict[str, Any] | None  # None: unchanged (a local stage is read directly)
    error: tuple[str, str] | None = None  # (source id, detail) when the call failed
    rows: list[SharedRows] = field(default_factory=list)  # partitioned: rows for the bias worker
    links: list[SharedLinks] = field(default_factory=list)  # partitioned: links for worker 1
    system: SystemTrackView | None = None  # new system tracks, if the call made them (drawn)
    result: Any = None  # what the stage's call returned (``export_state``; None for the others)
    drawings: list[Drawing] = field(default_factory=list)  # pictures to draw, oldest first
    #: The aid of association on: the links' grid's crossings, with the owned pairs' links
    crossings: list[Crossing] = field(default_factory=list)


def answer(stage: CorrelationStage, op: str, args: tuple[Any, ...]) -> Answer:
    """Apply one call to ``stage`` and say what it changed.  A failure costs this call's pair
    updates, never the stage (it is reported with the answer)."""
    biases_before = stage.biases
    keys: list[Key] = []
    error = None
    result = None
    try:
        if op == "radar":
            keys = stage.radar(*args)
        else:
            result = getattr(stage, op)(*args)
    except Exception as exc:
        error = (str(args[0]) if args else "", f"correlation failed: {type(exc).__name__}: {exc}")
    return Answer(
        op,
        [(k, stage.views[k]) for k in keys],
        stage.biases if stage.biases is not biases_before else None,
        None,
        error,
        stage.take_rows(),
        stage.take_links(),
        None,
        result,
        stage.take_drawings(),
        stage.take_crossings(),
    )


class Answers:
    """The answers taken so far, until the engine takes them (in call order); the system tracks
    of their pictures drawn as they are taken (:class:`~.system_stage.SystemDrawer`)."""

    def __init__(self, prediction: PredictionParams) -> None:
        self.drawer = SystemDrawer(prediction)
        self.biases: list[dict[str, Any]] = []
        self.system_view: SystemTrackView | None = None
        self._answers: list[Answer] = []
        self._errors: list[tuple[str, str]] = []
        self._rows: list[SharedRows] = []
        self._links: list[SharedLinks] = []

    def _take_answer(self, a: Answer) -> None:
        if a.drawings:  # every picture drawn, in order; the newest is what is shown
            views = [self.drawer.draw(d) for d in a.drawings]
            drawn = [v for v in views if v is not None]
            a = replace(a, drawings=[], system=drawn[-1] if drawn else None)
        self._answers.append(a)
        if a.biases is not None:
            self.biases = a.biases
        if a.system is not None:
            self.system_view = a.system
        if a.error is not None:
            self._errors.append(a.error)
        self._rows.extend(a.rows)
        self._links.extend(a.links)

    def take_answers(self) -> list[Answer]:
        """The answers since the last call, in call order: one per call (a pair updated twice
        comes twice, each with its own view)."""
        out, self._answers = self._answers, []
        return out

    def take_rows(self) -> list[SharedRows]:
        """Registration rows the owned pairs added (answered since the last call)."""
        out, self._rows = self._rows, []
        return out

    def take_links(self) -> list[SharedLinks]:
        """Links of the owned pairs updated (answered since the last call)."""
        out, self._links = self._links, []
        return out

    def take_errors(self) -> list[tuple[str, str]]:
        """``(source id, detail)`` of the calls that failed since the last call."""
        out, self._errors = self._errors, []
        return out


class CorrelationRunner(Protocol):
    """The engine's correlation stage, wherever it runs."""

    biases: list[dict[str, Any]]
    system_view: SystemTrackView | None
    drawer: SystemDrawer

    def radar(self, radar_id: str, geometry: Site, table: TrackTable, time_s: float) -> None: ...
    def reference(self, source_id: str, time_s: float, *columns: Any) -> None: ...
    def silent(self, source_id: str) -> None: ...
    def forget(self, source_id: str) -> None: ...
    def moved(self, site: Site) -> None: ...
    def mirror_rows(
        self, key: Key, site_a: Site, site_b: Site | None, rows: RegistrationRowsData
    ) -> None: ...
    def mirror_links(self, shared: SharedLinks) -> None: ...
    def others_through(self, time_s: float) -> None: ...
    def take_answers(self) -> list[Answer]: ...
    def take_rows(self) -> list[SharedRows]: ...
    def take_links(self) -> list[SharedLinks]: ...
    def take_errors(self) -> list[tuple[str, str]]: ...
    def timings(self) -> dict[str, Any]: ...
    @property
    def pending(self) -> int: ...
    def poll(self) -> None: ...
    def finish(self) -> None: ...
    def correlated_through(self, released_s: float) -> float: ...
    def wait_through(self, time_s: float) -> None: ...
    def export_state(self) -> dict[str, Any]: ...
    def request_state(self) -> Callable[[], dict[str, Any] | None]: ...
    def restore_state(
        self, state: Mapping[str, Any] | None, epoch: int, sites: Mapping[str, Site]
    ) -> None: ...
    def pair_correlators(self) -> list[PairCorrelator]: ...
    def close(self) -> None: ...


class InProcessRunner(Answers):
    """The stage in this process: every call answered at once."""

    def __init__(self, *stage_args: Any) -> None:
        self.stage = CorrelationStage(*stage_args)
        super().__init__(self.stage.correlation_params.prediction)

    def _call(self, op: str, *args: Any) -> None:
        self._take_answer(answer(self.stage, op, args))

    def radar(self, radar_id: str, geometry: Site, table: TrackTable, time_s: float) -> None:
        self._call("radar", radar_id, geometry, table, time_s)

    def reference(self, source_id: str, time_s: float, *columns: Any) -> None:
        self._call("reference", source_id, time_s, *columns)

    def silent(self, source_id: str) -> None:
        self._call("silent", source_id)

    def forget(self, source_id: str) -> None:
        self._call("forget", source_id)

    def moved(self, site: Site) -> None:
        self._call("moved", site)

    def mirror_rows(self, key: Key, site_a: Site, site_b: Site | None, rows: RegistrationRowsData) -> None:
        self._call("mirror_rows", key, site_a, site_b, rows)

    def mirror_links(self, shared: SharedLinks) -> None:
        self._call("mirror_links", shared)

    def others_through(self, time_s: float) -> None:
        self._call("others_through", time_s)

    def timings(self) -> dict[str, Any]:
        return self.stage.timings()

    @property
    def pending(self) -> int:
        return 0

    def poll(self) -> None:
        pass

    def finish(self) -> None:
        self._call("finish")

    def correlated_through(self, released_s: float) -> float:
        return released_s

    def wait_through(self, time_s: float) -> None:
        pass  # (every call is answered at once)

    def export_state(self) -> dict[str, Any]:
        return self.stage.export_state()

    def request_state(self) -> Callable[[], dict[str, Any] | None]:
        state = self.stage.export_state()
        return lambda: state

    def restore_state(self, state: Mapping[str, Any] | None, epoch: int, sites: Mapping[str, Site]) -> None:
        self.drawer.restart(epoch)
        self.stage.restore_state(state, sites)
        self.biases = self.stage.biases

    def pair_correlators(self) -> list[PairCorrelator]:
        return list(self.stage.pair_correlators.values())

    def close(self) -> None:
        pass
