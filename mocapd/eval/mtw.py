"""Noise levels of real Xsens MTw recordings (OpenSense example exports), for the simulator's documentation.

Each export is a tab-separated text file (``//`` header lines, then a column header) with ``Acc_X..Z`` (m/s²,
sensor frame, gravity included) and the orientation matrix ``Mat[i][j]`` (sensor → global). We find the most
static 1-second windows (lowest accelerometer variation) and measure there: accelerometer noise (per-axis
standard deviation), orientation noise (RMS angle of each sample from the window's mean orientation) and the
heading change rate over the window (deg/min; short windows make this an upper bound).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.rotations import matrix_from_quat, quat_from_matrix, quat_normalize
from mocapd.io.mt_export import read_mt_export

FloatArray = NDArray[np.float64]


def read_mtw_text(path: Path) -> tuple[float, FloatArray, FloatArray]:
    """Rate (Hz), accelerations (n, 3) and orientation matrices (n, 3, 3, sensor → ENU) of an MT Manager export
    (:func:`mocapd.io.mt_export.read_mt_export`)."""
    e = read_mt_export(path)
    return e.rate_hz, e.acc, matrix_from_quat(e.quat)


def static_noise(path: Path, window_s: float = 1.0, windows: int = 3) -> dict[str, Any]:
    """Noise levels in the ``windows`` most static, non-overlapping windows of one recording."""
    rate, acc, mat = read_mtw_text(path)
    n = int(window_s * rate)
    mag = np.linalg.norm(acc, axis=1)
    starts = np.arange(0, len(acc) - n, n // 2)
    score = np.array([mag[s : s + n].std() for s in starts])
    chosen: list[int] = []
    for i in np.argsort(score):
        s = int(starts[i])
        if all(abs(s - c) >= n for c in chosen):
            chosen.append(s)
        if len(chosen) == windows:
            break
    acc_std, ori_rms, heading = [], [], []
    for s in chosen:
        a = acc[s : s + n]
        acc_std.append(a.std(axis=0))
        q = quat_from_matrix(mat[s : s + n])
        q = np.where((q @ q[0] < 0)[:, None], -q, q)
        qm = quat_normalize(q.mean(axis=0))
        Rm = matrix_from_quat(qm)
        rel = np.swapaxes(mat[s : s + n], -1, -2) @ Rm
        ang = np.degrees(np.arccos(np.clip((np.einsum("nii->n", rel) - 1) / 2, -1, 1)))
        ori_rms.append(float(np.sqrt(np.mean(ang**2))))
        # Heading: yaw of the sensor's x axis about the global vertical (z for Xsens exports).
        axis = int(np.argmin(np.abs(mat[s, 2, :])))  # the sensor axis closest to horizontal
        x = mat[s : s + n, :, axis]
        yaw = np.unwrap(np.arctan2(x[:, 1], x[:, 0]))
        slope = np.polyfit(np.arange(n) / rate, np.degrees(yaw), 1)[0]
        heading.append(abs(slope) * 60.0)
    return {
        "file": Path(path).name,
        "rate_hz": rate,
        "static_windows_s": [round(s / rate, 2) for s in chosen],
        "acc_std_per_axis_ms2": [round(float(v), 4) for v in np.mean(acc_std, axis=0)],
        "acc_noise_rms_ms2": round(float(np.sqrt(np.mean(np.square(acc_std)))), 4),
        "acc_gravity_norm_ms2": round(float(mag[chosen[0] : chosen[0] + n].mean()), 3),
        "orientation_noise_rms_deg": round(float(np.mean(ori_rms)), 3),
        "heading_rate_deg_per_min": round(float(np.median(heading)), 2),
    }


def measure_all(folder: Path) -> dict[str, Any]:
    files = sorted(Path(folder).glob("*.txt"))
    per = [static_noise(f) for f in files]
    return {
        "files": per,
        "median_acc_noise_rms_ms2": round(float(np.median([p["acc_noise_rms_ms2"] for p in per])), 4),
        "median_orientation_noise_rms_deg": round(float(np.median([p["orientation_noise_rms_deg"] for p in per])), 3),
        "median_heading_rate_deg_per_min": round(float(np.median([p["heading_rate_deg_per_min"] for p in per])), 2),
    }
