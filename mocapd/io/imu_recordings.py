"""Existing IMU recordings (MT Manager exports, MVNX) as time-aligned sensor streams, and writing them as a session.

What ``mocapd import`` builds on (:mod:`mocapd.service.session.importer` adds the manifest).

Time: all sensors of one recording share a time base: SampleTimeFine when every file has it, else the
PacketCounter at the update rate (an Awinda station counts for all its MTws alike), else each file's own rows at
its rate from a common start. Sample ``k`` is filed at ``T0_NS + time_k`` on the session's clock, its device ticks
and packet counter kept.

MVNX files have no sensor ids: each sensor gets ``4D56xxxx`` (``"MV"`` + its index) and its segment label is kept;
its orientation and specific force are MVN's ``sensorOrientation`` (Z-up global frame) and
``sensorFreeAcceleration`` with gravity added back (:meth:`mocapd.io.mvnx.MvnxRecording.sensor_readings`). The
segment labels map onto bones by :data:`MVN_SENSOR_BONES` (the shoulder sensors have no bone).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.errors import InputError
from mocapd.io.mt_export import TICK_HZ, MtExport
from mocapd.io.mvnx import MvnxRecording
from mocapd.io.output_files import atomic_directory, check_output_dir
from mocapd.io.prior import resolve_prior
from mocapd.io.session import MANIFEST, STREAMS, SUFFIX, WriterCounters, write_json_atomic
from mocapd.protocols.session_format import T_HEADER, T_IMU, ImuRecord, encode_header, encode_imu, encode_record

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

T0_NS = 1_000_000_000
"""Session time of the recording's first instant."""

MVN_SENSOR_BONES: dict[str, str] = {
    "Pelvis": "Hips", "T8": "Spine3", "Head": "Head",
    "RightUpperArm": "RightUpperArm", "RightForeArm": "RightLowerArm", "RightHand": "RightHand",
    "LeftUpperArm": "LeftUpperArm", "LeftForeArm": "LeftLowerArm", "LeftHand": "LeftHand",
    "RightUpperLeg": "RightUpperLeg", "RightLowerLeg": "RightLowerLeg", "RightFoot": "RightFoot",
    "LeftUpperLeg": "LeftUpperLeg", "LeftLowerLeg": "LeftLowerLeg", "LeftFoot": "LeftFoot",
}  # fmt: skip
"""MVN sensor (segment) labels → mocapd bones (MVN's 23 segments on the 21 bones, DESIGN.md)."""


@dataclass(frozen=True)
class SensorStream:
    """One sensor's samples on the recording's shared time base.

    Attributes
    ----------
    sensor : str
        8 hex digits.
    time_ns : int array, shape (n,)
        From the recording's first instant.
    quat : array, shape (n, 4)
        Orientation in the device's global frame (ENU or another Z-up frame), (w, x, y, z).
    acc : array, shape (n, 3)
        Specific force in the sensor frame (m/s², gravity included).
    ticks, counter : int arrays, shape (n,), or None
    info : dict
        What the manifest says about the sensor (source file, rate, orientation and acceleration sources, label).
    """

    sensor: str
    time_ns: IntArray
    quat: FloatArray
    acc: FloatArray
    ticks: IntArray | None
    counter: IntArray | None
    info: dict[str, Any]


def streams_from_mt_exports(exports: list[tuple[str, MtExport]]) -> list[SensorStream]:
    """The exports of one recording (file name, parsed export) on one time base (see the module docstring)."""
    if not exports:
        raise InputError("no MT Manager export given")
    ids = [e.sensor for _, e in exports]
    if len(set(ids)) != len(ids):
        raise InputError(f"the same sensor appears in more than one file: {sorted(i for i in ids if ids.count(i) > 1)}")
    if all(e.ticks is not None for _, e in exports):
        start = min(int(e.ticks[0]) for _, e in exports if e.ticks is not None)
        times = [np.asarray((e.ticks - start) * (1_000_000_000 // TICK_HZ), dtype=np.int64) for _, e in exports
                 if e.ticks is not None]  # fmt: skip
        base = "SampleTimeFine"
    elif all(e.counter is not None for _, e in exports):
        start = min(int(e.counter[0]) for _, e in exports if e.counter is not None)
        times = [np.round((e.counter - start) / e.rate_hz * 1e9).astype(np.int64) for _, e in exports
                 if e.counter is not None]  # fmt: skip
        base = "PacketCounter"
    else:
        times = [np.round(e.time_s * 1e9).astype(np.int64) for _, e in exports]
        base = "rows"
    out = []
    for (name, e), t in zip(exports, times, strict=True):
        info = {"file": name, "samples": e.n, "rate_hz": e.rate_hz, "orientation": e.orientation,
                "acceleration": e.acceleration, "dropped_rows": e.dropped_rows, "time_base": base}  # fmt: skip
        out.append(SensorStream(e.sensor, t, e.quat, e.acc, e.ticks, e.counter, info))
    return out


def streams_from_mvnx(rec: MvnxRecording, name: str) -> list[SensorStream]:
    """Every sensor of an MVNX recording (ids ``4D56xxxx``, see the module docstring)."""
    quat, acc = rec.sensor_readings()
    t = np.round((rec.time_ms - rec.time_ms[0]) * 1e6).astype(np.int64)
    if np.any(np.diff(t) <= 0):
        raise InputError(f"{name}: frame times do not increase")
    out = []
    for k, label in enumerate(rec.sensors):
        ok = np.all(np.isfinite(quat[:, k]), axis=1) & (np.linalg.norm(quat[:, k], axis=1) > 0.5)
        info = {"file": name, "label": label, "samples": int(ok.sum()), "rate_hz": rec.fps,
                "orientation": "sensorOrientation", "acceleration": "sensorFreeAcceleration + gravity"}  # fmt: skip
        out.append(SensorStream(f"{0x4D560000 + k + 1:08X}", t[ok], quat[ok, k], acc[ok, k], None, None, info))
    return out


def mvnx_assignment(streams: list[SensorStream]) -> dict[str, str]:
    """Sensor id → bone for the MVNX sensors whose label has a bone."""
    return {s.sensor: MVN_SENSOR_BONES[s.info["label"]] for s in streams if s.info.get("label") in MVN_SENSOR_BONES}


def write_imported_session(directory: str | Path, streams: list[SensorStream], manifest: dict[str, Any]) -> Path:
    """Write the session: manifest, the default prior, every sample in time order into ``imu.mcs``.

    The directory must not exist or be empty (:func:`mocapd.io.output_files.check_output_dir`, best called before
    reading the recordings). It is built beside its final name and renamed into place when complete, so a failed
    import leaves nothing half-written; the samples are encoded and written as they are taken in time order
    (memory: the recordings' arrays and one sort index, nothing per sample).
    """
    path = check_output_dir(directory, what="session directory")
    prior = resolve_prior("default")
    n = sum(len(s.time_ns) for s in streams)
    times = np.concatenate([s.time_ns for s in streams]) if streams else np.empty(0, np.int64)
    which = np.concatenate([np.full(len(s.time_ns), i, np.int32) for i, s in enumerate(streams)]) if streams else (
        np.empty(0, np.int32))  # fmt: skip
    where = np.concatenate([np.arange(len(s.time_ns)) for s in streams]) if streams else np.empty(0, np.int64)
    order = np.lexsort((which, times))  # by time, then by the stream's place (as the writer queue had them)
    counters = WriterCounters()
    with atomic_directory(path) as tmp:
        if prior is not None:
            np.savez(tmp / "prior.npz", M=prior.M, mu=prior.mu, sigma=prior.sigma)
        for name in STREAMS:
            if name != "imu":
                with (tmp / f"{name}{SUFFIX}").open("wb") as fh:
                    fh.write(encode_record(T_HEADER, encode_header(name)))
                    os.fsync(fh.fileno())
        with (tmp / f"imu{SUFFIX}").open("wb", buffering=1 << 20) as fh:
            fh.write(encode_record(T_HEADER, encode_header("imu")))
            for i, k in _in_order(which, where, order):
                s = streams[i]
                t = T0_NS + int(s.time_ns[k])
                q, a = s.quat[k], s.acc[k]
                rec = ImuRecord(
                    s.sensor, t, t, None if s.ticks is None else int(s.ticks[k]),
                    None if s.counter is None else int(s.counter[k]),
                    (float(q[0]), float(q[1]), float(q[2]), float(q[3])), (float(a[0]), float(a[1]), float(a[2])),
                )  # fmt: skip
                data = encode_record(T_IMU, encode_imu(rec))
                fh.write(data)
                counters.bytes += len(data)
            fh.flush()
            os.fsync(fh.fileno())
        counters.queued = counters.written = n
        counters.flushes = 1
        ended = T0_NS + max((int(s.time_ns[-1]) for s in streams if s.time_ns.size), default=0)
        write_json_atomic(tmp / MANIFEST, {**manifest, "closed": True, "ended_monotonic_ns": ended,
                                           "writer": asdict(counters)})  # fmt: skip
    return path


def _in_order(which: NDArray[np.int32], where: IntArray, order: IntArray) -> Iterator[tuple[int, int]]:
    """(stream, sample) pairs in ``order``, 65536 at a time (never a Python list of every sample)."""
    for start in range(0, len(order), 1 << 16):
        part = order[start : start + (1 << 16)]
        yield from zip(which[part].tolist(), where[part].tolist(), strict=True)
