"""Packed detection for free-running cameras: two real video replays (the Pose2Sim multi-person demo) share one
PackedDetector pass per detection round, each camera's detections stamped with its own frames' capture times. A
pass's results cross to the loop through its mailbox: those of passes done while the loop is busy wake it once."""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import pytest

from mocapd.core.sorting import Detections2D
from mocapd.io.pose2sim_demo import demo_video
from mocapd.io.video_source import VideoFileSource
from mocapd.pipeline.detection_mode import ModeChooser, ModeChooserOptions
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.frame_ring import FrameRef
from mocapd.pipeline.packed_source import MAX_REST_NS, PackedDetectionGroup, PackedKeypointSource, Session
from mocapd.pipeline.packing import detectors_from_config, packed_detector_from_config
from tests.loop_spy import spy_wakeups


@pytest.mark.asyncio
async def test_two_cameras_share_packed_passes_and_keep_their_own_stamps() -> None:
    cams = [VideoFileSource(f"cam0{i}", demo_video("Demo_MultiPerson", f"cam0{i}"), realtime=True, loop=True)
            for i in (1, 2)]  # fmt: skip
    sizes = [(c.ring.shape[1], c.ring.shape[0]) for c in cams]
    executor = ThreadPoolExecutor(1)
    group = PackedDetectionGroup(packed_detector_from_config(DetectorConfig(intra_op_threads=2), sizes), executor)
    sources = [PackedKeypointSource(i, c, group) for i, c in enumerate(cams)]
    got: list[tuple[int, int, Detections2D, int]] = []
    tasks = [asyncio.create_task(s.run(lambda cam, t, d, arrival: got.append((cam, t, d, arrival)))) for s in sources]
    try:
        for _ in range(1200):  # until both cameras were detected 3 times (a minute at most on a starved CPU)
            if all(s.detected >= 3 for s in sources):
                break
            await asyncio.sleep(0.05)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        group.close()
    per_cam = [[g for g in got if g[0] == i] for i in (0, 1)]
    assert all(len(p) >= 3 for p in per_cam), [len(p) for p in per_cam]
    # A pass takes the cameras that share a canvas: never more inferences than camera frames (besides the
    # refresh tiles that open a canvas of their own), and cameras share canvases when their ROIs fit.
    st = group.packer.stats
    # (+ the results a newer pass replaced before their camera took them, and the last pass, whose results may be
    # on their way to the loop when the test stops)
    assert st.canvases <= len(got) + group.replaced + len(group.packer.last_packings) + st.refresh_tiles
    assert group.passes <= len(got) + group.replaced + 1
    for cam, p in enumerate(per_cam):
        stamps = [t for _, t, _, _ in p]
        assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
        assert all(arrival >= t for _, t, _, arrival in p)
        assert sources[cam].detected == len(p)
        assert sources[cam].detected + sources[cam].skipped <= sources[cam].captured
        # Real people in real frames: at least two confident people in this camera's best frame.
        best = max(int((d.confidences.mean(axis=1) > 0.5).sum()) if len(d) else 0 for _, _, d, _ in p)
        assert best >= 2, f"camera {cam}: at most {best} confident people"
        assert all(np.all(np.isfinite(d.keypoints)) for _, _, d, _ in p)
    status = sources[0].status()
    assert status["kind"] == "packed detector" and status["packing"]["passes"] == group.passes
    # The detector's time inside onnxruntime is part of its busy time (the rest is mocapd's own work per pass).
    packing = status["packing"]
    assert 0 < packing["inference_s"] <= packing["detector_busy_s"] + 0.01, packing


@pytest.mark.asyncio
async def test_auto_mode_runs_both_kinds_of_pass_and_reports_its_choice() -> None:
    """``[detector.packing] enabled = "auto"``: the group's worker runs whole-frame passes while every ROI is a
    whole frame, then packed passes once the people are found (two cameras a canvas cost less per frame than one
    whole frame each); both deliver real people stamped in order, and whole-frame passes seed the packed ROIs."""
    cams = [VideoFileSource(f"cam0{i}", demo_video("Demo_MultiPerson", f"cam0{i}"), realtime=True, loop=True)
            for i in (1, 2)]  # fmt: skip
    sizes = [(c.ring.shape[1], c.ring.shape[0]) for c in cams]
    packer = packed_detector_from_config(DetectorConfig(intra_op_threads=2), sizes)
    chooser = ModeChooser(
        ModeChooserOptions(explore_unsettled_s=0.3, explore_after_s=0.5, explore_always_s=1.0), first="whole"
    )
    group = PackedDetectionGroup(packer, ThreadPoolExecutor(1), chooser=chooser)
    sources = [PackedKeypointSource(i, c, group) for i, c in enumerate(cams)]
    got: list[tuple[int, int, Detections2D, int]] = []
    tasks = [asyncio.create_task(s.run(lambda cam, t, d, arrival: got.append((cam, t, d, arrival)))) for s in sources]
    try:
        for _ in range(2400):  # two minutes at most on a starved CPU
            passes = chooser.status()["passes"]
            if min(passes.values()) >= 2 and all(s.detected >= 3 for s in sources):
                break
            await asyncio.sleep(0.05)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        group.close()
    assert group.whole_passes > 0 and group.passes > group.whole_passes, (group.status(), chooser.status())  # both ran
    # people's ROIs, not whole frames (two people far apart may span a camera's width, not its whole frame)
    assert all(r.width * r.height < w * h for rois, (w, h) in zip(packer.rois, sizes, strict=True) for r in rois), (
        packer.rois
    )
    for cam in (0, 1):
        stamps = [t for c, t, _, _ in got if c == cam]
        assert len(stamps) >= 3 and stamps == sorted(stamps) and len(set(stamps)) == len(stamps), (cam, stamps)
    assert max(len(d) for _, _, d, _ in got) >= 2, [len(d) for _, _, d, _ in got]
    st = sources[0].status()["packing"]
    assert st["whole_frame_passes"] == group.whole_passes and st["failed_passes"] == 0
    assert st["mode"]["passes"]["whole"] == group.whole_passes and set(st["mode"]["rates"]) == {"packed", "whole"}
    assert all(v is not None for v in st["mode"]["ns_per_pixel"].values())  # both modes' costs measured


class _Replay:
    """A camera of the group that always has a new frame (the detector far slower than 60 fps): demo frames."""

    def __init__(self, camera: int, frames: list[np.ndarray]) -> None:
        self.camera, self.frames, self.seq = camera, frames, 0

    def has_new_frame(self) -> bool:
        return True

    def take_newest(self) -> tuple[FrameRef, np.ndarray]:
        self.seq += 1
        return FrameRef(f"cam{self.camera}", self.seq, self.seq, self.seq, self.seq), self.frames[self.seq % 2]


@pytest.mark.parametrize("batch", [False, True])
def test_a_batched_detector_passes_over_every_camera_and_a_cpu_one_over_one_canvas(batch: bool) -> None:
    frames = []
    for name in ("cam01", "cam02", "cam03", "cam04"):
        cap = cv2.VideoCapture(str(demo_video("Demo_MultiPerson", name)))
        pair = [cv2.cvtColor(cv2.resize(cap.read()[1], (544, 960)), cv2.COLOR_BGR2RGB) for _ in range(2)]
        frames.append([np.asarray(f, np.uint8) for f in pair])
        cap.release()
    cfg = DetectorConfig(intra_op_threads=2, batch=batch)
    group = PackedDetectionGroup(packed_detector_from_config(cfg, [(544, 960)] * 4), ThreadPoolExecutor(1))
    for cam, f in enumerate(frames):
        group.add(_Replay(cam, f))  # type: ignore[arg-type]  # the group calls has_new_frame and take_newest
    try:
        group._run_pass()  # whole frames in: the ROIs follow
        found = group._run_pass()
    finally:
        group.close()
    assert found is not None and all(len(d) >= 1 for _, d in found.values())
    canvases = len(group.packer.last_packings)
    if batch:  # every camera, their canvases in one inference
        assert sorted(found) == [0, 1, 2, 3] and canvases >= 2
    else:  # one canvas's worth of cameras (these four need more than one)
        assert canvases == 1 and 1 <= len(found) < 4


@pytest.mark.asyncio
async def test_several_sessions_run_passes_at_once_on_disjoint_cameras() -> None:
    """``[detector] workers = 2``: two sessions of one thread each; their passes overlap in time, never on a
    camera, and every camera keeps being detected."""
    frames = []
    for name in ("cam01", "cam02", "cam03", "cam04"):
        cap = cv2.VideoCapture(str(demo_video("Demo_MultiPerson", name)))
        pair = [cv2.cvtColor(cv2.resize(cap.read()[1], (544, 960)), cv2.COLOR_BGR2RGB) for _ in range(2)]
        frames.append([np.asarray(f, np.uint8) for f in pair])
        cap.release()
    cfg = DetectorConfig(intra_op_threads=1)
    sizes = [(544, 960)] * 4
    pairs = [detectors_from_config(cfg, sizes) for _ in range(2)]
    packer = packed_detector_from_config(cfg, sizes)
    group = PackedDetectionGroup(packer, ThreadPoolExecutor(2), sessions=[Session(w, c) for w, c in pairs],
                                 chooser=ModeChooser(first="whole"))  # fmt: skip
    for cam, f in enumerate(frames):
        group.add(_Replay(cam, f))  # type: ignore[arg-type]
    spans: list[tuple[float, float, frozenset[int]]] = []
    run_pass = group._run_pass

    def timed(plan: object = None, worker: int = 0) -> object:
        t0 = time.perf_counter()
        found = run_pass(plan, worker)  # type: ignore[arg-type]
        spans.append((t0, time.perf_counter(), frozenset(found or ())))
        return found

    group._run_pass = timed  # type: ignore[method-assign,assignment]
    group.poke()
    try:
        for _ in range(2400):
            if len(spans) >= 12 and group.in_flight_max >= 2:
                break
            await asyncio.sleep(0.05)
    finally:
        group.close()
    assert group.in_flight_max == 2 and group.failed_passes == 0
    overlapping = [(a, b) for i, a in enumerate(spans) for b in spans[i + 1 :] if a[0] < b[1] and b[0] < a[1]]
    assert overlapping, spans  # two passes in flight at once ...
    assert all(not (a[2] & b[2]) for a, b in overlapping)  # ... never on the same camera
    assert {c for _, _, cams in spans for c in cams} == {0, 1, 2, 3}
    assert group.status()["sessions"] == 2


@pytest.mark.asyncio
async def test_a_detector_at_half_duty_rests_as_long_as_it_detects() -> None:
    """The governor's detector duty (issue 39): at 0.5 each worker rests after every pass as long as the pass took,
    so passes take at most half the time and the rest is left to the tick; /status says the duty and the rest."""
    cams = [VideoFileSource(f"cam0{i}", demo_video("Demo_MultiPerson", f"cam0{i}"), realtime=True, loop=True)
            for i in (1, 2)]  # fmt: skip
    sizes = [(c.ring.shape[1], c.ring.shape[0]) for c in cams]
    group = PackedDetectionGroup(packed_detector_from_config(DetectorConfig(intra_op_threads=1), sizes),
                                 ThreadPoolExecutor(1))  # fmt: skip
    group.duty = 0.5
    group.max_rest_ns = group.starved_ns = 10**12  # the proportion itself (the cap and the floor: own test)
    sources = [PackedKeypointSource(i, c, group) for i, c in enumerate(cams)]
    # Both cameras count as detected just now: a camera never detected counts as starved and its pass rests not
    # at all (the cap and the floor: own test); a first pass over one camera only (whole mode) would then rest 0.
    for cam in group.sources:
        group._detected_ns[cam] = group.clock()
    tasks = [asyncio.create_task(s.run(lambda *_: None)) for s in sources]
    try:
        for _ in range(1200):
            if group.passes >= 4:
                break
            await asyncio.sleep(0.05)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        group.close()
    assert group.passes >= 4
    # Every finished pass was followed by a rest of its own length (measured around the whole pass: at least
    # the detector's busy time of all passes but the one in flight at the stop).
    st = sources[0].status()["packing"]
    assert st["duty"] == 0.5 and st["rested_s"] > 0
    assert group.rests_skipped == 0
    assert group.rested_ns >= 0.9 * group.busy_ns * (group.passes - 1) / group.passes, (group.rested_ns, group.busy_ns)


def test_a_rest_never_ages_the_tracked_people_out() -> None:
    """A pass a starved detector took 2 s for rests at most MAX_REST_NS at any duty, and not at all while a camera
    has had no detection for STARVED_NS (issue 39: 35 % duty rested ~2 s after each 1 s pass, its cameras' tracked
    people aged out and came back as new identities)."""
    cams = [VideoFileSource("cam01", demo_video("Demo_MultiPerson", "cam01"))]
    sizes = [(c.ring.shape[1], c.ring.shape[0]) for c in cams]
    group = PackedDetectionGroup(packed_detector_from_config(DetectorConfig(intra_op_threads=1), sizes),
                                 ThreadPoolExecutor(1))  # fmt: skip
    PackedKeypointSource(0, cams[0], group)
    try:
        group.duty = 0.35
        group._rest(2_000_000_000)  # cam01 never detected: no rest at all
        assert group.rested_ns == 0 and group.rests_skipped == 1
        group._detected_ns[0] = group.clock()
        group._rest(2_000_000_000)
        assert group.rested_ns == MAX_REST_NS
        group.duty = 0.75
        group._rest(300_000_000)
        assert group.rested_ns == MAX_REST_NS + 100_000_000  # a short pass rests its duty's share
    finally:
        group.close()


@pytest.mark.asyncio
async def test_the_results_of_passes_done_while_the_loop_is_busy_wake_it_once() -> None:
    """Each pass's results crossed to the loop with their own ``call_soon_threadsafe`` (the old code: 10 wake-ups
    for 10 passes); through the loop's mailbox the passes done while the loop is busy share one, and they are still
    handed over in order (each camera ends with the newest pass's result, the 9 before it counted as replaced)."""
    group = PackedDetectionGroup(packed_detector_from_config(DetectorConfig(intra_op_threads=1), [(544, 960)] * 2),
                                 ThreadPoolExecutor(1))  # fmt: skip
    for cam in range(2):
        group.add(_Replay(cam, []))  # type: ignore[arg-type]  # always a new frame; the pass below reads none
    passes: list[int] = []
    release = threading.Event()

    def quick_pass(plan: object = None, worker: int = 0) -> dict[int, tuple[FrameRef, Detections2D]] | None:
        n = len(passes) + 1
        passes.append(n)
        if n > 10:  # ten passes, then the worker waits (no result, nothing posted) until the test ends
            release.wait(30)
            return None
        return {cam: (FrameRef(f"cam{cam}", n, n, n, n), Detections2D(np.zeros((1, 17, 2)), np.ones((1, 17))))
                for cam in (0, 1)}  # fmt: skip

    group._run_pass = quick_pass  # type: ignore[method-assign]
    wakeups = spy_wakeups(asyncio.get_running_loop())
    group.poke()
    try:
        deadline = time.monotonic() + 30
        while len(passes) <= 10 and time.monotonic() < deadline:  # the loop is busy here while the passes deliver
            time.sleep(0.001)
        await asyncio.sleep(0.05)
        crossings = [name for name in wakeups if name in ("_deliver", "_drain")]
        results = {cam: group._results[cam][0].seq for cam in (0, 1)}
    finally:
        release.set()
        group.close()
    assert len(passes) == 11 and results == {0: 10, 1: 10} and group.replaced == 18
    assert crossings == ["_drain"], crossings  # the old code: ten "_deliver"


def test_a_paced_detector_rests_until_its_oldest_camera_is_due() -> None:
    """The governor's deepest steps (issue 39): paced, a worker rests after a pass until the camera detected
    longest ago is a pace past its detection, whatever the duty and however long the pass took (at 0.4 of a core the
    duty's rest, a multiple of a throttled pass's wall time, took no CPU away); not at all while a camera has no
    detection yet or is already a pace past it (the starvation guard built in); /status says the pace."""
    cams = [VideoFileSource(f"cam0{i}", demo_video("Demo_MultiPerson", f"cam0{i}")) for i in (1, 2)]
    sizes = [(c.ring.shape[1], c.ring.shape[0]) for c in cams]
    group = PackedDetectionGroup(packed_detector_from_config(DetectorConfig(intra_op_threads=1), sizes),
                                 ThreadPoolExecutor(1))  # fmt: skip
    sources = [PackedKeypointSource(i, c, group) for i, c in enumerate(cams)]
    now = 50_000_000_000
    group.clock = lambda: now
    try:
        group.duty, group.pace_ns = 0.35, 200_000_000
        group._detected_ns[0] = now
        group._rest(2_000_000_000)  # cam02 never detected: no rest at all
        assert group.rested_ns == 0 and group.rests_skipped == 1
        group._detected_ns.update({0: now - 50_000_000, 1: now - 150_000_000})
        group._rest(2_000_000_000)  # a 2 s pass at 35 % duty: the duty would rest MAX_REST_NS
        assert group.rested_ns == 50_000_000  # until cam02, detected 150 ms ago, is 200 ms past it
        group._detected_ns[1] = now - 300_000_000
        group._rest(10_000_000)  # cam02 is past its pace already
        assert group.rested_ns == 50_000_000 and group.rests_skipped == 2
        group.pace_ns = 0  # not paced: the duty as before
        group._detected_ns.update({0: now, 1: now})
        group._rest(2_000_000_000)
        assert group.rested_ns == 50_000_000 + MAX_REST_NS
        group.pace_ns = 200_000_000
        st = sources[0].status()["packing"]
        assert st["pace_s"] == 0.2 and st["tile_ratio"] == 1.0
    finally:
        group.close()
