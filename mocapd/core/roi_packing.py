"""ROI packing and temporal sub-sampling of keypoint detection (seed 000 §3.3.1–3.3.2, seed 003 §3.4).

A pose network costs the same whatever is in its input image, and the people in a camera image fill only
part of it. So each camera gets a region of interest (ROI): the box around its last detections, expanded by a
margin, or the whole image when it found nobody. The ROIs of several cameras (and optionally of two
consecutive frames) are scaled by one common factor and packed into one model-sized canvas; detections on the
canvas are assigned back to the tile they lie in and mapped to that camera's pixels.

Temporal sub-sampling ``N_o/N_p`` detects the first ``N_o`` frames of every ``N_p``; with ``N_o = 2`` the two
consecutive frames are packed into the same canvas (8 ROIs for 4 cameras, as in seed 003).

Everything is pure geometry; the image copies are done by :mod:`mocapd.pipeline.packing`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.pose2d import PoseDetections, box_iou
from mocapd.errors import ConfigError, InputError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Roi:
    """An integer pixel rectangle ``[x0, x1) x [y0, y1)`` of a source image."""

    x0: int
    y0: int
    x1: int
    y1: int

    @property
    def width(self) -> int:
        return self.x1 - self.x0

    @property
    def height(self) -> int:
        return self.y1 - self.y0


def full_roi(img_w: int, img_h: int) -> Roi:
    """The whole image."""
    return Roi(0, 0, img_w, img_h)


def roi_from_boxes(boxes: FloatArray, img_w: int, img_h: int, *, margin: float = 0.2, min_size: int = 64) -> Roi:
    """Expanded bounding box of ``boxes (n, 4)`` clipped to the image; the whole image when ``n == 0``.

    Parameters
    ----------
    boxes : ndarray, shape (n, 4)
        x0, y0, x1, y1 of the last detections in this camera (pixels).
    img_w, img_h : int
        Image size.
    margin : float
        Each side grows by this fraction of the union box's larger side, so that a person who moved
        between the detection and the next frame stays inside.
    min_size : int
        The ROI is at least this many pixels wide and high (centred), where the image allows.
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    b = b[np.all(np.isfinite(b), axis=1)]
    if b.shape[0] == 0:
        return full_roi(img_w, img_h)
    x0, y0 = b[:, 0].min(), b[:, 1].min()
    x1, y1 = b[:, 2].max(), b[:, 3].max()
    grow = margin * max(x1 - x0, y1 - y0)
    x0, y0, x1, y1 = x0 - grow, y0 - grow, x1 + grow, y1 + grow
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    half_w = max(x1 - x0, min(min_size, img_w)) / 2
    half_h = max(y1 - y0, min(min_size, img_h)) / 2
    rx0 = max(0, math.floor(cx - half_w))
    ry0 = max(0, math.floor(cy - half_h))
    rx1 = min(img_w, math.ceil(cx + half_w))
    ry1 = min(img_h, math.ceil(cy + half_h))
    if rx1 - rx0 < 1 or ry1 - ry0 < 1:
        # The boxes lay entirely outside the image: look everywhere again.
        return full_roi(img_w, img_h)
    return Roi(rx0, ry0, rx1, ry1)


def _area(r: Roi) -> int:
    return r.width * r.height


def rois_from_boxes(
    boxes: FloatArray,
    img_w: int,
    img_h: int,
    *,
    margin: float = 0.1,
    min_size: int = 64,
    merge_cost: float = 1.0,
) -> list[Roi]:
    """One expanded ROI per person, cheaply mergeable ones merged; ``[whole image]`` when there is nobody.

    Packing people separately (rather than the union of all of a camera's people) keeps a bystander at the
    far edge of the image from dragging a large empty area into the canvas.

    Parameters
    ----------
    boxes : ndarray, shape (n, 4)
        x0, y0, x1, y1 of the last detections in this camera (pixels).
    img_w, img_h, margin, min_size
        As in :func:`roi_from_boxes`, applied per person.
    merge_cost : float
        Two overlapping ROIs merge into their union when its area is at most this × the sum of their areas.
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    b = b[np.all(np.isfinite(b), axis=1)]
    if b.shape[0] == 0:
        return [full_roi(img_w, img_h)]
    rois = [roi_from_boxes(bb[None], img_w, img_h, margin=margin, min_size=min_size) for bb in b]
    merged = True
    while merged:  # merge until no two ROIs overlap (a few people: quadratic is fine)
        merged = False
        for i in range(len(rois)):
            for j in range(i + 1, len(rois)):
                a, c = rois[i], rois[j]
                u = Roi(min(a.x0, c.x0), min(a.y0, c.y0), max(a.x1, c.x1), max(a.y1, c.y1))
                overlap = a.x0 < c.x1 and c.x0 < a.x1 and a.y0 < c.y1 and c.y0 < a.y1
                # Merge only when the union costs little more canvas than the two ROIs apart; otherwise keep
                # both (the same pixels then appear twice and the duplicate detection is removed later).
                if overlap and _area(u) <= merge_cost * (_area(a) + _area(c)):
                    rois[i] = u
                    del rois[j]
                    merged = True
                    break
            if merged:
                break
    return rois


def grow_cut_boxes(
    boxes: FloatArray,
    rois: Sequence[Roi],
    img_w: int,
    img_h: int,
    *,
    margin: float,
    grow: float = 0.5,
) -> FloatArray:
    """Boxes that end at an inner edge of the ROI they were found in, grown past that edge.

    A person cut by a ROI edge (they moved faster than the margin, or a previous detection was partial) is
    detected only up to the edge; an ROI built from that box would cut them again, for ever. A box whose side
    lies closer to an inner ROI edge (one that is not the image border) than half the ROI margin is therefore
    extended by ``grow`` of its size on that side, so that the next ROI takes in the rest of the person.

    Parameters
    ----------
    boxes : ndarray, shape (n, 4)
        Detections of one camera (x0, y0, x1, y1, image pixels).
    rois : sequence of Roi
        The ROIs this camera was detected through.
    img_w, img_h : int
        Image size.
    margin : float
        The ROI margin (fraction of the box's larger side) the ROIs were built with.
    grow : float
        Growth, as a fraction of the box's width (left/right) or height (top/bottom).
    Returns
    -------
    ndarray, shape (n, 4)
    """
    out = np.array(boxes, dtype=np.float64).reshape(-1, 4)
    for b in out:
        cx, cy = (b[0] + b[2]) / 2, (b[1] + b[3]) / 2
        w, h = b[2] - b[0], b[3] - b[1]
        tol = max(4.0, 0.5 * margin * max(w, h))
        # The ROI the person was found in: the one holding most of the box (as unpack_detections assigns
        # detections to tiles). Testing only "contains the centre" would take a neighbour's overlapping ROI,
        # whose edge runs through this person, and grow boxes that were never cut.
        inside = [
            (min(r.x1, b[2]) - max(r.x0, b[0])) * (min(r.y1, b[3]) - max(r.y0, b[1]))
            if r.x0 <= cx <= r.x1 and r.y0 <= cy <= r.y1
            else -1.0
            for r in rois
        ]
        if not inside or max(inside) < 0:
            continue
        r = rois[int(np.argmax(inside))]
        if r.x0 > 0 and b[0] - r.x0 < tol:
            b[0] -= grow * w
        if r.x1 < img_w and r.x1 - b[2] < tol:
            b[2] += grow * w
        if r.y0 > 0 and b[1] - r.y0 < tol:
            b[1] -= grow * h
        if r.y1 < img_h and r.y1 - b[3] < tol:
            b[3] += grow * h
    return out


@dataclass(frozen=True)
class Tile:
    """Where one ROI went on the canvas: source pixel ``p`` lands at ``(p - roi origin) * (sx, sy) + (x, y)``.

    Attributes
    ----------
    index : int
        Position of the ROI in the list given to the packer.
    roi : Roi
        Source rectangle.
    x, y : float
        Canvas position of the ROI's top-left corner (may be fractional in aligned packing).
    sx, sy : float
        Canvas pixels per source pixel.
    """

    index: int
    roi: Roi
    x: float
    y: float
    sx: float
    sy: float

    @property
    def w(self) -> float:
        """Width on the canvas (pixels)."""
        return self.roi.width * self.sx

    @property
    def h(self) -> float:
        """Height on the canvas (pixels)."""
        return self.roi.height * self.sy

    def to_source(self, det: PoseDetections) -> PoseDetections:
        """Detections in canvas pixels → source-image pixels."""
        sx, sy = self.sx, self.sy
        return det.transformed(1.0 / sx, 1.0 / sy, self.roi.x0 - self.x / sx, self.roi.y0 - self.y / sy)

    def to_canvas(self, det: PoseDetections) -> PoseDetections:
        """Detections in source-image pixels → canvas pixels (for tests and drawing)."""
        sx, sy = self.sx, self.sy
        return det.transformed(sx, sy, self.x - self.roi.x0 * sx, self.y - self.roi.y0 * sy)


@dataclass(frozen=True)
class Packing:
    """A layout of ROIs on a ``canvas_w x canvas_h`` canvas at one common ``scale``."""

    canvas_w: int
    canvas_h: int
    scale: float
    tiles: tuple[Tile, ...]


def _shelf(sizes: Sequence[tuple[int, int]], scale: float, W: int, H: int, gap: int) -> list[tuple[int, int]] | None:
    """Shelf-pack scaled sizes into W x H; positions in input order, or None when they do not fit."""
    scaled = [(max(1, math.floor(w * scale)), max(1, math.floor(h * scale))) for w, h in sizes]
    order = sorted(range(len(sizes)), key=lambda i: -scaled[i][1])
    pos: list[tuple[int, int]] = [(0, 0)] * len(sizes)
    x = y = shelf_h = 0
    for i in order:
        w, h = scaled[i]
        if w > W:
            return None
        if x > 0 and x + w > W:
            y += shelf_h + gap
            x = shelf_h = 0
        if y + h > H:
            return None
        pos[i] = (x, y)
        x += w + gap
        shelf_h = max(shelf_h, h)
    return pos


def _layout(
    sizes: Sequence[tuple[int, int]], scale: float, W: int, H: int, gap: int
) -> tuple[list[tuple[int, int]], bool] | None:
    """Positions of ``sizes`` at ``scale``: row shelves, else column shelves; None when neither fits."""
    pos = _shelf(sizes, scale, W, H, gap)
    if pos is not None:
        return pos, False
    tpos = _shelf([(h, w) for w, h in sizes], scale, H, W, gap)
    if tpos is not None:
        return [(y, x) for x, y in tpos], True
    return None


def pack_rois(rois: Sequence[Roi], canvas_w: int, canvas_h: int, *, gap: int = 4, max_scale: float = 1.0) -> Packing:
    """Pack ``rois`` onto one canvas at the largest common scale (shelf packing, rows or columns).

    Parameters
    ----------
    rois : sequence of Roi
        Source rectangles, any number ≥ 1.
    canvas_w, canvas_h : int
        The detector's input size.
    gap : int
        Canvas pixels of padding left between tiles, so that one tile's people do not bleed into the next.
    max_scale : float
        Never enlarge beyond this (1.0: no up-sampling of small ROIs).

    Returns
    -------
    Packing
        Tiles in the order of ``rois``.
    """
    if not rois:
        raise InputError("pack_rois needs at least one ROI")
    sizes = [(r.width, r.height) for r in rois]
    if min(min(s) for s in sizes) < 1:
        raise InputError(f"empty ROI among {rois}")
    hi = min(max_scale, *(min(canvas_w / w, canvas_h / h) for w, h in sizes))
    found = _layout(sizes, hi, canvas_w, canvas_h, gap)
    scale = hi
    if found is None:
        lo = 0.0
        # Bisection on the common scale; 24 halvings leave < 1e-7 of the range, far below a pixel.
        for _ in range(24):
            mid = (lo + hi) / 2
            if _layout(sizes, mid, canvas_w, canvas_h, gap) is None:
                hi = mid
            else:
                lo = mid
        found = _layout(sizes, lo, canvas_w, canvas_h, gap)
        scale = lo
    if found is None or scale <= 0.0:
        raise InputError(f"cannot pack {len(rois)} ROIs onto {canvas_w}x{canvas_h} with gap {gap}")
    positions, _ = found
    tiles = []
    for i, (r, (x, y)) in enumerate(zip(rois, positions, strict=True)):
        # Whole canvas pixels per tile (what _shelf reserved); the exact per-axis scale follows from them.
        w = max(1, math.floor(r.width * scale))
        h = max(1, math.floor(r.height * scale))
        tiles.append(Tile(index=i, roi=r, x=float(x), y=float(y), sx=w / r.width, sy=h / r.height))
    return Packing(canvas_w, canvas_h, scale, tuple(tiles))


def plan_canvases(
    rois: Sequence[Roi],
    min_scales: Sequence[float],
    canvas_w: int,
    canvas_h: int,
    *,
    gap: int = 4,
    max_scale: float = 1.0,
) -> list[Packing]:
    """Group ROIs onto as few canvases as possible without scaling any below its ``min_scale``.

    First-fit decreasing by area: each ROI joins the first canvas where everything still fits at the
    largest ``min_scale`` of that canvas's members, else opens a new canvas. Each canvas is then packed at
    its largest common scale. A ROI that cannot reach its ``min_scale`` even alone (e.g. a whole frame with a
    ``min_scale`` above the letterbox scale) gets a canvas of its own.

    Returns
    -------
    list of Packing
        Every tile's ``index`` refers to ``rois``.
    """
    if len(rois) != len(min_scales):
        raise InputError(f"{len(rois)} ROIs but {len(min_scales)} min_scales")
    order = sorted(range(len(rois)), key=lambda i: -rois[i].width * rois[i].height)
    groups: list[list[int]] = []
    for i in order:
        for g in groups:
            members = [*g, i]
            need = max(min_scales[m] for m in members)
            sizes = [(rois[m].width, rois[m].height) for m in members]
            if need <= max_scale and _layout(sizes, need, canvas_w, canvas_h, gap) is not None:
                g.append(i)
                break
        else:
            groups.append([i])
    packings = []
    for g in groups:
        p = pack_rois([rois[m] for m in g], canvas_w, canvas_h, gap=gap, max_scale=max_scale)
        tiles = tuple(Tile(index=g[t.index], roi=t.roi, x=t.x, y=t.y, sx=t.sx, sy=t.sy) for t in p.tiles)
        packings.append(Packing(canvas_w, canvas_h, p.scale, tiles))
    return packings


@dataclass(frozen=True)
class AlignedRoi:
    """A ROI to be packed at a fixed transform: the whole-frame letterbox's scale and stride phase.

    Attributes
    ----------
    roi : Roi
        Source rectangle.
    sx, sy : float
        The whole-frame letterbox scale of this camera.
    pad_x, pad_y : float
        The whole-frame letterbox padding: source pixel ``p`` sits at ``p * s + pad`` there.
    """

    roi: Roi
    sx: float
    sy: float
    pad_x: float
    pad_y: float

    @property
    def phase(self) -> tuple[float, float]:
        """Canvas position of the ROI's origin in the whole-frame letterbox."""
        return self.roi.x0 * self.sx + self.pad_x, self.roi.y0 * self.sy + self.pad_y


def snap_roi_to_grid(roi: Roi, item_sx: float, item_sy: float, pad_x: float, pad_y: float, stride: int,
                     img_w: int, img_h: int) -> Roi:  # fmt: skip
    """Grow ``roi`` outward so that its whole-frame letterbox edges fall on the ``stride`` grid.

    Aligned tiles must sit at their letterbox position modulo the stride; a ROI whose edges are already on
    that grid packs with no slack at all, and the slack it would have cost is filled with image context
    instead. The left/top edges land within a fraction of a pixel after a grid line (never before it, which
    would cost a whole stride); the result is clipped to the image.
    """

    def grow(lo: int, hi: int, s: float, pad: float, size: int) -> tuple[int, int]:
        g_lo = math.floor((lo * s + pad) / stride) * stride
        g_hi = math.ceil((hi * s + pad) / stride) * stride
        new_lo = max(0, math.ceil((g_lo - pad) / s - 1e-9))
        new_hi = min(size, math.floor((g_hi - pad) / s + 1e-9))
        return min(new_lo, lo), max(new_hi, hi)

    x0, x1 = grow(roi.x0, roi.x1, item_sx, pad_x, img_w)
    y0, y1 = grow(roi.y0, roi.y1, item_sy, pad_y, img_h)
    return Roi(x0, y0, x1, y1)


def _shelf_aligned(
    items: Sequence[AlignedRoi], W: int, H: int, gap: int, stride: int
) -> list[tuple[float, float]] | None:
    """Shelf-pack at fixed scales; each tile's origin ≡ its whole-frame position (mod ``stride``)."""
    order = sorted(range(len(items)), key=lambda i: -items[i].roi.height * items[i].sy)
    pos: list[tuple[float, float]] = [(0.0, 0.0)] * len(items)
    x = y = shelf_h = 0.0

    def snap(cursor: float, phase: float) -> float:
        return cursor + (phase - cursor) % stride

    for i in order:
        it = items[i]
        w, h = it.roi.width * it.sx, it.roi.height * it.sy
        px, py = it.phase
        tx = snap(x, px)
        if x > 0 and tx + w > W:
            y += shelf_h + gap
            x = shelf_h = 0.0
            tx = snap(x, px)
        ty = snap(y, py)
        if tx + w > W or ty + h > H:
            return None
        pos[i] = (tx, ty)
        x = math.ceil(tx + w) + gap
        shelf_h = max(shelf_h, math.ceil(ty + h) - y)
    return pos


def plan_aligned_canvases(
    items: Sequence[AlignedRoi], canvas_w: int, canvas_h: int, *, gap: int = 4, stride: int = 32
) -> list[Packing]:
    """Group ROIs onto few canvases, each at its whole-frame scale and stride phase.

    A convolutional detector is not exactly shift-invariant: its output depends on where the content sits
    relative to its stride grid. Placing every tile so that its pixels are the whole-frame letterbox's pixels
    moved by a multiple of ``stride`` makes packed detection see exactly what whole-frame detection sees
    (up to the context outside the ROI), at the cost of up to ``stride`` pixels of slack per tile and axis.
    Two planners run and the one with fewer canvases wins (shelves on a tie, the older layout):

    * shelves: first-fit decreasing, tried in three orders (area, height, width); each canvas is laid out in
      row shelves or, failing that, column shelves;
    * grid (:func:`_plan_grid`): every tile occupies whole ``stride`` cells, and tiles go top-left first-fit
      onto a cell occupancy grid, so that a short tile can sit under a tall one's neighbour instead of opening
      a shelf as high as the tallest tile.

    A ROI always fits alone when it lies inside its letterboxed frame (or, for a tile with its own scale, when
    it is no larger than the canvas).
    """
    keys = (
        lambda i: -items[i].roi.width * items[i].roi.height,
        lambda i: -items[i].roi.height * items[i].sy,
        lambda i: -items[i].roi.width * items[i].sx,
    )
    best: list[list[int]] | None = None
    for key in keys:
        groups: list[list[int]] = []
        for i in sorted(range(len(items)), key=key):
            for g in groups:
                if _layout_aligned([items[m] for m in [*g, i]], canvas_w, canvas_h, gap, stride) is not None:
                    g.append(i)
                    break
            else:
                groups.append([i])
        if best is None or len(groups) < len(best):
            best = groups
    grid = _plan_grid(items, canvas_w, canvas_h, gap, stride) if stride > 0 else None
    if grid is not None and len(grid) < len(best or []):
        return grid
    packings = []
    for g in best or []:
        pos = _layout_aligned([items[m] for m in g], canvas_w, canvas_h, gap, stride)
        if pos is None:  # only possible for a ROI outside its frame: a caller bug
            raise InputError(f"ROI {items[g[0]].roi} does not fit its own letterbox")
        tiles = tuple(
            Tile(index=m, roi=items[m].roi, x=px, y=py, sx=items[m].sx, sy=items[m].sy)
            for m, (px, py) in zip(g, pos, strict=True)
        )
        packings.append(Packing(canvas_w, canvas_h, items[g[0]].sx, tiles))
    return packings


def _grid_footprint(it: AlignedRoi, gap: int, stride: int) -> tuple[int, int, float, float]:
    """Cells ``(cols, rows)`` an aligned tile covers, and its offset inside its first cell (canvas pixels)."""
    px, py = it.phase
    fx, fy = px % stride, py % stride
    # 1e-6: a tile whose far edge lies on a grid line (up to float noise) must not take one more cell.
    cols = math.ceil((fx + it.roi.width * it.sx + gap) / stride - 1e-6)
    rows = math.ceil((fy + it.roi.height * it.sy + gap) / stride - 1e-6)
    return max(cols, 1), max(rows, 1), fx, fy


def _free_cell(occupied: NDArray[np.bool_], cols: int, rows: int) -> tuple[int, int] | None:
    """Top-most, then left-most cell where a ``cols x rows`` block of free cells starts; None if none."""
    gh, gw = occupied.shape
    if cols > gw or rows > gh:
        return None
    s = np.zeros((gh + 1, gw + 1), dtype=np.int32)
    s[1:, 1:] = occupied.cumsum(0).cumsum(1)
    used = s[rows:, cols:] - s[:-rows, cols:] - s[rows:, :-cols] + s[:-rows, :-cols]
    free = np.argwhere(used == 0)  # row-major: the first one is top-most, then left-most
    return None if len(free) == 0 else (int(free[0][0]), int(free[0][1]))


def _plan_grid(
    items: Sequence[AlignedRoi], canvas_w: int, canvas_h: int, gap: int, stride: int
) -> list[Packing] | None:
    """Top-left first-fit of whole-cell footprints, in three orders (height, area, width); fewest canvases.

    Returns None when a tile does not fit an empty canvas (the shelf planner then reports it).
    """
    gw, gh = canvas_w // stride, canvas_h // stride
    foot = [_grid_footprint(it, gap, stride) for it in items]
    if any(c > gw or r > gh for c, r, _, _ in foot):
        return None
    keys = (
        lambda i: (-foot[i][1], -foot[i][0]),
        lambda i: (-foot[i][0] * foot[i][1], -foot[i][1]),
        lambda i: (-foot[i][0], -foot[i][1]),
    )
    best: list[list[tuple[int, int, int]]] | None = None
    for key in keys:
        grids: list[NDArray[np.bool_]] = []
        placed: list[list[tuple[int, int, int]]] = []  # per canvas: (item, row, col)
        for i in sorted(range(len(items)), key=key):
            cols, rows = foot[i][0], foot[i][1]
            for occ, members in zip(grids, placed, strict=True):
                cell = _free_cell(occ, cols, rows)
                if cell is not None:
                    occ[cell[0] : cell[0] + rows, cell[1] : cell[1] + cols] = True
                    members.append((i, *cell))
                    break
            else:
                occ = np.zeros((gh, gw), dtype=np.bool_)
                occ[:rows, :cols] = True
                grids.append(occ)
                placed.append([(i, 0, 0)])
        if best is None or len(placed) < len(best):
            best = placed
    packings = []
    for members in best or []:
        tiles = tuple(
            Tile(
                index=m,
                roi=items[m].roi,
                x=c * stride + foot[m][2],
                y=r * stride + foot[m][3],
                sx=items[m].sx,
                sy=items[m].sy,
            )
            for m, r, c in members
        )
        packings.append(Packing(canvas_w, canvas_h, items[members[0][0]].sx, tiles))
    return packings


def _layout_aligned(
    items: Sequence[AlignedRoi], W: int, H: int, gap: int, stride: int
) -> list[tuple[float, float]] | None:
    """Row shelves, else column shelves (the same packing on transposed geometry)."""
    pos = _shelf_aligned(items, W, H, gap, stride)
    if pos is not None:
        return pos
    flipped = [
        AlignedRoi(Roi(it.roi.y0, it.roi.x0, it.roi.y1, it.roi.x1), it.sy, it.sx, it.pad_y, it.pad_x) for it in items
    ]
    tpos = _shelf_aligned(flipped, H, W, gap, stride)
    return None if tpos is None else [(y, x) for x, y in tpos]


def unpack_detections(det: PoseDetections, packing: Packing, *, min_inside: float = 0.5) -> list[PoseDetections]:
    """Assign canvas detections to tiles and map them back to their source images.

    A detection goes to the tile that holds the largest part of its box, if that part is at least
    ``min_inside`` of the box area (boxes that mostly cover the gap or padding are dropped). Keypoints keep
    their confidences.

    Returns
    -------
    list of PoseDetections
        One per tile, in tile order, in source-image pixels.
    """
    n_kp = det.keypoints.shape[1]
    if len(det) == 0:
        return [PoseDetections.empty(n_kp) for _ in packing.tiles]
    tile_boxes = np.array([[t.x, t.y, t.x + t.w, t.y + t.h] for t in packing.tiles], dtype=np.float64)
    b = det.boxes
    lt = np.maximum(b[:, None, :2], tile_boxes[None, :, :2])
    rb = np.minimum(b[:, None, 2:], tile_boxes[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0.0, None), axis=2)  # (n, tiles)
    area = np.maximum(np.prod(np.clip(b[:, 2:] - b[:, :2], 0.0, None), axis=1), 1e-9)
    owner = np.argmax(inter, axis=1)
    frac = inter[np.arange(len(det)), owner] / area
    out = []
    for ti, tile in enumerate(packing.tiles):
        mine = np.flatnonzero((owner == ti) & (frac >= min_inside))
        out.append(tile.to_source(det.select(mine)))
    return out


def match_people(a: PoseDetections, b: PoseDetections, min_iou: float = 0.3) -> list[tuple[int, int]]:
    """Greedy one-to-one matching of two detection sets of the same image by box IoU (highest first)."""
    if len(a) == 0 or len(b) == 0:
        return []
    iou = box_iou(a.boxes, b.boxes)
    pairs: list[tuple[int, int]] = []
    used_a: set[int] = set()
    used_b: set[int] = set()
    for flat in np.argsort(-iou, axis=None):
        i, j = divmod(int(flat), iou.shape[1])
        if iou[i, j] < min_iou:
            break
        if i in used_a or j in used_b:
            continue
        pairs.append((i, j))
        used_a.add(i)
        used_b.add(j)
    return pairs


@dataclass(frozen=True)
class SubsampleSchedule:
    """Temporal sub-sampling ``N_o/N_p``: detect the first ``n_o`` frames of every ``n_p`` (seed 000 §4.1.2).

    ``1/1`` detects every frame, ``2/8`` detects frames 0, 1, 8, 9, 16, 17, ...
    """

    n_o: int = 1
    n_p: int = 1

    def __post_init__(self) -> None:
        if not (1 <= self.n_o <= self.n_p):
            raise ConfigError(f"sub-sampling needs 1 <= N_o <= N_p, got N_o={self.n_o} N_p={self.n_p}")

    def detects(self, frame_index: int) -> bool:
        """Whether frame ``frame_index`` (0-based count since the schedule started) is detected."""
        return frame_index % self.n_p < self.n_o

    def slot(self, frame_index: int) -> int:
        """Position of a detected frame inside its group of ``n_o`` (0 … n_o-1); -1 for skipped frames."""
        r = frame_index % self.n_p
        return r if r < self.n_o else -1

    @property
    def fraction(self) -> float:
        """Fraction of frames detected."""
        return self.n_o / self.n_p
