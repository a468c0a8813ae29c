"""The daemon's health as Prometheus text (exposition format 0.0.4), rendered by ``prometheus_client`` from one
``/status`` snapshot: counters, gauges and the latency histograms per stage.

The daemon keeps its own counters (plain ints on the tick's path); this module only turns a snapshot of them into
metric families, once per snapshot (see :class:`~mocapd.service.http_status.StatusServer`), so a scrape never
touches live state and never costs the tick loop more than one render per snapshot.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
from prometheus_client import generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4
from prometheus_client.registry import Collector, CollectorRegistry

from mocapd.pipeline.latency import BUCKETS_MS, LatencyStats

#: the Content-Type of /metrics
CONTENT_TYPE = CONTENT_TYPE_PLAIN_0_0_4


def latency_snapshot(latency: Mapping[str, LatencyStats]) -> dict[str, dict[str, Any]]:
    """The latency histograms as plain data (cumulative bucket counts, sum in seconds, count): copied when the
    status snapshot is taken, so the histograms on /metrics are of the same instant as the rest."""
    return {
        stage: {
            "buckets": [int(c) for c in np.cumsum(s.bucket_counts)],
            "sum_s": s.sum_ns / 1e9,
            "count": s.count,
        }
        for stage, s in latency.items()
    }


class _SnapshotCollector(Collector):
    """Metric families from one status document (``status["latency_histograms"]``: :func:`latency_snapshot`)."""

    def __init__(self, status: Mapping[str, Any]) -> None:
        self.status = status

    def collect(self) -> Iterator[Metric]:
        st = self.status
        o = st["output"]

        def counter(name: str, help_: str, labels: list[str], samples: list[tuple[list[str], float]]) -> Metric:
            m = CounterMetricFamily(name, help_, labels=labels)
            for values, v in samples:
                m.add_metric(values, v)
            return m

        def gauge(name: str, help_: str, labels: list[str], samples: list[tuple[list[str], float]]) -> Metric:
            m = GaugeMetricFamily(name, help_, labels=labels)
            for values, v in samples:
                m.add_metric(values, v)
            return m

        yield counter("mocapd_frames_published", "Pose frames published.", [], [([], o["frames"])])
        yield counter("mocapd_missed_ticks", "Output ticks skipped because the previous one overran.", [],
                      [([], o["missed_ticks"])])  # fmt: skip
        yield counter("mocapd_late_ticks", "Output ticks run late (within daemon.max_catch_up_s).", [],
                      [([], o["late_ticks"])])  # fmt: skip
        yield gauge("mocapd_output_rate_hz", "Frames published in the last second.", [], [([], o["achieved_hz"])])
        yield gauge("mocapd_output_rate_configured_hz", "Configured output rate.", [], [([], o["configured_hz"])])
        people = len(st["frame"]["people"]) if st["frame"] else 0
        yield gauge("mocapd_people", "People solved in the latest frame.", [], [([], people)])
        yield counter("mocapd_person_solves", "Per-person solves.", [], [([], st["counters"]["person_solves"])])
        yield counter("mocapd_solves_not_converged", "Solves that hit the iteration limit or failed.", [],
                      [([], st["counters"]["not_converged"])])  # fmt: skip
        cams = st["cameras"]
        yield counter("mocapd_camera_detected_frames", "Detected frames received per camera.", ["camera"],
                      [([str(c["name"])], c["frames"]) for c in cams])  # fmt: skip
        yield counter("mocapd_keypoint_lookups",
                      "Keypoint look-ups per camera and outcome (stale/empty: the camera was missing at solve time).",
                      ["camera", "status"],
                      [([str(c["name"]), str(k)], v) for c in cams for k, v in c["samples"].items()])  # fmt: skip
        devices = st["imu"]["devices"]
        yield gauge("mocapd_imu_device_streaming", "1 while the serial IMU device streams.", ["device"],
                    [([str(x["path"])], 1 if x["streaming"] else 0) for x in devices])  # fmt: skip
        yield counter("mocapd_imu_device_samples", "Samples received per serial IMU device.", ["device"],
                      [([str(x["path"])], x["samples"]) for x in devices])  # fmt: skip
        yield counter("mocapd_imu_device_disconnects", "Links lost per serial IMU device.", ["device"],
                      [([str(x["path"])], x["disconnects"]) for x in devices])  # fmt: skip
        yield counter("mocapd_imu_lookups", "IMU look-ups at solve time per sensor and outcome.", ["sensor", "status"],
                      [([str(k), str(s)], v) for k, c in st["imu_lookups"].items() for s, v in c.items()])  # fmt: skip
        tasks = st["tasks"]
        yield counter("mocapd_task_failures", "Failures of supervised tasks (each restarted with back-off).",
                      ["task"], [([str(k)], t["failures"]) for k, t in tasks.items()])  # fmt: skip
        yield gauge("mocapd_task_running", "1 while the supervised task runs.", ["task"],
                    [([str(k)], 1 if t["running"] else 0) for k, t in tasks.items()])  # fmt: skip
        yield counter("mocapd_input_rejected", "Input rejected at a door (network), per door and reason.",
                      ["door", "reason"], list(_rejections(st)))  # fmt: skip
        yield counter("mocapd_imu_sensors_evicted", "Unconfigured IMU sensors evicted from the bounded table.", [],
                      [([], st["imu"].get("sensors_evicted", 0))])  # fmt: skip
        yield counter("mocapd_stage_cpu_seconds", "CPU time spent per scheduler stage.", ["stage"],
                      [([str(k)], v) for k, v in st["cpu_s"].items()])  # fmt: skip
        h = HistogramMetricFamily(
            "mocapd_latency_seconds",
            "Latency per stage; end_to_end = solve instant -> frame published; "
            "imu_to_publish = instant a suit wearer's pose is for (newest IMU sample when predicted) -> published.",
            labels=["stage"],
        )
        for stage, s in st.get("latency_histograms", {}).items():
            bounds = [f"{b / 1e3:g}" for b in BUCKETS_MS] + ["+Inf"]
            h.add_metric([stage], list(zip(bounds, s["buckets"], strict=True)), sum_value=s["sum_s"])
        yield h


def render_metrics(status: Mapping[str, Any]) -> bytes:
    """The /metrics document of one status snapshot (which carries ``latency_histograms``)."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(_SnapshotCollector(status))
    return generate_latest(registry)


def _rejections(st: Mapping[str, Any]) -> Iterator[tuple[list[str], float]]:
    """(door, reason) counts of the network doors as ``/status`` shows them (docs/reliability.md)."""
    imu = st["imu"]
    if imu.get("bridge"):
        for reason, n in imu["bridge"]["rejected_reasons"].items():
            yield ["imu_bridge", str(reason)], n
    if imu.get("slimevr"):
        sv = imu["slimevr"]
        for reason, n in sv["bad_reasons"].items():
            yield ["slimevr", str(reason)], n
        yield ["slimevr", "unknown_source"], sv["unknown_source"]
        yield ["slimevr", "unannounced_sensor"], sv["unannounced_sensor"]
    ws = st.get("sinks", {}).get("websocket")
    if ws:
        for reason, n in ws["rejected_requests"].items():
            yield ["websocket", str(reason)], n
        for reason, n in ws["refused"].items():
            yield ["websocket", f"refused_{reason}"], n
