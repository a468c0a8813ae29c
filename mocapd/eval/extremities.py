"""Camera-only orientation of the feet, toes and hands on the synthetic rig, per keypoint set (issue 40).

COCO-17 has no point beyond the ankles and wrists, so with cameras alone the Foot, Toes and Hand segments are
unobserved: the solver leaves them where the prior and the last pose put them. BlazePose's 33 landmarks add the
heel and the tip of the second toe on each foot and the pinky and index knuckles and the thumb on each hand. Here
the synthetic rig (:mod:`mocapd.eval.simulate`: the 8-camera ring, the "realistic" detector model, the same seeded
clips as ``mocapd eval accuracy``) places each keypoint set's points on the true skeleton with the track targets'
offsets (a calibrated subject: the solver knows the offsets the points were placed with), the real
:class:`~mocapd.core.solver.PoseSolver` runs camera-only, online and warm-started, and the orientation error of
each extremity segment (angle of ``R_solvedᵀ R_true``, degrees) is reported per segment, median and p90.

``tools/extremity_orientation.py`` prints it as JSON; docs/accuracy.md carries the table.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.keypoints import keypoint_format
from mocapd.core.kinematics import Kinematics
from mocapd.core.prior import PcaPrior
from mocapd.core.retarget import Retargeted
from mocapd.core.skeleton import BONE_INDEX
from mocapd.core.solver import Observations, PoseSolver
from mocapd.core.terms import CostOptions
from mocapd.eval.data import load_clip, load_splits
from mocapd.eval.harness import windows
from mocapd.eval.metrics import orientation_errors
from mocapd.eval.simulate import DetectionNoise, simulate_detections, totalcapture_ring

FloatArray = NDArray[np.float64]

SEGMENTS: tuple[str, ...] = ("LeftFoot", "RightFoot", "LeftToes", "RightToes", "LeftHand", "RightHand")
"""The segments whose orientation a body keypoint set leaves unobserved or observes."""

TARGET_DEG = 15.0
"""Issue 40's target: camera-only orientation error of Foot and Hand at most this (median)."""


@dataclass(frozen=True)
class ExtremityOptions:
    """What :func:`extremity_orientation` runs."""

    split: str = "evaluation"
    formats: tuple[str, ...] = ("coco17", "blazepose33")
    n_cams: int = 8
    max_frames: int | None = 300
    """Frames per sequence (None: whole windows)."""
    max_sequences: int | None = 6
    seed: int = 0
    detections: DetectionNoise = field(default_factory=DetectionNoise.realistic)


def _head(clip: Retargeted, n: int | None) -> Retargeted:
    if n is None or clip.n_frames <= n:
        return clip
    return replace(clip, theta=clip.theta[:n], positions=clip.positions[:n], rotations=clip.rotations[:n],
                   source_positions=clip.source_positions[:n])  # fmt: skip


def clips(opts: ExtremityOptions, data_root: Path | None = None) -> list[tuple[Retargeted, int]]:
    """The split's windows (cut as the accuracy harness cuts them) and each one's seed."""
    out = []
    for f in load_splits(data_root)[opts.split]:
        for w in windows(load_clip(f)):
            out.append((_head(w, opts.max_frames), zlib.crc32(f"{opts.seed}:{w.name}".encode())))
    return out[: opts.max_sequences] if opts.max_sequences is not None else out


def solve_camera_only(
    clip: Retargeted, fmt: str, seed: int, n_cams: int, noise: DetectionNoise, prior: PcaPrior | None,
    cost: CostOptions | None = None,
) -> FloatArray:  # fmt: skip
    """The solver's θ, shape (f, 66), on simulated detections of keypoint set ``fmt`` from the first ``n_cams``
    cameras of the ring, no IMU; it starts from the clip's first pose and knows the offsets (as the harness)."""
    targets = keypoint_format(fmt).track_targets(clip.skeleton)
    cams = totalcapture_ring(n_cams)
    uv, conf = simulate_detections(clip, cams, targets, noise, np.random.default_rng(seed))
    solver = PoseSolver(clip.skeleton, cams, targets, (), prior, cost)
    solver.reset(clip.theta[0])
    out = np.zeros((clip.n_frames, 66))
    for t in range(clip.n_frames):
        out[t] = solver.solve(Observations(keypoints=uv[t], confidences=conf[t], dt=1.0 / clip.fps)).theta
    return out


def segment_errors(clip: Retargeted, theta: FloatArray) -> dict[str, FloatArray]:
    """Each of :data:`SEGMENTS`' orientation error per frame (degrees), solved ``theta`` (f, 66) against the truth."""
    rot = Kinematics(clip.skeleton).forward(theta).rotations
    err = orientation_errors(rot, clip.rotations)
    return {s: err[:, BONE_INDEX[s]] for s in SEGMENTS}


def _stats(x: FloatArray) -> dict[str, float]:
    return {"median": round(float(np.median(x)), 2), "p90": round(float(np.percentile(x, 90)), 2),
            "mean": round(float(np.mean(x)), 2)}  # fmt: skip


def extremity_orientation(
    opts: ExtremityOptions, prior: PcaPrior | None, data_root: Path | None = None,
    tick: Callable[[int], None] | None = None,
) -> dict[str, Any]:  # fmt: skip
    """Per keypoint set, per segment of :data:`SEGMENTS` (and Foot / Toes / Hand, both sides together): the
    camera-only orientation error's median, p90 and mean (degrees) over every frame of every sequence."""
    seqs = clips(opts, data_root)
    out: dict[str, Any] = {"sequences": [c.name for c, _ in seqs], "frames": sum(c.n_frames for c, _ in seqs)}
    for fmt in opts.formats:
        per: dict[str, list[FloatArray]] = {s: [] for s in SEGMENTS}
        for clip, seed in seqs:
            errs = segment_errors(clip, solve_camera_only(clip, fmt, seed, opts.n_cams, opts.detections, prior))
            for s in SEGMENTS:
                per[s].append(errs[s])
            if tick is not None:
                tick(clip.n_frames)
        table: dict[str, Any] = {s: _stats(np.concatenate(v)) for s, v in per.items()}
        for part in ("Foot", "Toes", "Hand"):
            table[part] = _stats(np.concatenate(per[f"Left{part}"] + per[f"Right{part}"]))
        out[fmt] = table
    return out
