"""ROI packing geometry and the N_o/N_p sub-sampling schedule (seed 000 §3.3)."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.pose2d import PoseDetections, letterbox_geometry
from mocapd.core.roi_packing import (
    AlignedRoi,
    Packing,
    Roi,
    SubsampleSchedule,
    full_roi,
    grow_cut_boxes,
    match_people,
    pack_rois,
    plan_aligned_canvases,
    plan_canvases,
    roi_from_boxes,
    rois_from_boxes,
    snap_roi_to_grid,
    unpack_detections,
)
from mocapd.errors import ConfigError, InputError


def _no_overlap(p: Packing) -> None:
    for i, a in enumerate(p.tiles):
        assert a.x >= 0 and a.y >= 0 and a.x + a.w <= p.canvas_w + 1e-9 and a.y + a.h <= p.canvas_h + 1e-9
        for b in p.tiles[i + 1 :]:
            apart = a.x + a.w <= b.x or b.x + b.w <= a.x or a.y + a.h <= b.y or b.y + b.h <= a.y
            assert apart, f"tiles {a} and {b} overlap"


def _random_rois(rng: np.random.Generator, n: int, w: int = 1088, h: int = 1920) -> list[Roi]:
    out = []
    for _ in range(n):
        rw, rh = int(rng.integers(30, w // 2)), int(rng.integers(60, h // 2))
        x0, y0 = int(rng.integers(0, w - rw)), int(rng.integers(0, h - rh))
        out.append(Roi(x0, y0, x0 + rw, y0 + rh))
    return out


def test_roi_is_whole_image_without_detections() -> None:
    assert roi_from_boxes(np.zeros((0, 4)), 1088, 1920) == full_roi(1088, 1920)
    assert rois_from_boxes(np.zeros((0, 4)), 1088, 1920) == [full_roi(1088, 1920)]
    assert roi_from_boxes(np.array([[np.nan, 0, 1, 1]]), 100, 100) == full_roi(100, 100)


def test_roi_expands_and_clips() -> None:
    r = roi_from_boxes(np.array([[100.0, 200.0, 300.0, 1000.0]]), 1088, 1920, margin=0.1)
    assert (r.x0, r.y0, r.x1, r.y1) == (20, 120, 380, 1080)
    edge = roi_from_boxes(np.array([[0.0, 0.0, 50.0, 100.0]]), 1088, 1920, margin=0.5)
    assert (edge.x0, edge.y0) == (0, 0)
    tiny = roi_from_boxes(np.array([[500.0, 500.0, 502.0, 502.0]]), 1088, 1920, margin=0.0, min_size=64)
    assert tiny.width == 64 and tiny.height == 64


def test_rois_from_boxes_keeps_distant_people_apart_and_merges_close_ones() -> None:
    far = np.array([[0.0, 300.0, 120.0, 750.0], [500.0, 400.0, 800.0, 1300.0]])
    assert len(rois_from_boxes(far, 1088, 1920, margin=0.05)) == 2
    close = np.array([[500.0, 400.0, 800.0, 1300.0], [520.0, 420.0, 810.0, 1290.0]])
    merged = rois_from_boxes(close, 1088, 1920, margin=0.05)
    assert len(merged) == 1
    assert merged[0].x0 <= 500 and merged[0].x1 >= 810


@pytest.mark.parametrize("seed", range(5))
def test_pack_rois_fits_without_overlap_and_round_trips(seed: int) -> None:
    rng = np.random.default_rng(seed)
    rois = _random_rois(rng, 8)
    p = pack_rois(rois, 640, 640, gap=4)
    _no_overlap(p)
    assert 0 < p.scale <= 1.0
    for tile, roi in zip(p.tiles, rois, strict=True):
        assert tile.roi == roi
        pts = rng.uniform([roi.x0, roi.y0], [roi.x1, roi.y1], (10, 2))
        det = PoseDetections(
            np.hstack([pts[:1], pts[:1] + 1]), np.ones(1), np.concatenate([pts, np.ones((10, 1))], 1)[None]
        )
        back = tile.to_source(tile.to_canvas(det))
        np.testing.assert_allclose(back.keypoints, det.keypoints, atol=1e-9)


def test_pack_rois_does_not_upscale_beyond_max_scale() -> None:
    p = pack_rois([Roi(0, 0, 100, 100)], 640, 640, max_scale=1.0)
    assert p.scale == 1.0 and p.tiles[0].w == 100


def test_pack_rois_needs_rois() -> None:
    with pytest.raises(InputError):
        pack_rois([], 640, 640)


def test_plan_canvases_respects_min_scale() -> None:
    rois = [Roi(0, 0, 400, 1000)] * 8
    packs = plan_canvases(rois, [1 / 3] * 8, 640, 640, gap=4, max_scale=1 / 3)
    assert sorted(t.index for p in packs for t in p.tiles) == list(range(8))
    for p in packs:
        _no_overlap(p)
        assert p.scale >= 1 / 3 - 1e-6
    assert len(packs) == 2  # 133 x 333 tiles: 4 per row, one row per canvas


def test_aligned_tiles_keep_whole_frame_scale_and_stride_phase() -> None:
    rng = np.random.default_rng(3)
    lb = letterbox_geometry(1088, 1920, 640, 640)
    items = [AlignedRoi(r, lb.sx, lb.sy, lb.pad_x, lb.pad_y) for r in _random_rois(rng, 10, 1088, 1920)]
    packs = plan_aligned_canvases(items, 640, 640, gap=4, stride=32)
    assert sorted(t.index for p in packs for t in p.tiles) == list(range(10))
    for p in packs:
        _no_overlap(p)
        for t in p.tiles:
            px, py = items[t.index].phase
            assert (t.x - px) % 32 == pytest.approx(0.0, abs=1e-9) or (t.x - px) % 32 == pytest.approx(32.0)
            assert (t.y - py) % 32 == pytest.approx(0.0, abs=1e-9) or (t.y - py) % 32 == pytest.approx(32.0)
            assert (t.sx, t.sy) == (lb.sx, lb.sy)


def test_whole_frame_aligned_tile_is_the_letterbox() -> None:
    lb = letterbox_geometry(1088, 1920, 640, 640)
    (p,) = plan_aligned_canvases([AlignedRoi(full_roi(1088, 1920), lb.sx, lb.sy, lb.pad_x, lb.pad_y)], 640, 640)
    (t,) = p.tiles
    # Left-most spot with the letterbox's phase: the letterbox moved left by whole strides.
    assert (t.x, t.y) == (lb.pad_x % 32, lb.pad_y)
    assert (t.sx, t.sy) == (lb.sx, lb.sy)


def test_unpack_assigns_detections_to_their_tile_and_source() -> None:
    rois = [Roi(100, 200, 500, 1200), Roi(0, 0, 300, 600), Roi(600, 900, 1000, 1800)]
    p = pack_rois(rois, 640, 640, gap=4)
    rng = np.random.default_rng(4)
    truth = []
    canvas_parts = []
    for t in p.tiles:
        r = t.roi
        x0, y0 = r.x0 + 0.2 * r.width, r.y0 + 0.2 * r.height
        box = np.array([[x0, y0, x0 + 0.5 * r.width, y0 + 0.6 * r.height]])
        kp = np.concatenate([rng.uniform([x0, y0], box[0, 2:], (17, 2)), rng.uniform(0, 1, (17, 1))], 1)[None]
        d = PoseDetections(box, np.array([0.9]), kp)
        truth.append(d)
        canvas_parts.append(t.to_canvas(d))
    # A detection that lies mostly in the gap/padding belongs to no tile.
    stray = PoseDetections(np.array([[630.0, 630.0, 700.0, 700.0]]), np.array([0.9]), np.zeros((1, 17, 3)))
    canvas_det = PoseDetections.concatenate([*canvas_parts, stray], 17)
    out = unpack_detections(canvas_det, p)
    assert len(out) == 3
    for got, want in zip(out, truth, strict=True):
        assert len(got) == 1
        np.testing.assert_allclose(got.boxes, want.boxes, atol=1e-9)
        np.testing.assert_allclose(got.keypoints, want.keypoints, atol=1e-9)
    assert [len(d) for d in unpack_detections(PoseDetections.empty(17), p)] == [0, 0, 0]


def test_match_people_pairs_by_overlap() -> None:
    a = PoseDetections(np.array([[0, 0, 10, 10], [100, 100, 110, 110.0]]), np.ones(2), np.zeros((2, 17, 3)))
    b = PoseDetections(np.array([[101, 101, 111, 111], [50, 50, 60, 60.0]]), np.ones(2), np.zeros((2, 17, 3)))
    assert match_people(a, b) == [(1, 0)]


@pytest.mark.parametrize(
    ("n_o", "n_p", "expected"),
    [
        (1, 1, [1, 1, 1, 1, 1, 1, 1, 1]),
        (1, 2, [1, 0, 1, 0, 1, 0, 1, 0]),
        (2, 4, [1, 1, 0, 0, 1, 1, 0, 0]),
        (2, 8, [1, 1, 0, 0, 0, 0, 0, 0]),
        (3, 4, [1, 1, 1, 0, 1, 1, 1, 0]),
    ],
)
def test_subsample_schedule(n_o: int, n_p: int, expected: list[int]) -> None:
    s = SubsampleSchedule(n_o, n_p)
    assert [int(s.detects(f)) for f in range(8)] == expected
    assert s.fraction == pytest.approx(n_o / n_p)
    assert sum(s.detects(f) for f in range(8 * n_p)) == 8 * n_o
    assert [s.slot(f) for f in range(n_p)] == [*range(n_o), *([-1] * (n_p - n_o))]


@pytest.mark.parametrize(("n_o", "n_p"), [(0, 4), (5, 4), (-1, 1)])
def test_subsample_schedule_rejects_bad_ratios(n_o: int, n_p: int) -> None:
    with pytest.raises(ConfigError):
        SubsampleSchedule(n_o, n_p)


@pytest.mark.parametrize("seed", range(3))
def test_snapped_rois_contain_the_roi_and_sit_on_the_stride_grid(seed: int) -> None:
    rng = np.random.default_rng(seed)
    lb = letterbox_geometry(1088, 1920, 640, 640)
    for roi in _random_rois(rng, 20):
        s = snap_roi_to_grid(roi, lb.sx, lb.sy, lb.pad_x, lb.pad_y, 32, 1088, 1920)
        assert s.x0 <= roi.x0 and s.y0 <= roi.y0 and s.x1 >= roi.x1 and s.y1 >= roi.y1
        assert s.x0 >= 0 and s.y0 >= 0 and s.x1 <= 1088 and s.y1 <= 1920
        for edge, sc, pad, lo in ((s.x0, lb.sx, lb.pad_x, 0), (s.y0, lb.sy, lb.pad_y, 0)):
            phase = (edge * sc + pad) % 32
            assert edge == lo or phase < 1.0  # just after a grid line (or clipped at the image edge)
        # Packed alone next to nothing, a snapped ROI costs no slack: it lands on a grid line.
        (p,) = plan_aligned_canvases([AlignedRoi(s, lb.sx, lb.sy, lb.pad_x, lb.pad_y)], 640, 640, gap=0)
        if s.x0 > 0:
            assert p.tiles[0].x < 1.0


def test_boxes_cut_by_an_inner_roi_edge_grow_past_it() -> None:
    roi = Roi(100, 200, 600, 1200)
    boxes = np.array(
        [
            [200.0, 400.0, 400.0, 1199.0],  # cut at the ROI's bottom edge (inside the image)
            [250.0, 400.0, 450.0, 1000.0],  # well inside: unchanged
            [0.0, 300.0, 150.0, 900.0],  # outside every ROI's centre test: unchanged
        ]
    )
    out = grow_cut_boxes(boxes, [roi], 1088, 1920, margin=0.1)
    np.testing.assert_allclose(out[0], [200.0, 400.0, 400.0, 1199.0 + 0.5 * 799.0])
    np.testing.assert_allclose(out[1:], boxes[1:])
    # At the image border there is nothing more to see: no growth.
    edge = Roi(0, 0, 1088, 1920)
    np.testing.assert_allclose(grow_cut_boxes(np.array([[0.0, 0.0, 300.0, 1920.0]]), [edge], 1088, 1920, margin=0.1),
                               [[0.0, 0.0, 300.0, 1920.0]])  # fmt: skip


def _cells(cols: int, rows: int, x0: int = 0, y0: int = 0) -> AlignedRoi:
    """A ROI of exactly ``cols x rows`` stride cells at scale 1 and phase 0."""
    return AlignedRoi(Roi(x0, y0, x0 + 32 * cols, y0 + 32 * rows), 1.0, 1.0, 0.0, 0.0)


def test_grid_planner_fills_the_space_beside_tall_tiles() -> None:
    # On a 20 x 20-cell canvas: a 7x12 tile, then 10x9 beside it, leave no room on the 12-high row shelf for
    # the last 7x9 tile, and 12 + 9 rows do not stack (columns fail alike): shelves need 2 canvases. Whole
    # cells placed top-left first fit put the 7x9 tile under the 10x9 one, beside the tall tile.
    items = [_cells(7, 12), _cells(10, 9), _cells(7, 9)]
    packs = plan_aligned_canvases(items, 640, 640, gap=0, stride=32)
    assert len(packs) == 1
    _no_overlap(packs[0])
    assert sorted(t.index for t in packs[0].tiles) == list(range(3))


@pytest.mark.parametrize("seed", range(5))
def test_grid_planner_keeps_phase_and_never_needs_more_canvases(seed: int) -> None:
    rng = np.random.default_rng(seed)
    lb = letterbox_geometry(1088, 1920, 640, 640)
    rois = [snap_roi_to_grid(r, lb.sx, lb.sy, lb.pad_x, lb.pad_y, 32, 1088, 1920) for r in _random_rois(rng, 14)]
    items = [AlignedRoi(r, lb.sx, lb.sy, lb.pad_x, lb.pad_y) for r in rois]
    packs = plan_aligned_canvases(items, 640, 640, gap=0, stride=32)
    area = sum(it.roi.width * it.sx * it.roi.height * it.sy for it in items)
    assert len(packs) >= area / 640**2
    assert sorted(t.index for p in packs for t in p.tiles) == list(range(14))
    for p in packs:
        _no_overlap(p)
        for t in p.tiles:
            px, py = items[t.index].phase
            assert min((t.x - px) % 32, 32 - (t.x - px) % 32) == pytest.approx(0.0, abs=1e-6)
            assert min((t.y - py) % 32, 32 - (t.y - py) % 32) == pytest.approx(0.0, abs=1e-6)


def test_a_box_is_judged_by_the_roi_holding_most_of_it() -> None:
    # Two people side by side with overlapping ROIs; the right one's centre lies in the left ROI too, whose
    # right edge runs through them. They were found in their own ROI, which does not cut them: no growth.
    left, right = Roi(100, 200, 650, 1300), Roi(380, 200, 900, 1300)
    box = np.array([[450.0, 300.0, 750.0, 1200.0]])
    np.testing.assert_allclose(grow_cut_boxes(box, [left, right], 1088, 1920, margin=0.1), box)
    # Cut by its own ROI's bottom edge, it still grows.
    cut = np.array([[450.0, 300.0, 750.0, 1299.0]])
    assert grow_cut_boxes(cut, [left, right], 1088, 1920, margin=0.1)[0, 3] > 1299.0
