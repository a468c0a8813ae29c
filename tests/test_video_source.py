"""Video-file and image-folder replay sources on the Pose2Sim demo video and images."""

from __future__ import annotations

import asyncio
import itertools
from pathlib import Path

import cv2
import numpy as np
import pytest

from mocapd.errors import InputError
from mocapd.io.video_source import ImageFolderSource, VideoFileSource
from mocapd.pipeline.frame_ring import FrameRef
from tests.pose2sim_data import demo_root


@pytest.fixture(scope="module")
def pose2sim_demo() -> Path:
    return demo_root()


def _decode(path: Path, n: int) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    frames: list[np.ndarray] = []
    while len(frames) < n:
        ok, bgr = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    cap.release()
    return frames


async def _collect(source: VideoFileSource | ImageFolderSource, limit: int) -> list[tuple[FrameRef, np.ndarray]]:
    got: list[tuple[FrameRef, np.ndarray]] = []
    done = asyncio.Event()

    def on_frame(ref: FrameRef) -> None:
        image = source.ring.read(ref.seq)
        assert image is not None
        got.append((ref, image))
        if len(got) >= limit:
            done.set()

    task = asyncio.create_task(source.run(on_frame))
    finished = asyncio.create_task(done.wait())
    await asyncio.wait({task, finished}, return_when=asyncio.FIRST_COMPLETED)
    task.cancel()
    finished.cancel()
    await asyncio.gather(task, finished, return_exceptions=True)
    return got[:limit]


def test_video_file_as_fast_as_possible_matches_decoder(pose2sim_demo: Path) -> None:
    path = pose2sim_demo / "Demo_SinglePerson" / "videos" / "cam01.mp4"
    expected = _decode(path, 12)
    source = VideoFileSource("cam01", path, realtime=False, ring_slots=64)
    got = asyncio.run(_collect(source, 12))
    assert len(got) == 12
    for i, (ref, image) in enumerate(got):
        assert ref.frame_id == i and ref.seq == i
        assert ref.device_ns == round(i * 1e9 / source.fps)
        assert np.array_equal(image, expected[i])
    assert all(b[0].host_ns > a[0].host_ns for a, b in itertools.pairwise(got))


def test_video_file_realtime_is_never_early(pose2sim_demo: Path) -> None:
    path = pose2sim_demo / "Demo_SinglePerson" / "videos" / "cam02.mp4"
    source = VideoFileSource("cam02", path, realtime=True, gray=True)
    got = asyncio.run(_collect(source, 6))
    assert got[0][1].shape[2] == 1
    first = got[0][0]
    for ref, _ in got[1:]:
        # Paced on presentation time: a frame is never published before its time has come.
        assert ref.host_ns - first.host_ns >= ref.device_ns - first.device_ns - 2_000_000


def test_image_folder_source(pose2sim_demo: Path, tmp_path: Path) -> None:
    folder = pose2sim_demo / "Demo_SinglePerson" / "calibration" / "intrinsics" / "int_cam01_img"
    source = ImageFolderSource("imgs", folder, fps=50.0, realtime=False, loop=True)
    n = len(source.files)
    got = asyncio.run(_collect(source, n + 2))
    first = cv2.cvtColor(np.asarray(cv2.imread(str(source.files[0])), np.uint8), cv2.COLOR_BGR2RGB)
    assert np.array_equal(got[0][1], first)
    assert [r.frame_id for r, _ in got] == [*range(n), 0, 1]
    # Looping keeps presentation times increasing.
    assert all(b[0].device_ns > a[0].device_ns for a, b in itertools.pairwise(got))
    with pytest.raises(InputError, match="no image"):
        ImageFolderSource("empty", tmp_path)


def test_video_ends() -> None:
    with pytest.raises(InputError, match=r"video /nonexistent\.mp4: no such file"):
        VideoFileSource("x", Path("/nonexistent.mp4"))


def test_unexpected_error_in_the_thread_reaches_the_task(pose2sim_demo: Path) -> None:
    # A bug in a source must not look like a normal end of capture.
    class Broken(VideoFileSource):
        def _grab(self) -> FrameRef | bool | None:
            raise ZeroDivisionError("bug")

    source = Broken("b", pose2sim_demo / "Demo_SinglePerson" / "videos" / "cam01.mp4", realtime=False)

    async def main() -> None:
        await source.run(lambda ref: None)

    with pytest.raises(ZeroDivisionError, match="bug"):
        asyncio.run(main())
