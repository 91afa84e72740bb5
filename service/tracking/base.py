"""The tracking contract: what a radar's tracker takes in and gives out (pure numpy).

The engine hands each radar's validated plot batches to one :class:`Tracker`, in ``seq``
order, and reads its tracks back as a :class:`TrackTable`.  Everything here works in data
time (the plots' and batches' ``time_s``), never the wall clock.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from service.columns import concat_rows, take_rows
from service.geo import Site

if TYPE_CHECKING:
    from service.tracking.aid import PartnerReferences

FloatArray = NDArray[np.float64]

#: Track numbers one start of the service may give (per radar, and for system tracks).  With a
#: state directory (``service.state``) start ``E`` (an epoch, 0 the first) numbers from
#: :func:`first_number` ``(E)``, so no number is given twice across restarts.
TRACK_IDS_PER_EPOCH = 10**9


def first_number(epoch: int) -> int:
    """The first track number of start ``epoch`` (0: the first start, numbers from 1)."""
    if epoch < 0:
        raise ValueError(f"epoch {epoch} < 0")
    return epoch * TRACK_IDS_PER_EPOCH + 1


def _fill_labels(table: object, n: int, names: tuple[str, ...]) -> None:
    """Label columns left out (None) become ``n`` Nones (frozen dataclasses: set once here)."""
    for name in names:
        if getattr(table, name) is None:
            object.__setattr__(table, name, np.full(n, None, dtype=object))


@dataclass(frozen=True)
class PlotColumns:
    """One batch of one radar's plots, columnar, all arrays of equal length ``n``.

    ``elevation_deg`` is NaN where the radar gave none; ``altitude_m`` is NaN where none was
    given (a 2-D radar with neither: altitude 0 is assumed by the measurement model).
    ``truth_id`` is for evaluation only: no algorithm may read it, trackers only carry it.
    ``mode_3a`` and ``mode_s`` are the plots' identity codes (real radar data, strings or None;
    left out: all None).
    """

    time_s: FloatArray
    range_m: FloatArray
    azimuth_deg: FloatArray
    elevation_deg: FloatArray
    altitude_m: FloatArray
    truth_id: NDArray[np.object_]
    mode_3a: NDArray[np.object_] = None  # type: ignore[assignment]  # filled by __post_init__
    mode_s: NDArray[np.object_] = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        _fill_labels(self, self.time_s.shape[0], ("mode_3a", "mode_s"))

    def __len__(self) -> int:
        return int(self.time_s.shape[0])

    @staticmethod
    def empty() -> PlotColumns:
        f = np.empty(0)
        return PlotColumns(f, f, f, f, f, np.empty(0, dtype=object))

    def take(self, index: NDArray[np.intp] | NDArray[np.bool_]) -> PlotColumns:
        return take_rows(self, index)

    @staticmethod
    def concat(parts: list[PlotColumns]) -> PlotColumns:
        return concat_rows(PlotColumns, parts) if parts else PlotColumns.empty()


@dataclass(frozen=True)
class TrackTable:
    """A radar's tracks at one moment, columnar (row ``i`` is one track).

    States are in ECEF as the radar sees them: its systematic errors are *not* removed.
    ``covariance`` is the 6x6 covariance of ``[position, velocity]`` in ECEF.
    ``mode_3a`` / ``mode_s``: the latest identity codes of each track's plots (None: none seen).
    ``quality``: how unambiguous the track's recent plot associations were, in [0, 1] (1: every
    plot clearly its own; NaN: not known, e.g. no plot associated since its birth, or a
    tracker that does not say; left out: all NaN).
    """

    track_id: NDArray[np.str_]
    confirmed: NDArray[np.bool_]
    time_s: FloatArray
    position_ecef_m: FloatArray  # (n, 3)
    velocity_ecef_mps: FloatArray  # (n, 3)
    covariance: FloatArray  # (n, 6, 6)
    plots: NDArray[np.int64]
    #: Evaluation only, carried through (left out by the trackers: all None; the simulator's
    #: labels are written by service.evaluation.truth).
    truth_id: NDArray[np.object_] = None  # type: ignore[assignment]  # filled by __post_init__
    mode_3a: NDArray[np.object_] = None  # type: ignore[assignment]
    mode_s: NDArray[np.object_] = None  # type: ignore[assignment]
    quality: FloatArray = None  # type: ignore[assignment]  # filled by __post_init__

    def __post_init__(self) -> None:
        n = self.track_id.shape[0]
        _fill_labels(self, n, ("truth_id", "mode_3a", "mode_s"))
        if self.quality is None:
            object.__setattr__(self, "quality", np.full(n, np.nan))

    def __len__(self) -> int:
        return int(self.track_id.shape[0])

    @staticmethod
    def empty() -> TrackTable:
        return TrackTable(
            np.empty(0, dtype=str),
            np.empty(0, dtype=bool),
            np.empty(0),
            np.empty((0, 3)),
            np.empty((0, 3)),
            np.empty((0, 6, 6)),
            np.empty(0, dtype=np.int64),
        )

    def take(self, index: NDArray[np.intp] | NDArray[np.bool_]) -> TrackTable:
        return take_rows(self, index)

    def by_id(self) -> TrackTable:
        """The same tracks with rows in ``track_id`` order: the canonical order in which
        correlation reads a table, so that a table rebuilt from what another process sent is
        the same table row for row (partitioned workers)."""
        if len(self) < 2:
            return self
        order = np.argsort(self.track_id, kind="stable")
        if np.all(order[1:] > order[:-1]):
            return self
        return self.take(order)

    @staticmethod
    def concat(parts: list[TrackTable]) -> TrackTable:
        return concat_rows(TrackTable, parts) if parts else TrackTable.empty()


class Tracker(ABC):
    """Per-radar tracker: a sliding window of plots plus the tracks grown from it.

    ``update`` is called once per accepted batch, in ``seq`` order, with the batch's plots
    and the batch ``time_s`` (the time up to which the radar has reported).  It must be
    deterministic given the sequence of calls.
    """

    def __init__(self, site: Site, window_s: float) -> None:
        self.site = site
        self.window_s = window_s

    def follow(self, site: Site) -> None:
        """The radar's site was updated (the same radar: new sigmas, scan period or position):
        the plots from now on are measured with it."""
        self.site = site

    @abstractmethod
    def update(self, plots: PlotColumns, time_s: float) -> None:
        """Absorb one batch: update tracks, keep unused plots in the window, prune by data time."""

    def take_aid(self, partners: PartnerReferences | None) -> None:
        """The references of the tracks' confirmed partners for the next batch
        (:mod:`.aid`; None: no aid).  A tracker that takes no aid ignores them."""
        return None

    def wants_aid(self, time_s: float) -> bool:
        """Whether a batch at ``time_s`` may ask for the references (:meth:`take_aid`): only
        then does the engine wait for what they are read from.  A tracker that takes no aid
        never asks."""
        return False

    @abstractmethod
    def tracks(self) -> TrackTable:
        """All live tracks (tentative and confirmed) as of the last update."""

    @abstractmethod
    def drop_tracks(self) -> None:
        """Forget every track and every plot of the window (the radar expired: silent in data
        or wall time); the ids of new tracks go on from where they were, so none repeats."""

    @property
    @abstractmethod
    def window_plots(self) -> int:
        """Number of plots currently held in the sliding window."""

    @property
    def window_evicted(self) -> int:
        """Plots evicted from the sliding window so far because it held its maximum number of
        plots (0 for a tracker whose window has no such cap)."""
        return 0

    @property
    def plots_coincident(self) -> int:
        """Plots dropped so far as repeats of another plot of their batch (0 for a tracker
        without the rule)."""
        return 0

    @property
    def measurement_sigma_scale(self) -> float:
        """What the tracker multiplies the site's sigmas by (1: the site's own)."""
        return 1.0

    @property
    def aided_associations(self) -> int:
        """Associations so far decided by the aid of association (:mod:`.aid`; 0 for a tracker
        that takes no aid)."""
        return 0

    @property
    def scan_period_observed_s(self) -> float | None:
        """The revisit period the radar's plots show (None: not measured, or not by this
        tracker); the tracker counts in it where it departs from the site's."""
        return None

    @property
    def pd_measured(self) -> float | None:
        """The detection probability the radar's established tracks show (None: not measured,
        or not by this tracker)."""
        return None

    @property
    def misses_to_delete(self) -> int | None:
        """Expected misses in a row that now delete an established confirmed track (None: a
        tracker that does not count them)."""
        return None
