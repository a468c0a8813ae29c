"""Hostile input, round two (issue 34), the media doors: pictures and videos a user points mocapd at
(``[[cameras]]`` of ``source = "video"`` and ``"images"``, ``calibrate cameras`` picture folders).

A FIFO among the pictures made ``check-config`` (and ``run``) wait forever in OpenCV's ``imread``; a FIFO, a folder
or a device given as the video was reported as "no such video file". Now each is one line naming the file and what
it is (:mod:`mocapd.io.media_files`). Special files are tried in a child process with a time-out
(:func:`tests.test_fuzz_imports.run_guarded`), so a regression fails instead of hanging CI.
"""

from __future__ import annotations

import os
import signal
import socket
import struct
import subprocess
import sys
import zlib
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
from tests.test_fuzz_imports import FUZZ, REPO, alarm, run_guarded


def _picture(width: int = 64, height: int = 48) -> bytes:
    image = np.zeros((height, width, 3), np.uint8)
    image[::8, :, 1] = 255
    ok, data = cv2.imencode(".png", image)
    assert ok
    return bytes(data)


def _bomb(width: int = 32767, height: int = 32767) -> bytes:
    """A PNG of a few kilobytes whose header declares ``width`` x ``height`` gray pixels (its data: a few rows)."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    rows = zlib.compress(bytes(8 * (width + 1)))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", rows) + chunk(b"IEND", b"")


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


def test_a_decompression_bomb_is_refused_before_it_is_decoded(tmp_path: Path) -> None:
    """Issue 45: a small PNG declaring 32767x32767 pixels as the second picture of an ``images`` camera: check-config
    said ok (it decoded the first picture only), ``run`` then decoded it (19 GB peak RSS); ``calibrate cameras`` on
    it used 9 GB, deaf to SIGINT. Now its header is read first: one line each, exit 2, nothing decoded (the child has
    2 GiB of address space, which the 3 GiB decode would not fit)."""
    assert len(_bomb()) < 64 << 10
    for name in ("good", "images"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "0001.png").write_bytes(_picture(1920, 1080))  # the calibration's size
        (tmp_path / name / "0002.png").write_bytes(_picture(1920, 1080) if name == "good" else _bomb())
    write_ring_calibration(["cam0", "cam1"], tmp_path / "calibration.toml")
    config = tmp_path / "bomb.toml"
    config.write_text(toml_tables({"calibration": {"file": str(tmp_path / "calibration.toml")}},
                                  [{"name": f"cam{i}", "source": "images", "path": str(tmp_path / name)}
                                   for i, name in enumerate(("good", "images"))]), encoding="utf-8")  # fmt: skip
    calib = tmp_path / "intrinsics" / "cam0"
    calib.mkdir(parents=True)
    (calib / "0001.png").write_bytes(_bomb())
    argv = [
        ["check-config", str(config)],
        ["calibrate", "cameras", "--cols", "9", "--rows", "6", "--square-mm", "25", "--intrinsics",
         str(tmp_path / "intrinsics"), "--output", str(tmp_path / "out.toml")],
    ]  # fmt: skip
    for (code, err), name in zip(run_guarded(argv), ("images/0002.png", "cam0/0001.png"), strict=True):
        assert code == 2 and len(err.strip().splitlines()) == 1, (code, err)
        assert f"{name}: declares more than" in err and "(not decoded)" in err, err


def test_pictures_over_the_pixel_bound_or_unlike_the_first_are_not_decoded(tmp_path: Path) -> None:
    """Under Pillow's own bound but over ours (67 Mpx): refused by its header (the old code decoded 243 MB); an image
    folder's picture of another size than the first is refused by its header too (it was decoded, then refused)."""
    big = tmp_path / "big.png"
    big.write_bytes(_bomb(9000, 9000))
    with pytest.raises(InputError, match=r"big\.png: declares 9000x9000 pixels, more than the 67,108,864"):
        read_image(big)
    with pytest.raises(InputError, match=r"big\.png: declares 9000x9000 pixels, more than"):
        detect_in_files([big], Board("checkerboard", 9, 6, 0.025))
    folder = tmp_path / "folder"
    folder.mkdir()
    (folder / "0001.png").write_bytes(_picture(64, 48))
    (folder / "0002.png").write_bytes(_bomb(640, 480))
    src = ImageFolderSource("cam0", folder, realtime=False)
    src._open()
    assert src._grab() not in (None, False)
    with pytest.raises(DeviceError, match=r"0002\.png: declares 640x480 pixels, not 64x48 like the first"):
        src._grab()


def test_calibrate_cameras_stops_on_a_signal_inside_a_long_board_search(tmp_path: Path) -> None:
    """``calibrate cameras`` ignored SIGINT and SIGTERM while OpenCV searched a cluttered picture for the board (one
    C call of minutes: 40 s for 1024x1024 pixels of noise here). Now the search runs in a worker and the command
    ends on the signal, exit 128 + the signal, nothing written."""
    folder = tmp_path / "intrinsics" / "cam0"
    folder.mkdir(parents=True)
    noise = np.random.default_rng(45).integers(0, 256, (2048, 2048), np.uint8)
    assert cv2.imwrite(str(folder / "0001.png"), noise)
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify.sock"))
    notify.settimeout(120)
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify.sock")}
    argv = [sys.executable, "-m", "mocapd", "calibrate", "cameras", "--cols", "9", "--rows", "6", "--square-mm",
            "25", "--intrinsics", str(tmp_path / "intrinsics"), "--output", str(tmp_path / "out.toml")]  # fmt: skip
    proc = subprocess.Popen(argv, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with notify:  # the old code never said its phase: the signal then came after 120 s of waiting
            while "calibrating" not in notify.recv(4096).decode():
                pass
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)  # the board search of 2048x2048 pixels of noise takes minutes
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + signal.SIGINT, err
    assert "SIGINT while calibrating" in err and "Traceback" not in err, err
    assert not (tmp_path / "out.toml").exists()
