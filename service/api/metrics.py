"""Prometheus exposition, computed from the node's snapshot at scrape time."""

from __future__ import annotations

from collections.abc import Iterator

from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from service.transport.node import ServiceNode


class NodeCollector(Collector):
    def __init__(self, node: ServiceNode) -> None:
        self.node = node

    def collect(self) -> Iterator[Metric]:
        status = self.node.status()
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
        restarts = CounterMetricFamily(
            "topofusion_source_restarts", "Publisher restarts recognised (seq back near 1)", labels=["radar"]
        )
        expired = GaugeMetricFamily(
            "topofusion_source_expired",
            "1 while the radar has sent nothing for the expiry time",
            labels=["radar"],
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
            restarts.add_metric([rid], r["restarts"])
            expired.add_metric([rid], float(r["expired"]))
        yield from (batches, plots, lost, window, tracks, evicted, restarts, expired)
        rejected = CounterMetricFamily("topofusion_rejected", "Rejected messages", labels=["reason"])
        for reason, n in status["rejected"].items():
            rejected.add_metric([reason], n)
        yield rejected
        pairs = GaugeMetricFamily("topofusion_pairs", "Correlated pairs", labels=["status"])
        pairs.add_metric(["confirmed"], status["pairs_confirmed"])
        pairs.add_metric(["tentative"], status["pairs_tentative"])
        yield pairs
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
            value=float("nan") if agreement is None else agreement,
        )
        corr = status["correlation"]
        yield CounterMetricFamily(
            "topofusion_correlation_updates", "Correlation updates", value=corr["updates"]
        )
        p = GaugeMetricFamily(
            "topofusion_correlation_ms", "Correlation update time (ms)", labels=["quantile"]
        )
        p.add_metric(["0.5"], corr["p50_ms"])
        p.add_metric(["0.99"], corr["p99_ms"])
        yield p
        q = status["queue"]
        yield GaugeMetricFamily("topofusion_queue_depth", "Samples waiting for the worker", value=q["depth"])
        yield CounterMetricFamily(
            "topofusion_queue_dropped", "Samples dropped on a full queue", value=q["dropped"]
        )
        yield GaugeMetricFamily("topofusion_uptime_seconds", "Process uptime", value=status["uptime_s"])


def registry_for(node: ServiceNode) -> CollectorRegistry:
    registry = CollectorRegistry()
    registry.register(NodeCollector(node))
    return registry
