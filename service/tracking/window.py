"""The per-radar sliding window of plots, kept by data time and bounded in plots."""

from __future__ import annotations

from collections import deque

import numpy as np

from service.tracking.base import PlotColumns


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
    """

    def __init__(self, window_s: float, max_plots: int | None = None) -> None:
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s!r}")
        if max_plots is not None and max_plots < 0:
            raise ValueError(f"max_plots must be >= 0, got {max_plots!r}")
        self.window_s = float(window_s)
        self.max_plots = max_plots
        self._chunks: deque[PlotColumns] = deque()
        self._count = 0
        self._joined: PlotColumns | None = PlotColumns.empty()
        self.newest_time_s = -np.inf
        #: Plots evicted so far because the window held more than ``max_plots``.
        self.evicted = 0

    def __len__(self) -> int:
        return self._count

    def copy(self) -> PlotWindow:
        """An independent window with the same plots and counters (chunks shared, O(chunks))."""
        out = PlotWindow.__new__(PlotWindow)
        out.__dict__.update(self.__dict__)
        out._chunks = deque(self._chunks)
        return out

    @property
    def plots(self) -> PlotColumns:
        """All plots in the window, in arrival order."""
        if self._joined is None:
            self._joined = PlotColumns.concat(list(self._chunks))
            self._chunks = deque([self._joined]) if len(self._joined) else deque()
        return self._joined

    def extend(self, plots: PlotColumns, time_s: float) -> None:
        """Add a batch's plots and advance the data clock to ``time_s``, then prune."""
        if len(plots):
            self._chunks.append(plots)
            self._count += len(plots)
            self._joined = None
        self.newest_time_s = max(self.newest_time_s, float(time_s))
        self.prune()

    def replace(self, plots: PlotColumns) -> None:
        """Keep exactly ``plots`` (e.g. after an initiator consumed some of them)."""
        self._chunks = deque([plots]) if len(plots) else deque()
        self._count = len(plots)
        self._joined = plots

    def prune(self) -> None:
        """Drop plots older than the window, then evict the oldest beyond ``max_plots``."""
        cutoff = self.newest_time_s - self.window_s
        changed = False
        kept: deque[PlotColumns] = deque()
        for chunk in self._chunks:
            if chunk.time_s.size and chunk.time_s.min() < cutoff:
                keep = chunk.time_s >= cutoff
                self._count -= int(np.count_nonzero(~keep))
                changed = True
                if keep.any():
                    kept.append(chunk.take(keep))
            else:
                kept.append(chunk)
        if changed:
            self._chunks = kept
            self._joined = None
        self._evict()

    def _evict(self) -> None:
        excess = self._count - self.max_plots if self.max_plots is not None else 0
        if excess <= 0:
            return
        plots = self.plots  # arrival order, so a stable sort by time breaks ties by arrival
        keep = np.ones(len(plots), dtype=bool)
        keep[np.argsort(plots.time_s, kind="stable")[:excess]] = False
        self.replace(plots.take(keep))
        self.evicted += excess
