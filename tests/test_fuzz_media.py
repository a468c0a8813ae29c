"""Hostile input, round two (issue 34), the media doors: pictures and videos a user points mocapd at
(``[[cameras]]`` of ``source = "video"`` and ``"images"``, ``calibrate cameras`` picture folders).

A FIFO among the pictures made ``check-config`` (and ``run``) wait forever in OpenCV's ``imread``; a FIFO, a folder
or a device given as the video was reported as "no such video file". Now each is one line naming the file and what
it is (:mod:`mocapd.io.media_files`). Special files are tried in a child process with a time-out
(:func:`tests.test_fuzz_imports.run_guarded`), so a regression fails instead of hanging CI.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mocapd.errors import DeviceError, InputError
from mocapd.io.board_calibration import Board, detect_in_files
from mocapd.io.media_files import open_video, read_image
from mocapd.io.video_source import ImageFolderSource
from mocapd.sim.camera_hosts import toml_tables, write_ring_calibration
from tests.test_fuzz_imports import FUZZ, alarm, run_guarded


def _picture(width: int = 64, height: int = 48) -> bytes:
    image = np.zeros((height, width, 3), np.uint8)
    image[::8, :, 1] = 255
    ok, data = cv2.imencode(".png", image)
    assert ok
    return bytes(data)


def _config(folder: Path, name: str, camera: dict[str, object]) -> str:
    write_ring_calibration(["cam0"], folder / "calibration.toml")
    path = folder / f"{name}.toml"
    path.write_text(toml_tables({"calibration": {"file": str(folder / "calibration.toml")}},
                                [{"name": "cam0", **camera}]), encoding="utf-8")  # fmt: skip
    return str(path)


def test_special_media_files_are_refused_not_waited_on(tmp_path: Path) -> None:
    """``check-config`` on a rig whose media are special files: one line each (``imread`` of the FIFO waited
    forever before: the 20 s alarm of the child; the video cases said "no such video file")."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    cases: list[tuple[str, dict[str, object], str]] = []
    for kind, target in (("fifo", fifo), ("zero", Path("/dev/zero"))):
        folder = tmp_path / f"pictures-{kind}"
        folder.mkdir()
        (folder / "0001.png").symlink_to(target)
        what = "a FIFO" if kind == "fifo" else "a character device"
        cases.append((f"images-{kind}", {"source": "images", "path": str(folder)}, what))
    cases.append(("video-fifo", {"source": "video", "path": str(fifo)}, "a FIFO"))
    (tmp_path / "zero.mp4").symlink_to("/dev/zero")
    cases.append(("video-zero", {"source": "video", "path": str(tmp_path / "zero.mp4")}, "a character device"))
    (tmp_path / "folder.mp4").mkdir()
    cases.append(("video-folder", {"source": "video", "path": str(tmp_path / "folder.mp4")}, "a directory"))
    argv = [["check-config", _config(tmp_path, name, cam)] for name, cam, _ in cases]
    for (name, _, what), (code, err) in zip(cases, run_guarded(argv), strict=True):
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1, (name, code, err)
        assert "cameras[0]" in lines[0] and what in lines[0], (name, err)


def test_calibrate_cameras_names_a_special_file_among_the_pictures(tmp_path: Path) -> None:
    """A FIFO among a camera's calibration pictures was left out without a word (the board's views silently
    fewer); now it is one line naming it, exit 2."""
    folder = tmp_path / "intrinsics" / "cam0"
    folder.mkdir(parents=True)
    (folder / "0001.png").write_bytes(_picture())
    os.mkfifo(folder / "0002.png")
    argv = ["calibrate", "cameras", "--cols", "9", "--rows", "6", "--square-mm", "25", "--intrinsics",
            str(tmp_path / "intrinsics"), "--output", str(tmp_path / "out.toml")]  # fmt: skip
    [(code, err)] = run_guarded([argv])
    assert code == 2 and len(err.strip().splitlines()) == 1, (code, err)
    assert "0002.png: not a regular file (a FIFO)" in err, err
    assert not (tmp_path / "out.toml").exists()


def test_a_picture_larger_than_a_picture_is_refused_before_it_is_read(tmp_path: Path) -> None:
    big = tmp_path / "cam0" / "big.png"
    big.parent.mkdir()
    with big.open("wb") as fh:  # sparse: 600 MiB on paper, nothing on disk
        fh.write(_picture())
        fh.truncate(600 << 20)
    with pytest.raises(InputError, match=r"calibration image .*big\.png: 600 MiB, larger than the 512 MiB"):
        detect_in_files([big], Board("checkerboard", 9, 6, 0.025))


def test_an_image_folder_source_refuses_a_fifo_among_its_pictures(tmp_path: Path) -> None:
    (tmp_path / "0001.png").write_bytes(_picture())
    os.mkfifo(tmp_path / "0002.png")
    src = ImageFolderSource("cam0", tmp_path, realtime=False)
    src._open()
    assert src._grab() not in (None, False)
    with alarm(20), pytest.raises(DeviceError, match=r"0002\.png: not a regular file \(a FIFO\)"):
        src._grab()


@given(cut=st.integers(0, 400), flips=st.lists(st.tuples(st.integers(0, 399), st.integers(0, 255)), max_size=6))
@settings(FUZZ, max_examples=60)
def test_damaged_pictures_decode_or_are_one_line(tmp_path_factory: pytest.TempPathFactory, cut: int,
                                                 flips: list[tuple[int, int]]) -> None:  # fmt: skip
    data = bytearray(_picture()[:cut])
    for at, value in flips:
        if at < len(data):
            data[at] = value
    path = tmp_path_factory.mktemp("pic") / "x.png"
    path.write_bytes(bytes(data))
    try:
        image = read_image(path)
    except InputError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
    else:
        assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3


@given(cut=st.integers(0, 1 << 14), data=st.binary(max_size=64))
@settings(FUZZ, max_examples=60)
def test_damaged_videos_open_or_are_one_line(tmp_path_factory: pytest.TempPathFactory, cut: int, data: bytes) -> None:
    folder = tmp_path_factory.mktemp("vid")
    good = folder / "good.avi"
    writer = cv2.VideoWriter(str(good), cv2.VideoWriter.fourcc(*"MJPG"), 30.0, (64, 48))
    for k in range(5):
        writer.write(np.full((48, 64, 3), 40 * k, np.uint8))
    writer.release()
    bad = folder / "bad.avi"
    bad.write_bytes(good.read_bytes()[:cut] + data)
    try:
        cap = open_video(bad)
    except InputError as exc:
        assert "\n" not in str(exc) and str(bad) in str(exc)
    else:
        cap.read()  # a damaged frame reads as not ok; it never raises
        cap.release()
