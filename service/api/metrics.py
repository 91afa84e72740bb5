"""Prometheus exposition, computed from the node's snapshot at scrape time.

Every family is built from ``node.status()`` and the bias estimates (``GET /biases``) when
scraped, so that ``/metrics`` and ``/status`` never disagree.  Two figures need a clock the
snapshot does not hold, and are measured here in wall time:

* a radar's data lag: now minus its data clock (``last_time_s``);
* a radar's update rate: batches per wall second over about ``RATE_WINDOW_S``, from the
  ``batches`` counter as this collector saw it at earlier scrapes.  Wall seconds, not data
  seconds: a silent radar's data clock stops, so a rate in data time would keep its last value
  for ever, while the wall rate falls to 0 (docs/operations/metrics.md).

The registry also carries prometheus_client's process, platform and garbage-collector
collectors, and ``topofusion_build_info``.
"""

from __future__ import annotations

import math
import platform
import threading
import time
from collections import deque
from collections.abc import Iterator
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.gc_collector import GCCollector
from prometheus_client.platform_collector import PlatformCollector
from prometheus_client.process_collector import ProcessCollector
from prometheus_client.registry import Collector

from service.transport.node import ServiceNode
from service.wire.vocabulary import REJECTION_REASONS

#: A radar's update rate is measured over (about) this much wall time (s): a minute averages
#: several scans of the slowest radars (12 s), and a silent radar reads 0 within it.
RATE_WINDOW_S = 60.0
#: Counter readings are kept at most once per this many seconds (bounds the memory whatever
#: the scrape rate), and a rate is measured over at least this long.
RATE_SAMPLE_S = 1.0
#: Bias families: (metric name, ``BiasEstimate`` field, help).
BIAS_GAUGES = (
    ("topofusion_bias_range_m", "range_bias_m", "Estimated range bias (m)"),
    ("topofusion_bias_azimuth_deg", "azimuth_bias_deg", "Estimated azimuth bias (deg)"),
    ("topofusion_bias_elevation_deg", "elevation_bias_deg", "Estimated elevation bias (deg)"),
    ("topofusion_bias_range_sigma_m", "range_bias_sigma_m", "1-sigma of the range bias estimate (m)"),
    ("topofusion_bias_azimuth_sigma_deg", "azimuth_bias_sigma_deg", "1-sigma of the azimuth bias (deg)"),
    (
        "topofusion_bias_elevation_sigma_deg",
        "elevation_bias_sigma_deg",
        "1-sigma of the elevation bias (deg)",
    ),
    ("topofusion_bias_pairs_used", "pairs_used", "Confirmed pairs of the latest update in the bias solve"),
    ("topofusion_bias_range_gain_ppm", "range_gain_ppm", "Estimated range gain (ppm; 0: held at zero)"),
    ("topofusion_bias_range_gain_sigma_ppm", "range_gain_sigma_ppm", "1-sigma of the range gain (ppm)"),
    ("topofusion_bias_time_s", "time_bias_s", "Estimated time-stamp bias (s)"),
    ("topofusion_bias_time_sigma_s", "time_bias_sigma_s", "1-sigma of the time-stamp bias (s)"),
)
#: Performance families (contract §5.3): (metric name, ``RadarPerformance`` section, field, help).
PERFORMANCE_GAUGES = (
    ("topofusion_performance_pd", "detection", "pd", "Detection probability against the references"),
    ("topofusion_performance_pd_sigma", "detection", "pd_sigma", "1-sigma of the detection probability"),
    (
        "topofusion_performance_position_rms_m",
        "position",
        "rms_m",
        "Horizontal error RMS, biases compensated (m)",
    ),
    (
        "topofusion_performance_position_rms_uncorrected_m",
        "position",
        "rms_uncorrected_m",
        "Horizontal error RMS before bias compensation (m)",
    ),
    ("topofusion_performance_mode_3a_rate", "mode_3a", "rate", "Share of correct Mode 3/A codes"),
    ("topofusion_performance_mode_c_rate", "mode_c", "rate", "Share of correct Mode C (within 200 ft)"),
    ("topofusion_performance_aircraft", None, "aircraft", "Reference aircraft behind the figures"),
)


def _distribution_version(name: str) -> str:
    try:
        return version(name)
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown"


class RateMeter:
    """Per radar, batches per wall second over about ``RATE_WINDOW_S``, from counter readings.

    Each scrape hands in the counters; the rate is the increase since the newest reading at
    least ``window_s`` old (or, until there is one, the oldest), over the wall time between.
    NaN until a radar has a reading at least ``sample_s`` old (two scrapes a moment apart
    would give 0 or some huge rate).  A counter that went down (the radar was forgotten and
    came back) starts the radar afresh.
    """

    def __init__(self, window_s: float = RATE_WINDOW_S, sample_s: float = RATE_SAMPLE_S) -> None:
        self.window_s = window_s
        self.sample_s = sample_s
        self._readings: dict[str, deque[tuple[float, int]]] = {}
        self._lock = threading.Lock()  # scrapes run on the HTTP server's worker threads

    def rates(self, counters: dict[str, int], now: float) -> dict[str, float]:
        out = {}
        with self._lock:
            for rid in set(self._readings) - set(counters):
                del self._readings[rid]
            for rid, n in counters.items():
                seen = self._readings.setdefault(rid, deque())
                if seen and n < seen[-1][1]:
                    seen.clear()
                while len(seen) >= 2 and now - seen[1][0] >= self.window_s:
                    seen.popleft()
                base = seen[0] if seen else None
                span = now - base[0] if base is not None else 0.0
                out[rid] = (n - base[1]) / span if base is not None and span >= self.sample_s else math.nan
                if not seen or now - seen[-1][0] >= self.sample_s:
                    seen.append((now, n))
        return out


class NodeCollector(Collector):
    def __init__(self, node: ServiceNode) -> None:
        self.node = node
        self.rates = RateMeter()
        self.build = {
            "version": _distribution_version("topofusion"),
            "python": platform.python_version(),
            "zenoh": _distribution_version("eclipse-zenoh"),
        }

    def collect(self) -> Iterator[Metric]:
        status = self.node.status()
        yield from self._radars(status)
        rejected = CounterMetricFamily("topofusion_rejected", "Rejected messages", labels=["reason"])
        # Every reason from the start: a reason's first rejection is then an increase from 0,
        # which rate() and increase() see (a series that appears at 1 shows no increase).
        for reason, n in {**dict.fromkeys(REJECTION_REASONS, 0), **status["rejected"]}.items():
            rejected.add_metric([reason], n)
        yield rejected
        pairs = GaugeMetricFamily("topofusion_pairs", "Correlated pairs", labels=["status"])
        pairs.add_metric(["confirmed"], status["pairs_confirmed"])
        pairs.add_metric(["tentative"], status["pairs_tentative"])
        yield pairs
        yield GaugeMetricFamily(
            "topofusion_pairs_held", "Tentative pairs held (Pair.held)", value=status.get("pairs_held", 0)
        )
        yield from self._identity(status)
        yield from self._correlation(status["correlation"])
        yield from self._biases()
        yield from self._performance()
        q = status["queue"]
        yield GaugeMetricFamily("topofusion_queue_depth", "Samples waiting for the worker", value=q["depth"])
        yield GaugeMetricFamily(
            "topofusion_queue_capacity", "Samples the ingest queue holds at most", value=q["capacity"]
        )
        yield GaugeMetricFamily(
            "topofusion_queue_bytes", "Payload bytes waiting for the worker", value=q.get("bytes", 0)
        )
        yield GaugeMetricFamily(
            "topofusion_queue_capacity_bytes",
            "Payload bytes the ingest queue holds at most (0: not reported)",
            value=q.get("capacity_bytes", 0),
        )
        yield CounterMetricFamily(
            "topofusion_queue_dropped", "Samples dropped on a full queue", value=q["dropped"]
        )
        by_key = CounterMetricFamily(
            "topofusion_queue_dropped_by_key",
            "Samples dropped on a full queue, by key expression (at most 1024 keys, the rest summed)",
            labels=["key"],
        )
        for key, n in sorted(q.get("dropped_by_key", {}).items()):
            by_key.add_metric([key], n)
        yield by_key
        yield GaugeMetricFamily("topofusion_uptime_seconds", "Process uptime", value=status["uptime_s"])
        yield from self._state(status.get("state"))
        complete = GaugeMetricFamily(
            "topofusion_outputs_data_time_seconds",
            "Data time up to which every published output reflects every processed input (Unix s)",
        )
        if status.get("outputs_time_s") is not None:
            complete.add_metric([], status["outputs_time_s"])
        yield complete
        yield GaugeMetricFamily(
            "topofusion_correlation_pending",
            "Radar messages the correlation stage has not answered yet",
            value=float(status["correlation"].get("pending", 0)),
        )
        yield GaugeMetricFamily(
            "topofusion_ready",
            "1 while GET /readyz answers 200 (it says why not)",
            value=float(self.node.ready),
        )
        yield from self._feed(status.get("feed"))
        info = GaugeMetricFamily(
            "topofusion_build_info",
            "Always 1: the service's version and those of Python and Zenoh",
            labels=list(self.build),
        )
        info.add_metric(list(self.build.values()), 1)
        yield info

    def _radars(self, status: dict[str, Any]) -> Iterator[Metric]:
        batches = CounterMetricFamily("topofusion_batches", "Accepted plot batches", labels=["radar"])
        plots = CounterMetricFamily("topofusion_plots", "Accepted plots", labels=["radar"])
        lost = CounterMetricFamily(
            "topofusion_lost_batches", "Batches missing from seq jumps", labels=["radar"]
        )
        window = GaugeMetricFamily("topofusion_window_plots", "Plots in the sliding window", labels=["radar"])
        tracks = GaugeMetricFamily("topofusion_tracks", "Live tracks", labels=["radar", "status"])
        evicted = CounterMetricFamily(
            "topofusion_window_evicted_plots",
            "Plots evicted from the window by its plot bound (oldest first)",
            labels=["radar"],
        )
        coincident = CounterMetricFamily(
            "topofusion_plots_coincident",
            "Plots dropped as repeats of another plot of their batch (one cell and Mode S address)",
            labels=["radar"],
        )
        pd = GaugeMetricFamily(
            "topofusion_radar_pd_measured",
            "The detection probability the radar's established tracks show (absent until measured)",
            labels=["radar"],
        )
        restarts = CounterMetricFamily(
            "topofusion_source_restarts", "Publisher restarts recognised (seq back near 1)", labels=["radar"]
        )
        expired = GaugeMetricFamily(
            "topofusion_source_expired",
            "1 while the radar has sent nothing for the expiry time",
            labels=["radar"],
        )
        lag = GaugeMetricFamily(
            "topofusion_radar_data_lag_seconds",
            "Wall clock now minus the radar's newest data time (s)",
            labels=["radar"],
        )
        rate = GaugeMetricFamily(
            "topofusion_radar_update_rate_hz",
            f"Accepted batches per wall second over the last {RATE_WINDOW_S:.0f} s (NaN: one reading yet)",
            labels=["radar"],
        )
        now = time.time()
        rates = self.rates.rates(
            {r["radar_id"]: int(r["batches"]) for r in status["radars"]}, time.monotonic()
        )
        for r in status["radars"]:
            rid = r["radar_id"]
            batches.add_metric([rid], r["batches"])
            plots.add_metric([rid], r["plots"])
            lost.add_metric([rid], r["lost_batches"])
            window.add_metric([rid], r["window_plots"])
            tracks.add_metric([rid, "confirmed"], r["tracks_confirmed"])
            tracks.add_metric([rid, "tentative"], r["tracks_tentative"])
            evicted.add_metric([rid], r["window_evicted"])
            coincident.add_metric([rid], r.get("plots_coincident", 0))
            if r.get("pd_measured") is not None:
                pd.add_metric([rid], float(r["pd_measured"]))
            restarts.add_metric([rid], r["restarts"])
            expired.add_metric([rid], float(r["expired"]))
            if r["last_time_s"] is not None:  # before its first batch a radar has no data to lag
                lag.add_metric([rid], now - float(r["last_time_s"]))
            rate.add_metric([rid], rates[rid])
        yield from (batches, plots, lost, window, tracks, evicted, coincident, pd)
        yield from (restarts, expired, lag, rate)

    def _identity(self, status: dict[str, Any]) -> Iterator[Metric]:
        ident = status.get("identity") or {"by_pair": []}
        with_s = GaugeMetricFamily(
            "topofusion_identity_pairs_with_mode_s",
            "Confirmed pairs whose two tracks both carry a Mode S address",
            labels=["radar_a", "radar_b"],
        )
        equal = GaugeMetricFamily(
            "topofusion_identity_mode_s_equal",
            "Of those, the pairs whose two Mode S addresses are equal",
            labels=["radar_a", "radar_b"],
        )
        for row in ident["by_pair"]:
            with_s.add_metric([row["radar_a"], row["radar_b"]], row["pairs_with_mode_s"])
            equal.add_metric([row["radar_a"], row["radar_b"]], row["mode_s_equal"])
        yield with_s
        yield equal
        agreement = ident.get("agreement")
        yield GaugeMetricFamily(
            "topofusion_identity_agreement",
            "Share of confirmed pairs with Mode S on both tracks whose addresses are equal (NaN: none)",
            value=math.nan if agreement is None else agreement,
        )

    def _correlation(self, corr: dict[str, Any]) -> Iterator[Metric]:
        yield CounterMetricFamily(
            "topofusion_correlation_updates", "Correlation updates", value=corr["updates"]
        )
        p = GaugeMetricFamily(
            "topofusion_correlation_ms", "Correlation update time (ms)", labels=["quantile"]
        )
        p.add_metric(["0.5"], corr["p50_ms"])
        p.add_metric(["0.99"], corr["p99_ms"])
        yield p
        yield HistogramMetricFamily(
            "topofusion_correlation_duration_seconds",
            "Pair update time, every update since the start (s)",
            buckets=list(corr["duration_buckets"].items()),
            sum_value=corr["duration_sum_s"],
        )

    def _performance(self) -> Iterator[Metric]:
        """Each radar's ``GET /radars/{id}/performance`` figures (a figure without data: none)."""
        snap = self.node.snapshot
        view = snap.performance
        figures = [] if view is None else [view.of(rid) for rid in sorted(view.figures)]
        for name, section, field, text in PERFORMANCE_GAUGES:
            gauge = GaugeMetricFamily(name, text, labels=["radar"])
            for f in figures:
                value = f[field] if section is None else f[section][field]
                if value is not None:
                    gauge.add_metric([f["radar_id"]], value)
            yield gauge

    def _biases(self) -> Iterator[Metric]:
        """The joint bias estimate, as ``GET /biases`` answers it (a radar without one: none)."""
        biases = self.node.snapshot.biases()
        for name, field, text in BIAS_GAUGES:
            gauge = GaugeMetricFamily(name, text, labels=["radar"])
            for b in biases:
                if b.get(field) is not None:  # a sigma may be null: not known
                    gauge.add_metric([b["radar_id"]], b[field])
            yield gauge

    @staticmethod
    def _feed(feed: dict[str, Any] | None) -> Iterator[Metric]:
        """``/status`` ``feed``: whether the outputs are still live (``pipeline.feed``)."""
        if feed is None:
            return
        yield GaugeMetricFamily(
            "topofusion_outputs_stale",
            "1 while the data clock has not moved for the feed's stale_s (GET /readyz says so)",
            value=float(feed["stale"]),
        )
        yield CounterMetricFamily(
            "topofusion_feed_outages",
            "Whole-feed outages that ended (the data clock jumped with a quorum of the sources)",
            value=feed["outages"],
        )
        yield CounterMetricFamily(
            "topofusion_sources_expired_by_wall_clock",
            "Sources expired for silence on the wall clock while the data clock stood still",
            value=feed["expired_by_wall_clock"],
        )

    @staticmethod
    def _state(state: dict[str, Any] | None) -> Iterator[Metric]:
        """``--state-dir``: the families are always there (no samples without a directory)."""
        writes = CounterMetricFamily("topofusion_state_writes", "State files written (--state-dir)")
        failures = CounterMetricFamily("topofusion_state_write_failures", "State writes that failed")
        data_time = GaugeMetricFamily(
            "topofusion_state_data_time_seconds", "Newest data clock of the state on disk (Unix s)"
        )
        size = GaugeMetricFamily("topofusion_state_bytes", "Size of the last state file written")
        if state is not None:
            writes.add_metric([], state["writes"])
            failures.add_metric([], state["failures"])
            if state["data_time_s"] is not None:
                data_time.add_metric([], state["data_time_s"])
            size.add_metric([], state["bytes"])
        yield from (writes, failures, data_time, size)


def registry_for(node: ServiceNode) -> CollectorRegistry:
    """The service's own registry: its node's families, and the process (CPU, memory, open
    files; Linux), the Python platform and the garbage collector."""
    registry = CollectorRegistry()
    registry.register(NodeCollector(node))
    ProcessCollector(registry=registry)
    PlatformCollector(registry=registry)
    GCCollector(registry=registry)
    return registry
