"""Packed multi-camera detection: ROIs of several cameras (and frames) on shared detector images.

:class:`PackedDetector` keeps, per camera, the ROIs around the people it found last time (seed 000 §3.3.1),
plans canvases with :func:`mocapd.core.roi_packing.plan_canvases`, copies the ROIs into them, runs the
detector once per canvas and maps every detection back to its camera and frame. A camera that found nobody
looks at its whole frame again on the next call.

Several passes may run at once on disjoint sets of cameras, each with its own inference session (the ``detector``
argument of :meth:`PackedDetector.detect`): the ROI state is read and updated under a lock, the canvases are
rendered and inferred outside it.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from mocapd.core.pose2d import FloatArray, PoseDetections, letterbox_geometry
from mocapd.core.roi_packing import (
    AlignedRoi,
    Packing,
    Roi,
    SubsampleSchedule,
    full_roi,
    grow_cut_boxes,
    plan_aligned_canvases,
    plan_canvases,
    rois_from_boxes,
    snap_roi_to_grid,
    unpack_detections,
)
from mocapd.errors import InputError
from mocapd.pipeline.detector import Image, OnnxPoseDetector
from mocapd.pipeline.detector_config import DetectorConfig, PackingConfig


@dataclass
class PackingStats:
    """Counters since construction."""

    calls: int = 0
    canvases: int = 0
    camera_frames: int = 0
    tiles: int = 0
    full_frame_tiles: int = 0
    refresh_tiles: int = 0


def _box_area(b: FloatArray) -> float:
    return float(max(b[2] - b[0], 0.0) * max(b[3] - b[1], 0.0))


def _intersection(a: FloatArray, b: FloatArray) -> float:
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    return float(max(w, 0.0) * max(h, 0.0))


def render_canvas(packing: Packing, images: Sequence[Image], pad_value: int) -> Image:
    """Copy every tile's ROI of ``images[tile.index]`` into a fresh ``(H, W, 3)`` canvas.

    Bilinear sampling with pixel centres at ``i + 0.5``, like ``cv2.resize`` in the whole-frame letterbox,
    so that a tile at the letterbox's scale and phase holds the letterbox's very pixels.
    """
    canvas = np.full((packing.canvas_h, packing.canvas_w, 3), pad_value, dtype=np.uint8)
    for t in packing.tiles:
        r = t.roi
        fx, fy = math.floor(t.x), math.floor(t.y)
        x1 = min(packing.canvas_w, math.ceil(t.x + t.w))
        y1 = min(packing.canvas_h, math.ceil(t.y + t.h))
        crop = images[t.index][r.y0 : r.y1, r.x0 : r.x1]
        m = np.array(
            [[t.sx, 0.0, t.x - fx + 0.5 * t.sx - 0.5], [0.0, t.sy, t.y - fy + 0.5 * t.sy - 0.5]],
            dtype=np.float64,
        )
        canvas[fy:y1, fx:x1] = cv2.warpAffine(
            crop, m, (x1 - fx, y1 - fy), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
    return canvas


def canvas_extent(packing: Packing) -> tuple[int, int]:
    """(width, height) of the top-left part of a canvas that its tiles cover (canvas pixels, rounded up)."""
    if not packing.tiles:
        return packing.canvas_w, packing.canvas_h
    w = max(math.ceil(t.x + t.w) for t in packing.tiles)
    h = max(math.ceil(t.y + t.h) for t in packing.tiles)
    return min(w, packing.canvas_w), min(h, packing.canvas_h)


class PackedDetector:
    """Detects people in groups of camera frames through ROI packing.

    Parameters
    ----------
    detector : OnnxPoseDetector
        The reference model: its input size defines the whole-frame scale (and, when aligned, the stride phase)
        of every tile, and it detects whole frames when packing is disabled.
    image_sizes : sequence of (int, int)
        (width, height) of each camera's images.
    cfg : PackingConfig
        Margin, gap, alignment and scale ratios.
    canvas_detector : OnnxPoseDetector, optional
        The same network exported at a larger fixed size, to run the packed canvases on (default: ``detector``).
        A larger canvas fits tall person tiles in more rows and wastes less of each inference.
    """

    def __init__(
        self,
        detector: OnnxPoseDetector,
        image_sizes: Sequence[tuple[int, int]],
        cfg: PackingConfig,
        canvas_detector: OnnxPoseDetector | None = None,
    ) -> None:
        self.detector = detector
        self.canvas_detector = canvas_detector if canvas_detector is not None else detector
        if self.canvas_detector.format != detector.format:
            raise InputError("the canvas model must output the same keypoint format as the reference model")
        self.cfg = cfg
        self.image_sizes = [(int(w), int(h)) for w, h in image_sizes]
        self.rois: list[list[Roi]] = [[full_roi(w, h)] for w, h in self.image_sizes]
        cw, ch = detector.input_size
        # The scale a whole-frame letterbox pass gives each camera: packing must not go below ratio × that.
        full_scales = [min(cw / w, ch / h) for w, h in self.image_sizes]
        self._min_scales = [cfg.min_scale_ratio * s for s in full_scales]
        # Upper bound of tile scales; never above 1 (no up-sampling).
        self._max_scale = min(1.0, cfg.max_scale_ratio * max(full_scales))
        self._letterboxes = [letterbox_geometry(w, h, cw, ch) for w, h in self.image_sizes]
        self.stats = PackingStats()
        self._refresh_due: dict[int, int] = {}  # camera → the call its refresh fell due
        self.last_packings: list[Packing] = []
        self.last_tile_images: list[Image] = []
        self._lock = threading.RLock()  # ROI state, refresh bookkeeping and counters (passes may run at once)
        #: every tile at most this multiple of its camera's whole-frame letterbox scale, with ``align_stride`` > 0
        #: (the default): the governor's deepest steps set 0.5, so that the four demo cameras' people share one
        #: canvas crop and a camera frame costs half the CPU (:meth:`_aligned`)
        self.tile_ratio = 1.0

    @property
    def n_cameras(self) -> int:
        return len(self.image_sizes)

    def reset(self) -> None:
        """Forget the ROIs: every camera looks at its whole frame next time."""
        self.rois = [[full_roi(w, h)] for w, h in self.image_sizes]

    def detect(
        self,
        frames: Sequence[Sequence[Image]],
        cameras: Sequence[int] | None = None,
        detector: OnnxPoseDetector | None = None,
        inputs: list[tuple[int, int]] | None = None,
    ) -> list[list[PoseDetections]]:
        """Detect people in ``frames[slot][camera]`` (BGR images), all slots sharing the current ROIs.

        Parameters
        ----------
        frames : sequence of sequence of ndarray
            One or more consecutive frames (slots), each with one image per camera.
        cameras : sequence of int, optional
            Detect only these cameras (default: all); the others' images are not read, their detections come
            back empty and their ROIs are kept for their next call.
        detector : OnnxPoseDetector, optional
            The session to infer with (default: ``canvas_detector``; packing disabled: ``detector``), of the canvas
            model's input size: passes over disjoint cameras may run at once, each on a session of its own.
        inputs : list, optional
            Given: the network input (width, height) of every canvas run is appended (what the pass cost).

        Returns
        -------
        list of list of PoseDetections
            ``[slot][camera]``, in each camera's pixels. The ROIs are then updated from the last slot.
        """
        n_kp = self.detector.format.n_keypoints
        subset = list(range(self.n_cameras)) if cameras is None else sorted(set(cameras))
        if not self.cfg.enabled:
            whole = detector if detector is not None else self.detector
            with self._lock:
                self.stats.calls += 1
                self.stats.camera_frames += len(frames) * len(subset)
                self.stats.canvases += len(frames) * len(subset)
            none = PoseDetections.empty(n_kp)
            return [[whole.detect(img) if c in subset else none for c, img in enumerate(cams)]
                    for cams in frames]  # fmt: skip
        runner = detector if detector is not None else self.canvas_detector
        if runner.input_size != self.canvas_detector.input_size:
            raise InputError(f"a packed pass needs a session of the canvas size {self.canvas_detector.input_size}, "
                             f"got {runner.input_size}")  # fmt: skip
        with self._lock:
            items, n_roi_items, packings, refresh = self._prepare(frames, subset)
        images = [frames[it[0]][it[1]] for it in items]
        parts: list[list[list[PoseDetections]]] = [[[] for _ in range(self.n_cameras)] for _ in frames]
        part_rois: list[list[list[Roi]]] = [[[] for _ in range(self.n_cameras)] for _ in frames]
        refreshed: list[PoseDetections | None] = [None] * self.n_cameras
        canvases = [render_canvas(packing, images, self.detector.spec.pad_value) for packing in packings]
        # One inference for all canvases where the detector batches (GPU), else one each, cropped to its tiles.
        extents = [canvas_extent(packing) for packing in packings]
        if inputs is not None:
            inputs.extend(runner.input_for_extent(e) for e in extents)
        for packing, dets in zip(packings, runner.run_canvases(canvases, extents), strict=True):
            found = unpack_detections(dets, packing)
            for tile, det in zip(packing.tiles, found, strict=True):
                slot, cam, _ = items[tile.index]
                if tile.index >= n_roi_items:
                    refreshed[cam] = det
                else:
                    parts[slot][cam].append(det)
                    part_rois[slot][cam].append(items[tile.index][2])
        out = [
            [self._merge(p, n_kp, cam, r) for cam, (p, r) in enumerate(zip(slot_parts, slot_rois, strict=True))]
            for slot_parts, slot_rois in zip(parts, part_rois, strict=True)
        ]
        seeds = list(out[-1])
        for cam, extra in enumerate(refreshed):
            if extra is not None:
                out[-1][cam], seeds[cam] = self._add_refreshed(out[-1][cam], extra, n_kp)
        with self._lock:
            self._update_rois(seeds, subset)
            self.last_packings = packings
            self.last_tile_images = images  # tile.index → its source image (for drawing the canvases)
            self.stats.calls += 1
            self.stats.canvases += len(packings)
            self.stats.camera_frames += len(frames) * len(subset)
            self.stats.tiles += len(items)
            self.stats.full_frame_tiles += sum(1 for _, cam, r in items[:n_roi_items] if self._is_full(cam, r))
            self.stats.refresh_tiles += len(refresh)
        return out

    def _prepare(
        self, frames: Sequence[Sequence[Image]], subset: list[int]
    ) -> tuple[list[tuple[int, int, Roi]], int, list[Packing], list[int]]:
        """Under the lock: the pass's items ``(slot, camera, roi)`` (refresh tiles from the returned count on), its
        canvases and the cameras refreshed."""
        items: list[tuple[int, int, Roi]] = []
        for slot, cams in enumerate(frames):
            if len(cams) != self.n_cameras:
                raise InputError(f"slot {slot} has {len(cams)} images, expected {self.n_cameras} cameras")
            for cam in subset:
                img = cams[cam]
                w, h = self.image_sizes[cam]
                if img.shape[:2] != (h, w):
                    raise InputError(f"camera {cam} image is {img.shape[1]}x{img.shape[0]}, expected {w}x{h}")
                items.extend((slot, cam, roi) for roi in self.rois[cam])
        # Refresh tiles come last: item index >= n_roi_items marks them.
        n_roi_items = len(items)
        call = self.stats.calls
        for cam in self.refresh_cameras(call):
            self._refresh_due.setdefault(cam, call)
        due = sorted(c for c in self._refresh_due if c in subset and not any(self._is_full(c, r) for r in self.rois[c]))
        # A due refresh rides along when it fits the canvases this call needs anyway; one that would open a
        # canvas of its own waits, at most one period (then it is forced, alone, keeping the stagger).
        forced = [c for c in due if call - self._refresh_due[c] >= self.cfg.refresh_every]
        refresh = forced
        items = [*items, *((len(frames) - 1, c, full_roi(*self.image_sizes[c])) for c in forced)]
        packings = self._plan(items, n_roi_items)
        optional = [c for c in due if c not in forced]
        if optional:
            more = [*items, *((len(frames) - 1, c, full_roi(*self.image_sizes[c])) for c in optional)]
            plan = self._plan(more, n_roi_items)
            if len(plan) <= len(packings):
                items, packings, refresh = more, plan, due
        for cam in list(self._refresh_due):
            if cam in refresh or any(self._is_full(cam, r) for r in self.rois[cam]):
                del self._refresh_due[cam]
        return items, n_roi_items, packings, refresh

    def _plan(self, items: Sequence[tuple[int, int, Roi]], n_roi_items: int) -> list[Packing]:
        """Canvases for ``items`` (``(slot, camera, roi)``; those from ``n_roi_items`` on are refresh tiles)."""
        cw, ch = self.canvas_detector.input_size
        if self.cfg.align_stride > 0:
            aligned = [self._aligned(cam, roi, k >= n_roi_items) for k, (_, cam, roi) in enumerate(items)]
            return plan_aligned_canvases(aligned, cw, ch, gap=self.cfg.gap, stride=self.cfg.align_stride)
        rois = [it[2] for it in items]
        min_scales = [self._min_scales[it[1]] for it in items]
        return plan_canvases(rois, min_scales, cw, ch, gap=self.cfg.gap, max_scale=self._max_scale)

    def _is_full(self, cam: int, roi: Roi) -> bool:
        return roi == full_roi(*self.image_sizes[cam])

    def refresh_cameras(self, call: int) -> list[int]:
        """Cameras that get a whole-frame refresh tile on packed call number ``call`` (0-based).

        Camera ``c`` falls due on calls ``c * refresh_every // n_cameras + k * refresh_every``: the refreshes
        of a rig are spread evenly over the period, so their cost is too. A camera that looks at its whole
        frame anyway (it found nobody) is skipped. :meth:`detect` then adds a due refresh tile as soon as it
        fits the canvases that call needs anyway, or when it has waited a whole period.
        """
        period = self.cfg.refresh_every
        if period <= 0:
            return []
        return [
            cam
            for cam in range(self.n_cameras)
            if (call - cam * period // self.n_cameras) % period == 0
            and not any(self._is_full(cam, r) for r in self.rois[cam])
        ]

    def _aligned(self, cam: int, roi: Roi, refresh: bool) -> AlignedRoi:
        """How one ROI goes on a canvas: its whole-frame letterbox transform, or its own smaller scale.

        A refresh tile is scaled by ``refresh_scale_ratio``; a person ROI taller than ``max_tile_height`` of the
        canvas is scaled down to that height; every tile is at most :attr:`tile_ratio` of the whole-frame scale
        (1 but at the governor's deepest steps). Either is placed on the stride grid (phase 0): with a scale of
        its own, no placement reproduces the whole-frame pixels, so alignment buys nothing there.
        """
        lb = self._letterboxes[cam]
        ratio = 1.0
        if refresh:
            ratio = self.cfg.refresh_scale_ratio
        elif self.cfg.max_tile_height > 0 and not self._is_full(cam, roi):
            cap = self.cfg.max_tile_height * self.canvas_detector.input_size[1]
            ratio = min(1.0, cap / (roi.height * lb.sy))
        ratio = min(ratio, self.tile_ratio)
        if ratio >= 1.0:
            return AlignedRoi(roi, lb.sx, lb.sy, lb.pad_x, lb.pad_y)
        sx, sy = lb.sx * ratio, lb.sy * ratio
        return AlignedRoi(roi, sx, sy, -roi.x0 * sx, -roi.y0 * sy)

    def _add_refreshed(
        self, found: PoseDetections, extra: PoseDetections, n_kp: int
    ) -> tuple[PoseDetections, PoseDetections]:
        """Output and ROI seeds of a camera that also had a whole-frame refresh tile.

        The output keeps the ROI detections (full resolution) and adds refresh detections of people no ROI
        found. The seeds take every refresh detection too, so that a person whom a ROI showed only in part
        (a cut-off upper body) gets a ROI around the whole body next time: the overlapping ROIs merge.
        """
        new = [j for j in range(len(extra)) if not any(self._same_person(extra.boxes[j], b) for b in found.boxes)]
        out = PoseDetections.concatenate([found, extra.select(np.asarray(new, dtype=np.int64))], n_kp)
        return out, PoseDetections.concatenate([found, extra], n_kp)

    def _is_cut(self, box: FloatArray, roi: Roi, img_w: int, img_h: int) -> bool:
        """Whether ``box`` ends at an inner edge of ``roi`` (one that is not the image border), within the
        tolerance :func:`mocapd.core.roi_packing.grow_cut_boxes` uses."""
        tol = max(4.0, 0.5 * self.cfg.roi_margin * max(box[2] - box[0], box[3] - box[1]))
        return bool(
            (roi.x0 > 0 and box[0] - roi.x0 < tol)
            or (roi.x1 < img_w and roi.x1 - box[2] < tol)
            or (roi.y0 > 0 and box[1] - roi.y0 < tol)
            or (roi.y1 < img_h and roi.y1 - box[3] < tol)
        )

    def _same_person(self, a: FloatArray, b: FloatArray) -> bool:
        inter = _intersection(a, b)
        union = _box_area(a) + _box_area(b) - inter
        return inter > self.detector.spec.iou_threshold * union or inter > 0.8 * min(_box_area(a), _box_area(b))

    def _merge(self, parts: list[PoseDetections], n_kp: int, cam: int = 0, rois: Sequence[Roi] = ()) -> PoseDetections:
        det = PoseDetections.concatenate(parts, n_kp)
        if len(parts) <= 1 or len(det) <= 1:
            return det
        # Overlapping ROIs of one camera show the same person twice, once maybe cut by a tile edge: drop a
        # detection from another tile that overlaps a better one, or lies mostly inside it. "Better" is first
        # "not cut by its own tile's inner edge", then the score: a neighbour's tile often shows a person's
        # upper half with a confident score, and keeping that would drop the whole person seen in their own tile.
        source = np.concatenate([np.full(len(p), i) for i, p in enumerate(parts)])
        cut = np.zeros(len(det), dtype=np.bool_)
        if len(rois) == len(parts):
            w, h = self.image_sizes[cam]
            for i in range(len(det)):
                cut[i] = self._is_cut(det.boxes[i], rois[int(source[i])], w, h)
        order = np.lexsort((-det.scores, cut))
        keep: list[int] = []
        for i in order:
            dup = False
            for k in keep:
                if source[k] != source[i] and self._same_person(det.boxes[i], det.boxes[k]):
                    dup = True
                    break
            if not dup:
                keep.append(int(i))
        return det.select(np.asarray(sorted(keep, key=lambda j: -det.scores[j]), dtype=np.int64))

    def seed_rois(self, camera: int, found: PoseDetections) -> None:
        """Set ``camera``'s ROIs from a whole-frame detection of it (as a packed call would from its own)."""
        seeds = [PoseDetections.empty(self.detector.format.n_keypoints)] * self.n_cameras
        seeds[camera] = found
        with self._lock:
            self.rois[camera] = [full_roi(*self.image_sizes[camera])]  # a whole frame: nothing was cut
            self._update_rois(seeds, [camera])

    def canvases_for(self, cameras: Sequence[int]) -> int:
        """Canvases a call detecting only ``cameras`` needs for their current ROIs (refresh tiles left out)."""
        return len(self._packings_for(cameras))

    def pass_inputs(self, cameras: Sequence[int]) -> list[tuple[int, int]]:
        """The network input (width, height) of each canvas a call detecting only ``cameras`` would run: the
        canvas cropped to its tiles where an export fits (:meth:`OnnxPoseDetector.input_for_extent`). Their pixels
        are what the pass costs (:mod:`~mocapd.pipeline.detection_mode`)."""
        det = self.canvas_detector
        return [det.input_for_extent(canvas_extent(p)) for p in self._packings_for(cameras)]

    def _packings_for(self, cameras: Sequence[int]) -> list[Packing]:
        with self._lock:
            items = [(0, cam, roi) for cam in cameras for roi in self.rois[cam]]
            return self._plan(items, len(items)) if items else []

    def _update_rois(self, last: list[PoseDetections], cameras: Sequence[int]) -> None:
        stride = self.cfg.align_stride
        for cam in cameras:
            det = last[cam]
            w, h = self.image_sizes[cam]
            boxes = grow_cut_boxes(det.boxes, self.rois[cam], w, h, margin=self.cfg.roi_margin)
            rois = rois_from_boxes(boxes, w, h, margin=self.cfg.roi_margin)
            if stride > 0:
                lb = self._letterboxes[cam]
                rois = [snap_roi_to_grid(r, lb.sx, lb.sy, lb.pad_x, lb.pad_y, stride, w, h) for r in rois]
            self.rois[cam] = rois


class ScheduledDetector:
    """Temporal sub-sampling ``N_o/N_p`` in front of a :class:`PackedDetector` (seed 000 §3.3.2).

    Frames arrive one by one (all cameras of one frame index at a time). Frames the schedule skips are
    dropped; the ``N_o`` consecutive detected frames of a period are gathered and detected together, their
    ROIs packed into shared canvases (seed 003 §3.4: 2 frames x 4 cameras).
    """

    def __init__(self, packer: PackedDetector, schedule: SubsampleSchedule) -> None:
        self.packer = packer
        self.schedule = schedule
        self._pending: list[tuple[int, Sequence[Image]]] = []

    def push(self, frame_index: int, images: Sequence[Image]) -> list[tuple[int, list[PoseDetections]]]:
        """Offer frame ``frame_index``; returns ``(frame_index, detections per camera)`` of every frame whose
        detection completed with this call (none while a group is still filling or the frame is skipped)."""
        slot = self.schedule.slot(frame_index)
        out: list[tuple[int, list[PoseDetections]]] = []
        if self._pending and (slot <= 0 or frame_index != self._pending[-1][0] + 1):
            out.extend(self.flush())  # a group was interrupted (dropped frames): detect what it has
        if slot < 0:
            return out
        self._pending.append((frame_index, images))
        if slot == self.schedule.n_o - 1:
            out.extend(self.flush())
        return out

    def flush(self) -> list[tuple[int, list[PoseDetections]]]:
        """Detect the frames gathered so far (e.g. at the end of a stream)."""
        if not self._pending:
            return []
        pending, self._pending = self._pending, []
        dets = self.packer.detect([imgs for _, imgs in pending])
        return [(idx, d) for (idx, _), d in zip(pending, dets, strict=True)]


def detectors_from_config(
    cfg: DetectorConfig, image_sizes: Sequence[tuple[int, int]]
) -> tuple[OnnxPoseDetector, OnnxPoseDetector]:
    """One inference session of the ``[detector]`` section for packed passes: (whole-frame detector, canvas
    detector), the same object unless ``[detector.packing]`` asks for canvases of another size than the model's
    input. ``intra_op_threads`` is taken as given (0: onnxruntime's default)."""
    ref = OnnxPoseDetector.from_config(cfg, image_sizes)  # the whole-frame passes' inputs made (or found missing)
    pk = cfg.packing
    cw = pk.canvas_width or cfg.model.input_width
    ch = pk.canvas_height or cfg.model.input_height
    if (cw, ch) == (cfg.model.input_width, cfg.model.input_height):
        return ref, ref
    spec = dataclasses.replace(cfg.model, path=pk.canvas_model_path, input_width=cw, input_height=ch)
    canvas = OnnxPoseDetector(
        spec,
        providers=cfg.providers,
        precision=cfg.precision,
        intra_op_threads=cfg.intra_op_threads,
        inter_op_threads=cfg.inter_op_threads,
        batch=cfg.batch,
        intra_op_spinning=cfg.intra_op_spinning,
    )
    return ref, canvas


def packed_detector_from_config(cfg: DetectorConfig, image_sizes: Sequence[tuple[int, int]]) -> PackedDetector:
    """A :class:`PackedDetector` for the ``[detector]`` section (its first session, :func:`detectors_from_config`)."""
    ref, canvas = detectors_from_config(cfg, image_sizes)
    return PackedDetector(ref, image_sizes, cfg.packing, canvas_detector=canvas)
