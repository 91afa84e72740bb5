"""The per-radar sliding window of plots, kept by data time and bounded in plots."""

from __future__ import annotations

from collections import deque

import numpy as np

from service.geo import Site
from service.tracking.base import PlotColumns
from service.tracking.measurement import Measurements

#: Default sliding window in seconds of data time: three looks of a 4 s radar, what the
#: ``logic`` initiator needs (three plots, allowing for the plots' spread within a scan).
DEFAULT_WINDOW_S: float = 12.0


def window_for(site: Site, window_s: float | None = None) -> float:
    """The window a radar's tracker keeps: ``window_s`` if given, else
    ``max(DEFAULT_WINDOW_S, 3 * site.scan_period_s)``, so that it always spans three looks."""
    return float(window_s) if window_s is not None else max(DEFAULT_WINDOW_S, 3.0 * site.scan_period_s)


class PlotWindow:
    """Plots of one radar not (yet) used by a track, over the last ``window_s`` of data time,
    at most ``max_plots`` of them.

    Pruning drops every plot older than ``newest_time - window_s``, where ``newest_time`` is
    the latest batch ``time_s`` seen (the radar's own data clock, never the wall clock).  When
    more than ``max_plots`` remain, the oldest by plot time are evicted (equal times: the
    earliest arrived first) and counted in :attr:`evicted`.

    Batches are kept as chunks and joined only when :attr:`plots` is read, so appending a
    batch costs O(batch), not O(window): raw ingest stays fast however long the window.
    A window is changed only by its own methods, and its chunks are never written in place,
    so :meth:`copy` is cheap (the chunks are shared) and a copy can be changed and then kept
    or dropped as a whole (the track manager's all-or-nothing update).

    A chunk may carry the :class:`Measurements` of its plots (row for row), which then follow
    the plots through pruning, eviction and :meth:`replace`: the track manager converts each
    plot once, when its batch arrives, instead of the whole window at every update.
    """

    def __init__(self, window_s: float, max_plots: int | None = None) -> None:
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s!r}")
        if max_plots is not None and max_plots < 0:
            raise ValueError(f"max_plots must be >= 0, got {max_plots!r}")
        self.window_s = float(window_s)
        self.max_plots = max_plots
        self._chunks: deque[tuple[PlotColumns, Measurements | None]] = deque()
        self._count = 0
        self._joined: tuple[PlotColumns, Measurements | None] | None = (PlotColumns.empty(), None)
        self.newest_time_s = -np.inf
        #: Plots evicted so far because the window held more than ``max_plots``.
        self.evicted = 0

    def __len__(self) -> int:
        return self._count

    def clear(self) -> None:
        """Every plot goes (the radar expired); the data clock and the counters stay."""
        self._chunks = deque()
        self._count = 0
        self._joined = (PlotColumns.empty(), None)

    def copy(self) -> PlotWindow:
        """An independent window with the same plots and counters (chunks shared, O(chunks))."""
        out = PlotWindow.__new__(PlotWindow)
        out.__dict__.update(self.__dict__)
        out._chunks = deque(self._chunks)
        return out

    def _join(self) -> tuple[PlotColumns, Measurements | None]:
        if self._joined is None:
            parts = list(self._chunks)
            plots = PlotColumns.concat([p for p, _ in parts])
            meas = [m for _, m in parts if m is not None]
            joined_meas = Measurements.concat(meas) if len(meas) == len(parts) else None
            self._joined = (plots, joined_meas)
            self._chunks = deque([self._joined]) if len(plots) else deque()
        return self._joined

    @property
    def plots(self) -> PlotColumns:
        """All plots in the window, in arrival order."""
        return self._join()[0]

    @property
    def measurements(self) -> Measurements | None:
        """The measurements of :attr:`plots` (same rows) when every chunk came with its own,
        else None."""
        return self._join()[1]

    def extend(self, plots: PlotColumns, time_s: float, measurements: Measurements | None = None) -> None:
        """Add a batch's plots (with their measurements, if given) and advance the data clock
        to ``time_s``, then prune."""
        if len(plots):
            self._chunks.append((plots, measurements))
            self._count += len(plots)
            self._joined = None
        self.newest_time_s = max(self.newest_time_s, float(time_s))
        self.prune()

    def replace(self, plots: PlotColumns, measurements: Measurements | None = None) -> None:
        """Keep exactly ``plots`` (e.g. after an initiator consumed some of them)."""
        self._joined = (plots, measurements)
        self._chunks = deque([self._joined]) if len(plots) else deque()
        self._count = len(plots)

    def prune(self) -> None:
        """Drop plots older than the window, then evict the oldest beyond ``max_plots``."""
        cutoff = self.newest_time_s - self.window_s
        changed = False
        kept: deque[tuple[PlotColumns, Measurements | None]] = deque()
        for chunk, meas in self._chunks:
            if chunk.time_s.size and chunk.time_s.min() < cutoff:
                keep = chunk.time_s >= cutoff
                self._count -= int(np.count_nonzero(~keep))
                changed = True
                if keep.any():
                    kept.append((chunk.take(keep), meas.take(keep) if meas is not None else None))
            else:
                kept.append((chunk, meas))
        if changed:
            self._chunks = kept
            self._joined = None
        self._evict()

    def _evict(self) -> None:
        excess = self._count - self.max_plots if self.max_plots is not None else 0
        if excess <= 0:
            return
        plots, meas = self._join()  # arrival order, so a stable sort by time breaks ties by arrival
        keep = np.ones(len(plots), dtype=bool)
        keep[np.argsort(plots.time_s, kind="stable")[:excess]] = False
        self.replace(plots.take(keep), meas.take(keep) if meas is not None else None)
        self.evicted += excess
