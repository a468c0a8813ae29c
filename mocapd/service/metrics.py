"""The daemon's health as Prometheus text (exposition format 0.0.4): counters, gauges and latency histograms."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from mocapd.pipeline.latency import LatencyStats


def _label(value: str) -> str:
    return value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def render_metrics(status: Mapping[str, Any], latency: Mapping[str, LatencyStats]) -> str:
    """Every metric of a running daemon, from its ``/status`` document and its latency histograms per stage."""
    out: list[str] = []
    o = status["output"]

    def metric(name: str, kind: str, help_: str, samples: list[tuple[str, float]]) -> None:
        out.append(f"# HELP {name} {help_}")
        out.append(f"# TYPE {name} {kind}")
        for labels, value in samples:
            out.append(f"{name}{{{labels}}} {value:g}" if labels else f"{name} {value:g}")

    metric("mocapd_frames_published_total", "counter", "Pose frames published.", [("", o["frames"])])
    metric("mocapd_missed_ticks_total", "counter", "Output ticks skipped because the previous one overran.",
           [("", o["missed_ticks"])])  # fmt: skip
    metric("mocapd_late_ticks_total", "counter", "Output ticks run late (within daemon.max_catch_up_s).",
           [("", o["late_ticks"])])  # fmt: skip
    metric("mocapd_output_rate_hz", "gauge", "Frames published in the last second.", [("", o["achieved_hz"])])
    metric("mocapd_output_rate_configured_hz", "gauge", "Configured output rate.", [("", o["configured_hz"])])
    people = len(status["frame"]["people"]) if status["frame"] else 0
    metric("mocapd_people", "gauge", "People solved in the latest frame.", [("", people)])
    metric("mocapd_person_solves_total", "counter", "Per-person solves.", [("", status["counters"]["person_solves"])])
    metric("mocapd_solves_not_converged_total", "counter", "Solves that hit the iteration limit or failed.",
           [("", status["counters"]["not_converged"])])  # fmt: skip
    cams = status["cameras"]
    names = [c["name"] for c in cams]
    metric("mocapd_camera_detected_frames_total", "counter", "Detected frames received per camera.",
           [(f'camera="{_label(n)}"', c["frames"]) for n, c in zip(names, cams, strict=False)])  # fmt: skip
    metric("mocapd_keypoint_lookups_total", "counter",
           "Keypoint look-ups per camera and outcome (stale/empty: the camera was missing at solve time).",
           [(f'camera="{_label(n)}",status="{k}"', v)
            for n, c in zip(names, cams, strict=False) for k, v in c["samples"].items()])  # fmt: skip
    imu = status["imu"]
    devices = imu["devices"]
    assert isinstance(devices, list)
    metric("mocapd_imu_device_streaming", "gauge", "1 while the serial IMU device streams.",
           [(f'device="{_label(str(x["path"]))}"', 1 if x["streaming"] else 0) for x in devices])  # fmt: skip
    metric("mocapd_imu_device_samples_total", "counter", "Samples received per serial IMU device.",
           [(f'device="{_label(str(x["path"]))}"', x["samples"]) for x in devices])  # fmt: skip
    metric("mocapd_imu_device_disconnects_total", "counter", "Links lost per serial IMU device.",
           [(f'device="{_label(str(x["path"]))}"', x["disconnects"]) for x in devices])  # fmt: skip
    metric("mocapd_imu_lookups_total", "counter", "IMU look-ups at solve time per sensor and outcome.",
           [(f'sensor="{_label(k)}",status="{st}"', v)
            for k, c in status["imu_lookups"].items() for st, v in c.items()])  # fmt: skip
    tasks = status["tasks"]
    metric("mocapd_task_failures_total", "counter", "Failures of supervised tasks (each restarted with back-off).",
           [(f'task="{_label(k)}"', t["failures"]) for k, t in tasks.items()])  # fmt: skip
    metric("mocapd_task_running", "gauge", "1 while the supervised task runs.",
           [(f'task="{_label(k)}"', 1 if t["running"] else 0) for k, t in tasks.items()])  # fmt: skip
    metric("mocapd_stage_cpu_seconds_total", "counter", "CPU time spent per scheduler stage.",
           [(f'stage="{k}"', v) for k, v in status["cpu_s"].items()])  # fmt: skip
    out.append(
        "# HELP mocapd_latency_seconds Latency per stage; end_to_end = solve instant -> frame published; "
        "imu_to_publish = instant a suit wearer's pose is for (newest IMU sample when predicted) -> published."
    )
    out.append("# TYPE mocapd_latency_seconds histogram")
    for stage, stats in latency.items():
        out.extend(stats.prometheus("mocapd_latency_seconds", f'stage="{stage}"'))
    return "\n".join(out) + "\n"
