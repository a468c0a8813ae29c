"""The detector stage: frames of a real replay source through a detector in a worker thread, newest frame first
while the detector is busy (sub-sampling counted), detections stamped with the capture time."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from mocapd.core.sorting import Detections2D
from mocapd.io.video_source import ImageFolderSource
from mocapd.pipeline.keypoint_source import DetectorKeypointSource


def _brightest_spot(image: np.ndarray) -> Detections2D:
    """A stand-in detector (the onnxruntime one is issue 6): every keypoint at the brightest pixel, slowly."""
    time.sleep(0.03)
    gray = image if image.ndim == 2 else image[..., 0]
    y, x = np.unravel_index(int(np.argmax(gray)), gray.shape[:2])
    return Detections2D(np.tile([float(x), float(y)], (1, 17, 1)), np.ones((1, 17)))


@pytest.mark.asyncio
async def test_detector_source_subsamples_and_stamps_capture_time(tmp_path: Path) -> None:
    for i in range(30):
        img = np.zeros((48, 64, 3), dtype=np.uint8)
        img[10, 2 * i] = 255
        cv2.imwrite(str(tmp_path / f"{i:03d}.png"), img)
    frames = ImageFolderSource("cam0", tmp_path, fps=100.0)
    got: list[tuple[int, int, Detections2D, int]] = []
    src = DetectorKeypointSource(0, frames, _brightest_spot)
    await src.run(lambda cam, t, d, arrival: got.append((cam, t, d, arrival)))
    assert src.detected == len(got) >= 3
    assert src.skipped > 0  # 100 Hz frames, a 30 ms detector: it keeps up by skipping to the newest frame
    assert src.detected + src.skipped + src.lost <= 30
    # Frames are converted (BGR -> RGB) when the detector takes them, not at capture: skipped frames cost nothing.
    # (+ 1: the detection in flight when the replay ended is dropped, its frame converted.)
    assert src.detected <= frames.ring.conversions <= src.detected + src.lost + 1 < src.captured
    times = [t for _, t, _, _ in got]
    assert times == sorted(times) and len(set(times)) == len(times)
    xs = [d.keypoints[0, 0, 0] for _, _, d, _ in got]
    assert xs == sorted(xs) and all(x % 2 == 0 for x in xs)  # real frames of the folder, in order
    assert all(arrival >= t for _, t, _, arrival in got)
    assert src.status()["kind"] == "detector"
