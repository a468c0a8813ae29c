"""Existing IMU recordings as mocapd sessions: ``mocapd import mtw`` and ``mocapd import mvnx``.

An imported session is an ordinary session directory (``docs/sessions.md``) with no cameras: ``imu.mcs`` holds
every sample of every sensor, ``keypoints.mcs`` and ``poses.mcs`` are empty, and ``manifest.json`` describes a rig
without cameras (the shipped config with the sensor assignment in ``[imu.assignment]``, the skeleton at
``--height`` with any segment lengths given (``--thigh`` ..., recorded in ``[imu.body]`` and ``skeleton.from``), the
default pose prior) plus an ``imported`` section: where the data came from, each sensor's
samples, rate, orientation and acceleration source, and the suit name. Its ``suits`` list is empty until
``mocapd calibrate imu --from SESSION`` calibrates it; then ``mocapd resolve`` solves it (IMU-only) and
``mocapd export`` writes BVH/CSV.

Reading and time alignment of the recordings, sensor ids of MVNX sensors and writing the streams:
:mod:`mocapd.io.imu_recordings`; this module adds the manifest (it needs the shipped config).
"""

from __future__ import annotations

import datetime as dt
import math
import platform
from typing import Any

import numpy as np

import mocapd
from mocapd.core.body_dims import BodySpec
from mocapd.core.imu_calibration import parse_assignment
from mocapd.core.keypoints import coco17_targets
from mocapd.core.names import check_name
from mocapd.errors import InputError
from mocapd.io.imu_recordings import (
    MVN_SENSOR_BONES,
    T0_NS,
    SensorStream,
    mvnx_assignment,
    streams_from_mt_exports,
    streams_from_mvnx,
    write_imported_session,
)
from mocapd.io.session import STREAMS
from mocapd.service.config import DEFAULT_CONFIG, config_document, load_config

MIN_HEIGHT_M = 0.5
MAX_HEIGHT_M = 2.5
"""Heights ``--height`` accepts (the skeleton is scaled from it)."""

__all__ = [
    "MVN_SENSOR_BONES",
    "imported_manifest",
    "mvnx_assignment",
    "parse_assign_pairs",
    "streams_from_mt_exports",
    "streams_from_mvnx",
    "write_imported_session",
]


def imported_manifest(
    streams: list[SensorStream],
    assignment: dict[str, str],
    *,
    source: str,
    suit: str,
    height: float,
    imu_set: str | None = None,
    segments: dict[str, float] | None = None,
    body_from: str | None = None,
) -> dict[str, Any]:
    """The manifest of an imported session (see the module docstring). The skeleton is the default proportions at
    ``height`` with any ``segments`` given (:mod:`mocapd.core.body_dims`); the manifest records which, and
    ``body_from`` where they came from a file (``"mvnx"``: MVN's calibrated body)."""
    check_name(suit, "--suit")
    if not (isinstance(height, float | int) and math.isfinite(height) and MIN_HEIGHT_M <= height <= MAX_HEIGHT_M):
        raise InputError(f"--height {height!r}: allowed: {MIN_HEIGHT_M:g} to {MAX_HEIGHT_M:g} m")
    missing = sorted(set(assignment) - {s.sensor for s in streams})
    if missing:
        raise InputError(
            f"assigned sensor(s) {missing} are not in the recording; it has {sorted(s.sensor for s in streams)}"
        )
    checked = parse_assignment(assignment, imu_set=imu_set)
    if not checked:
        raise InputError("no sensor is assigned to a bone: give SENSOR=BONE pairs (--assign)")
    cfg = load_config()
    raw = config_document(cfg)  # the defaults, as a recording of the daemon would store them
    imu = dict(raw.get("imu", {}))
    imu["assignment"] = checked
    imu["imu_set"] = imu_set or ""
    raw["imu"] = imu
    o = cfg.daemon.scheduler_options([])
    body = BodySpec(height, dict(segments or {}), source=body_from)
    skeleton = body.skeleton()
    imu["body"] = {"height_m": height, **{f"{k}_m": v for k, v in (segments or {}).items()}}
    targets = coco17_targets(skeleton)
    return {
        **manifest_head(raw),
        "scheduler": {
            "rate_hz": o.rate_hz, "latency_ns": o.latency_ns, "keypoint_max_age_ns": o.keypoint_max_age_ns,
            "keypoint_max_gap_ns": o.keypoint_max_gap_ns, "match_px": o.match_px, "camera_offsets_ns": [],
            "imu_offsets_ns": {}, "body_size_frames": 0,
        },
        "cameras": [],
        "skeleton": {"offsets": skeleton.offsets.tolist(), "root_height": skeleton.root_height,
                     "height": skeleton.height, "from": body.describe()},
        "targets": {"names": list(targets.names), "bones": targets.bones.tolist(), "offsets": targets.offsets.tolist()},
        "prior": "prior.npz",
        "suits": [],
        "devices": {"imu": [], "keypoint_sources": []},
        "imported": {
            "from": source, "config_file": str(DEFAULT_CONFIG), "suit": suit, "assignment": checked,
            "sensors": {s.sensor: s.info for s in streams},
            "duration_s": round(max(float(s.time_ns[-1]) for s in streams if s.time_ns.size) / 1e9, 3),
        },
    }  # fmt: skip


def parse_assign_pairs(pairs: list[str]) -> dict[str, str]:
    """``["00B42279=Hips", ...]`` → ``{"00B42279": "Hips"}`` (validated later against the recording)."""
    out: dict[str, str] = {}
    for p in pairs:
        sensor, sep, bone = p.partition("=")
        if not sep or not sensor.strip() or not bone.strip():
            raise InputError(f"--assign {p[:80]!r}: expected SENSOR=BONE, e.g. 00B42279=Hips")
        sid = sensor.strip().upper()
        if sid in out:  # the last one silently won: which bone did the user mean?
            raise InputError(f"--assign: sensor {sid[:40]} is assigned twice ({out[sid]} and {bone.strip()[:40]})")
        out[sid] = bone.strip()
    return out


def manifest_head(raw: dict[str, Any]) -> dict[str, Any]:
    """The opening entries of an imported session's manifest (format, software, start, host, streams, the config
    ``raw`` it was made with), shared by every importer."""
    return {
        "format": "mocapd-session",
        "version": 1,
        "software": {"mocapd": mocapd.__version__, "python": platform.python_version(), "numpy": np.__version__},
        "started_utc": dt.datetime.now(dt.UTC).isoformat(),
        "started_monotonic_ns": T0_NS,
        "host": platform.node(),
        "streams": list(STREAMS),
        "config": raw,
    }
