"""The per-radar sliding window of plots, kept by data time."""

from __future__ import annotations

import numpy as np

from service.tracking.base import PlotColumns


class PlotWindow:
    """Plots of one radar not (yet) used by a track, over the last ``window_s`` of data time.

    Appending keeps arrival order; pruning drops every plot older than
    ``newest_time - window_s``, where ``newest_time`` is the latest batch ``time_s`` seen
    (the radar's own data clock, never the wall clock).
    """

    def __init__(self, window_s: float) -> None:
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s!r}")
        self.window_s = float(window_s)
        self._plots = PlotColumns.empty()
        self.newest_time_s = -np.inf

    def __len__(self) -> int:
        return len(self._plots)

    @property
    def plots(self) -> PlotColumns:
        return self._plots

    def extend(self, plots: PlotColumns, time_s: float) -> None:
        """Add a batch's plots and advance the data clock to ``time_s``, then prune."""
        if len(plots):
            self._plots = PlotColumns.concat([self._plots, plots])
        self.newest_time_s = max(self.newest_time_s, float(time_s))
        self.prune()

    def replace(self, plots: PlotColumns) -> None:
        """Keep exactly ``plots`` (e.g. after an initiator consumed some of them)."""
        self._plots = plots

    def prune(self) -> None:
        keep = self._plots.time_s >= self.newest_time_s - self.window_s
        if not np.all(keep):
            self._plots = self._plots.take(keep)
