"""Calibration of keypoint track-target offsets ``t_pb`` (seed 003 §3.3.2, Eq. 17–18).

Given frames where the subject's bone poses are known (a reference mocap, or a trusted solve) and 2D
detections of the same frames from calibrated cameras:

1. each keypoint is triangulated per frame by confidence-weighted multi-view DLT (Eq. 17, with the
   confidence as weight and the robust loss replaced by the median of step 3);
2. the 3D point is moved into its bone's frame with the reference pose: ``t_pb = R_gb^T (t_pg - p_gb)``
   (Eq. 18);
3. the offset is the per-axis median over all frames, robust to the frames where the detector was wrong.

The offsets file (JSON, :func:`offsets_to_json`) is what the solver reads::

    {
      "format": "mocapd-keypoint-offsets",
      "version": 1,
      "keypoint_format": "coco17",
      "units": "m",
      "frame": "bone (rest pose axes: +X subject's left, +Y up, +Z forward; origin at the bone's joint)",
      "targets": {"nose": {"bone": "Head", "offset": [0.0, 0.05, 0.1], "frames": 812,
                           "mad": [0.004, 0.006, 0.005]}, ...}
    }

``frames`` is how many frames contributed, ``mad`` the per-axis median absolute deviation (metres), a
measure of how well the keypoint sticks to its bone.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import triangulate_projections
from mocapd.core.keypoints import KeypointFormat, TrackTarget
from mocapd.core.skeleton import BONE_NAMES
from mocapd.errors import CalibrationError, InputError

FloatArray = NDArray[np.float64]

OFFSETS_FORMAT = "mocapd-keypoint-offsets"
OFFSETS_VERSION = 1


def project(P: FloatArray, X: FloatArray) -> FloatArray:
    """Pixels of points ``X (..., 3)`` in cameras ``P (n_cams, 3, 4)`` → ``(n_cams, ..., 2)``."""
    Xh = np.concatenate([X, np.ones((*X.shape[:-1], 1))], axis=-1)
    uvw: FloatArray = np.einsum("cij,...j->c...i", P, Xh)
    uv: FloatArray = uvw[..., :2] / uvw[..., 2:3]
    return uv


def to_bone_space(points: FloatArray, bone_rot: FloatArray, bone_pos: FloatArray) -> FloatArray:
    """Eq. 18: world points ``(..., 3)`` → bone frame, with bone rotations ``(..., 3, 3)`` (bone→world) and
    origins ``(..., 3)``."""
    out: FloatArray = np.einsum("...ji,...j->...i", bone_rot, points - bone_pos)
    return out


@dataclass(frozen=True)
class OffsetEstimate:
    """Per-keypoint result of :func:`calibrate_offsets`.

    Attributes
    ----------
    offsets : ndarray, shape (n_kp, 3)
        Median bone-space offset (metres); NaN where no frame contributed.
    frames : ndarray of int, shape (n_kp,)
        Frames that contributed to each keypoint.
    mad : ndarray, shape (n_kp, 3)
        Per-axis median absolute deviation of the per-frame offsets.
    """

    offsets: FloatArray
    frames: NDArray[np.int64]
    mad: FloatArray


def calibrate_offsets(
    P: FloatArray,
    keypoints: FloatArray,
    bone_rot: FloatArray,
    bone_pos: FloatArray,
    keypoint_bones: Sequence[int],
    *,
    min_confidence: float = 0.3,
    min_views: int = 2,
) -> OffsetEstimate:
    """Estimate bone-space offsets of every keypoint over a set of frames (seed 003 Eq. 17–18).

    Parameters
    ----------
    P : ndarray, shape (n_cams, 3, 4)
        Camera projection matrices (undistorted pixels).
    keypoints : ndarray, shape (n_frames, n_cams, n_kp, 3)
        The subject's detected keypoints per frame and camera: x, y (pixels) and confidence; NaN or
        confidence 0 where the camera did not see the subject.
    bone_rot : ndarray, shape (n_frames, n_bones, 3, 3)
        Reference global rotation of every bone (bone → world).
    bone_pos : ndarray, shape (n_frames, n_bones, 3)
        Reference global position of every bone's origin (metres).
    keypoint_bones : sequence of int, length n_kp
        Index of the bone each keypoint is attached to (-1: skip the keypoint).
    min_confidence : float
        Views below this confidence do not take part in a triangulation.
    min_views : int
        Frames with fewer confident views of a keypoint are skipped for it.
    """
    P = np.asarray(P, dtype=np.float64)
    kp = np.asarray(keypoints, dtype=np.float64)
    R = np.asarray(bone_rot, dtype=np.float64)
    t = np.asarray(bone_pos, dtype=np.float64)
    if kp.ndim != 4 or kp.shape[1] != P.shape[0] or kp.shape[3] != 3:
        raise InputError(f"keypoints must be (n_frames, {P.shape[0]}, n_kp, 3), got {kp.shape}")
    n_frames, _, n_kp, _ = kp.shape
    if R.shape[:1] != (n_frames,) or R.shape[2:] != (3, 3) or t.shape != (n_frames, R.shape[1], 3):
        raise InputError(f"bone_rot must be ({n_frames}, n_bones, 3, 3) and bone_pos ({n_frames}, n_bones, 3)")
    if len(keypoint_bones) != n_kp:
        raise InputError(f"keypoint_bones has {len(keypoint_bones)} entries for {n_kp} keypoints")
    offsets = np.full((n_kp, 3), np.nan)
    mad = np.full((n_kp, 3), np.nan)
    frames = np.zeros(n_kp, dtype=np.int64)
    for k, b in enumerate(keypoint_bones):
        if b < 0:
            continue
        if b >= R.shape[1]:
            raise InputError(f"keypoint {k} attached to bone {b}, but poses have {R.shape[1]} bones")
        samples = []
        for f in range(n_frames):
            conf = np.nan_to_num(kp[f, :, k, 2])
            w = np.where(conf >= min_confidence, conf, 0.0)
            if np.count_nonzero(w) < min_views:
                continue
            X, ok = triangulate_projections(P, kp[f, :, k : k + 1, :2], w[:, None], max(min_views, 2))
            if ok[0]:
                samples.append(to_bone_space(X[0], R[f, b], t[f, b]))
        if samples:
            s = np.asarray(samples)
            med = np.median(s, axis=0)
            offsets[k] = med
            mad[k] = np.median(np.abs(s - med), axis=0)
            frames[k] = len(samples)
    return OffsetEstimate(offsets=offsets, frames=frames, mad=mad)


def offsets_to_json(fmt: KeypointFormat, estimate: OffsetEstimate) -> str:
    """The offsets file for ``fmt`` (only keypoints with a track target and at least one frame)."""
    targets: dict[str, object] = {}
    for k, name in enumerate(fmt.keypoints):
        tt = fmt.targets.get(name)
        if tt is None or estimate.frames[k] == 0:
            continue
        targets[name] = {
            "bone": tt.bone,
            "offset": [round(float(v), 5) for v in estimate.offsets[k]],
            "frames": int(estimate.frames[k]),
            "mad": [round(float(v), 5) for v in estimate.mad[k]],
        }
    doc = {
        "format": OFFSETS_FORMAT,
        "version": OFFSETS_VERSION,
        "keypoint_format": fmt.name,
        "units": "m",
        "frame": "bone (rest pose axes: +X subject's left, +Y up, +Z forward; origin at the bone's joint)",
        "targets": targets,
    }
    return json.dumps(doc, indent=2) + "\n"


def offsets_from_json(text: str, fmt: KeypointFormat) -> dict[str, TrackTarget]:
    """Parse an offsets file written by :func:`offsets_to_json` for keypoint format ``fmt``.

    Raises
    ------
    CalibrationError
        Wrong format tag, version or keypoint format, unknown keypoint or bone, or a malformed offset.
    """
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"offsets file is not JSON: {exc}") from exc
    if not isinstance(doc, Mapping) or doc.get("format") != OFFSETS_FORMAT:
        raise CalibrationError(f"not a {OFFSETS_FORMAT} file")
    if doc.get("version") != OFFSETS_VERSION:
        raise CalibrationError(f"offsets file version {doc.get('version')!r}, this mocapd reads {OFFSETS_VERSION}")
    if doc.get("keypoint_format") != fmt.name:
        raise CalibrationError(f"offsets are for {doc.get('keypoint_format')!r}, the detector uses {fmt.name!r}")
    targets = doc.get("targets")
    if not isinstance(targets, Mapping):
        raise CalibrationError("offsets file has no 'targets' table")
    out: dict[str, TrackTarget] = {}
    for name, entry in targets.items():
        if name not in fmt.keypoints:
            raise CalibrationError(f"offsets file names keypoint {name!r}, not in {fmt.name}")
        if not isinstance(entry, Mapping) or entry.get("bone") not in BONE_NAMES:
            raise CalibrationError(f"keypoint {name!r}: missing or unknown bone")
        off = entry.get("offset")
        if (
            not isinstance(off, list)
            or len(off) != 3
            or not all(isinstance(v, int | float) and np.isfinite(v) for v in off)
        ):
            raise CalibrationError(f"keypoint {name!r}: offset must be 3 finite numbers, got {off!r}")
        out[name] = TrackTarget(str(entry["bone"]), (float(off[0]), float(off[1]), float(off[2])))
    return out
