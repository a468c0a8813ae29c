"""The daemon's health as Prometheus text (exposition format 0.0.4): counters, gauges and latency histograms."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mocapd.service.app import Daemon


def _label(value: str) -> str:
    return value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def render_metrics(d: Daemon) -> str:
    """Every metric of a running :class:`~mocapd.service.app.Daemon`."""
    s = d.scheduler.status()
    out: list[str] = []

    def metric(name: str, kind: str, help_: str, samples: list[tuple[str, float]]) -> None:
        out.append(f"# HELP {name} {help_}")
        out.append(f"# TYPE {name} {kind}")
        for labels, value in samples:
            out.append(f"{name}{{{labels}}} {value:g}" if labels else f"{name} {value:g}")

    metric("mocapd_frames_published_total", "counter", "Pose frames published.", [("", s["frame"])])
    metric("mocapd_missed_ticks_total", "counter", "Output ticks skipped because the previous one overran.",
           [("", d.plan.missed if d.plan else 0)])  # fmt: skip
    metric("mocapd_late_ticks_total", "counter", "Output ticks run late (within daemon.max_catch_up_s).",
           [("", d.plan.late if d.plan else 0)])  # fmt: skip
    metric("mocapd_output_rate_hz", "gauge", "Frames published in the last second.", [("", len(d._rate_window))])
    metric("mocapd_output_rate_configured_hz", "gauge", "Configured output rate.", [("", d.scheduler.options.rate_hz)])
    people = len(d.latest.people) if d.latest else 0
    metric("mocapd_people", "gauge", "People solved in the latest frame.", [("", people)])
    metric("mocapd_person_solves_total", "counter", "Per-person solves.", [("", s["counters"]["person_solves"])])
    metric("mocapd_solves_not_converged_total", "counter", "Solves that hit the iteration limit or failed.",
           [("", s["counters"]["not_converged"])])  # fmt: skip
    cams = s["cameras"]
    names = [src.name for src in d.rig.sources]
    metric("mocapd_camera_detected_frames_total", "counter", "Detected frames received per camera.",
           [(f'camera="{_label(n)}"', c["frames"]) for n, c in zip(names, cams, strict=False)])  # fmt: skip
    metric("mocapd_keypoint_lookups_total", "counter",
           "Keypoint look-ups per camera and outcome (stale/empty: the camera was missing at solve time).",
           [(f'camera="{_label(n)}",status="{k}"', v)
            for n, c in zip(names, cams, strict=False) for k, v in c["samples"].items()])  # fmt: skip
    imu = d.imu.status()
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
            for k, c in s["imu_samples"].items() for st, v in c.items()])  # fmt: skip
    tasks = d.supervisor.tasks
    metric("mocapd_task_failures_total", "counter", "Failures of supervised tasks (each restarted with back-off).",
           [(f'task="{_label(k)}"', t.failures) for k, t in tasks.items()])  # fmt: skip
    metric("mocapd_task_running", "gauge", "1 while the supervised task runs.",
           [(f'task="{_label(k)}"', 1 if t.running else 0) for k, t in tasks.items()])  # fmt: skip
    metric("mocapd_stage_cpu_seconds_total", "counter", "CPU time spent per scheduler stage.",
           [(f'stage="{k}"', v) for k, v in s["cpu_s"].items()])  # fmt: skip
    out.append("# HELP mocapd_latency_seconds Latency per stage; end_to_end = solve instant -> frame published.")
    out.append("# TYPE mocapd_latency_seconds histogram")
    for stage, stats in d.scheduler.latency.items():
        out.extend(stats.prometheus("mocapd_latency_seconds", f'stage="{stage}"'))
    return "\n".join(out) + "\n"
