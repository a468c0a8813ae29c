"""Pure post-processing of 2D pose detectors: letterbox geometry, YOLO-pose decoding, NMS.

Everything here is numpy on arrays that a detector produced; no image I/O and no runtime. The
onnxruntime session that feeds it lives in :mod:`mocapd.pipeline.detector`.

Coordinates are pixels with the origin at the top-left corner of the top-left pixel (OpenCV's
convention for ``cv2.resize`` with ``INTER_LINEAR``: the centre of pixel ``i`` is at ``i + 0.5``).
A letterbox maps source pixels ``p`` to model-input pixels ``p * (sx, sy) + pad``, where ``sx, sy`` are the
exact ratios of the integer resized size to the source size (what ``cv2.resize`` does), so that a round trip
through the resize is exact to the sub-pixel.

The YOLO-pose output layout (Ultralytics YOLOv8/11 ``*-pose`` exported to ONNX without NMS) is
``(1, 4 + 1 + 3 K, N)``: for each of ``N`` anchors, box centre x, centre y, width, height (model-input
pixels), the person score (already sigmoid-ed), then ``K`` keypoints as x, y, visibility (sigmoid-ed).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class Letterbox:
    """Uniform scale plus padding from a source image into a fixed-size model input.

    Attributes
    ----------
    sx, sy : float
        Model pixels per source pixel along x and y (``new_w / src_w``, ``new_h / src_h``).
    pad_x, pad_y : float
        Offset of the scaled source image inside the model input (model pixels).
    new_w, new_h : int
        Size of the scaled source image (model pixels) before padding.
    """

    sx: float
    sy: float
    pad_x: float
    pad_y: float
    new_w: int
    new_h: int

    def to_model(self, xy: FloatArray) -> FloatArray:
        """Source pixels ``(..., 2)`` to model-input pixels ``(..., 2)``."""
        out: FloatArray = np.asarray(xy, dtype=np.float64) * np.array([self.sx, self.sy])
        res: FloatArray = out + np.array([self.pad_x, self.pad_y])
        return res

    def to_source(self, xy: FloatArray) -> FloatArray:
        """Model-input pixels ``(..., 2)`` to source pixels ``(..., 2)``."""
        out: FloatArray = np.asarray(xy, dtype=np.float64) - np.array([self.pad_x, self.pad_y])
        res: FloatArray = out / np.array([self.sx, self.sy])
        return res


def letterbox_geometry(src_w: int, src_h: int, dst_w: int, dst_h: int, *, center: bool = True) -> Letterbox:
    """Largest uniform scale that fits ``src`` inside ``dst``, centred (like Ultralytics) or top-left.

    Parameters
    ----------
    src_w, src_h : int
        Source image size in pixels (> 0).
    dst_w, dst_h : int
        Model input size in pixels (> 0).
    center : bool
        Split the padding evenly on both sides (True) or put it right/bottom (False).
    """
    if min(src_w, src_h, dst_w, dst_h) <= 0:
        raise InputError(f"letterbox sizes must be positive, got src {src_w}x{src_h} dst {dst_w}x{dst_h}")
    scale = min(dst_w / src_w, dst_h / src_h)
    new_w = max(1, min(dst_w, round(src_w * scale)))
    new_h = max(1, min(dst_h, round(src_h * scale)))
    # Integer padding so that the resized image lands on whole pixels, as cv2.copyMakeBorder needs.
    pad_x = (dst_w - new_w) // 2 if center else 0
    pad_y = (dst_h - new_h) // 2 if center else 0
    # The exact per-axis scale of the integer-sized resize is new/src; using it keeps round trips exact.
    return Letterbox(
        sx=new_w / src_w, sy=new_h / src_h, pad_x=float(pad_x), pad_y=float(pad_y), new_w=new_w, new_h=new_h
    )


def fitted_input_size(src_w: int, src_h: int, dst_w: int, dst_h: int, stride: int = 32) -> tuple[int, int]:
    """The model input ``dst`` trimmed to the letterboxed image: each axis shorter by whole ``2 * stride`` steps.

    A portrait 544×960 camera letterboxed into 640×640 fills 363 of the 640 columns; a network exported at
    384×640 sees the same image at the same scale with 256 fewer padding columns, 128 on each side. Trimming in
    steps of two strides keeps the centred image's offset a whole number of strides from where it sits in
    ``dst`` (``(dst - new) // 2`` moves by exactly ``k * stride``), so the network sees the very pixels on the
    very stride grid of the full-size input: its keypoints are those of the full-size letterbox, for ~40 % less
    work (docs/detection.md, "Whole frames at the camera's aspect").

    Parameters
    ----------
    src_w, src_h : int
        Source image size in pixels (> 0).
    dst_w, dst_h : int
        The model's own input size in pixels (> 0).
    stride : int
        The network's largest stride (32 for YOLO).

    Returns
    -------
    (width, height) : tuple of int
        ``(dst_w, dst_h)`` where no step fits (a square camera, or one that fills the input).
    """
    lb = letterbox_geometry(src_w, src_h, dst_w, dst_h)
    step = 2 * stride
    return dst_w - step * ((dst_w - lb.new_w) // step), dst_h - step * ((dst_h - lb.new_h) // step)


@dataclass(frozen=True)
class PoseDetections:
    """People found in one image.

    Attributes
    ----------
    boxes : ndarray, shape (n, 4)
        x0, y0, x1, y1 in pixels.
    scores : ndarray, shape (n,)
        Person confidence in [0, 1].
    keypoints : ndarray, shape (n, K, 3)
        x, y (pixels) and confidence in [0, 1] of each keypoint.
    """

    boxes: FloatArray
    scores: FloatArray
    keypoints: FloatArray

    @staticmethod
    def empty(n_keypoints: int) -> PoseDetections:
        """No detections, with ``n_keypoints`` keypoints per (absent) person."""
        return PoseDetections(boxes=np.zeros((0, 4)), scores=np.zeros(0), keypoints=np.zeros((0, n_keypoints, 3)))

    def __len__(self) -> int:
        return int(self.scores.shape[0])

    def select(self, index: IntArray | NDArray[np.bool_]) -> PoseDetections:
        """The detections at ``index`` (integer or boolean array)."""
        return PoseDetections(self.boxes[index], self.scores[index], self.keypoints[index])

    def transformed(self, sx: float, sy: float, offset_x: float, offset_y: float) -> PoseDetections:
        """Every coordinate mapped by ``p * (sx, sy) + offset`` (confidences unchanged)."""
        off = np.array([offset_x, offset_y])
        s = np.array([sx, sy])
        boxes = self.boxes * np.tile(s, 2) + np.tile(off, 2)
        kp = self.keypoints.copy()
        kp[..., :2] = kp[..., :2] * s + off
        return PoseDetections(boxes, self.scores.copy(), kp)

    @staticmethod
    def concatenate(parts: list[PoseDetections], n_keypoints: int) -> PoseDetections:
        """All detections of ``parts`` in order."""
        if not parts:
            return PoseDetections.empty(n_keypoints)
        return PoseDetections(
            np.concatenate([p.boxes for p in parts]),
            np.concatenate([p.scores for p in parts]),
            np.concatenate([p.keypoints for p in parts]),
        )


def box_iou(a: FloatArray, b: FloatArray) -> FloatArray:
    """Pairwise intersection over union of boxes ``a (n, 4)`` and ``b (m, 4)`` (x0, y0, x1, y1) → ``(n, m)``."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    wh = np.clip(rb - lt, 0.0, None)
    inter = wh[..., 0] * wh[..., 1]
    area_a = np.prod(np.clip(a[:, 2:] - a[:, :2], 0.0, None), axis=1)
    area_b = np.prod(np.clip(b[:, 2:] - b[:, :2], 0.0, None), axis=1)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0.0, inter / np.where(union > 0.0, union, 1.0), 0.0)


def nms(boxes: FloatArray, scores: FloatArray, iou_threshold: float, max_keep: int | None = None) -> IntArray:
    """Greedy non-maximum suppression.

    Parameters
    ----------
    boxes : ndarray, shape (n, 4)
        x0, y0, x1, y1.
    scores : ndarray, shape (n,)
    iou_threshold : float
        A box whose IoU with an already kept, higher-scoring box exceeds this is dropped.
    max_keep : int, optional
        Keep at most this many.

    Returns
    -------
    ndarray of int, shape (k,)
        Indices of the kept boxes, highest score first.
    """
    boxes = np.asarray(boxes, dtype=np.float64)
    scores = np.asarray(scores, dtype=np.float64)
    if boxes.ndim != 2 or boxes.shape[1] != 4 or scores.shape != (boxes.shape[0],):
        raise InputError(f"nms needs boxes (n, 4) and scores (n,), got {boxes.shape} and {scores.shape}")
    order = np.argsort(-scores, kind="stable")
    keep: list[int] = []
    limit = len(order) if max_keep is None else max_keep
    while order.size and len(keep) < limit:
        best = int(order[0])
        keep.append(best)
        rest = order[1:]
        ious = box_iou(boxes[best][None], boxes[rest])[0]
        order = rest[ious <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)


def decode_yolo_pose(
    output: NDArray[np.floating[Any]],
    n_keypoints: int,
    *,
    score_threshold: float = 0.25,
    iou_threshold: float = 0.65,
    max_people: int = 50,
) -> PoseDetections:
    """Decode a raw YOLO-pose output into people, in model-input pixels.

    Parameters
    ----------
    output : ndarray, shape (1, 5 + 3 K, N) or (5 + 3 K, N)
        The network output (see the module docstring).
    n_keypoints : int
        ``K``.
    score_threshold : float
        Anchors with a lower person score are dropped before NMS.
    iou_threshold : float
        NMS overlap threshold.
    max_people : int
        At most this many people are returned.

    Returns
    -------
    PoseDetections
        In model-input pixels, highest score first.
    """
    out = np.asarray(output)
    if out.ndim == 3:
        if out.shape[0] != 1:
            raise InputError(f"decode_yolo_pose handles one image at a time, got batch {out.shape[0]}")
        out = out[0]
    rows = 5 + 3 * n_keypoints
    if out.ndim != 2 or out.shape[0] != rows:
        raise InputError(f"YOLO-pose output must be ({rows}, N) for {n_keypoints} keypoints, got {out.shape}")
    scores = out[4]
    cand = np.flatnonzero(scores >= score_threshold)
    if cand.size == 0:
        return PoseDetections.empty(n_keypoints)
    sel = out[:, cand].astype(np.float64).T  # (n, rows)
    cx, cy, w, h = sel[:, 0], sel[:, 1], sel[:, 2], sel[:, 3]
    boxes = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
    keep = nms(boxes, sel[:, 4], iou_threshold, max_keep=max_people)
    kp = sel[keep, 5:].reshape(-1, n_keypoints, 3)
    return PoseDetections(boxes[keep], sel[keep, 4], kp)


def detections_to_source(det: PoseDetections, lb: Letterbox) -> PoseDetections:
    """Map detections from model-input pixels back to source pixels through letterbox ``lb``."""
    return det.transformed(1.0 / lb.sx, 1.0 / lb.sy, -lb.pad_x / lb.sx, -lb.pad_y / lb.sy)


def encode_yolo_pose(det: PoseDetections, n_anchors: int, rng: np.random.Generator) -> FloatArray:
    """Inverse of :func:`decode_yolo_pose` for tests and simulators: a ``(1, 5 + 3 K, n_anchors)`` output.

    Each person occupies one anchor; the remaining anchors get random boxes with scores below 0.01.
    """
    n, k = det.keypoints.shape[0], det.keypoints.shape[1]
    if n > n_anchors:
        raise InputError(f"cannot encode {n} people into {n_anchors} anchors")
    out = np.zeros((5 + 3 * k, n_anchors))
    out[:4] = rng.uniform(10.0, 100.0, size=(4, n_anchors))
    out[4] = rng.uniform(0.0, 0.01, size=n_anchors)
    out[5:] = rng.uniform(0.0, 1.0, size=(3 * k, n_anchors))
    slots = rng.choice(n_anchors, size=n, replace=False)
    b = det.boxes
    out[0, slots] = (b[:, 0] + b[:, 2]) / 2
    out[1, slots] = (b[:, 1] + b[:, 3]) / 2
    out[2, slots] = b[:, 2] - b[:, 0]
    out[3, slots] = b[:, 3] - b[:, 1]
    out[4, slots] = det.scores
    out[5:, slots] = det.keypoints.reshape(n, 3 * k).T
    return out[None]
