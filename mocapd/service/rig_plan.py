"""The rig a config describes, checked without touching a device: what ``mocapd check-config`` says, and what
``mocapd run`` checks before it builds the rig (:mod:`mocapd.service.rig`).

:func:`plan_rig` reads the calibration and the files the cameras replay and checks the rig against them: at least
one camera or one IMU source (a rig of IMUs alone, an Xsens suit or SlimeVR trackers, has no cameras, no
calibration file and no detector); every camera in the calibration file; the image size each camera will deliver
(an Aravis ``region``, a webcam's ``width``/``height``, a video's or an image folder's first frame) equal to its
calibration's; readable videos and image folders. Each problem is one line naming the key and its value.

A module of its own, apart from the rig's builder, so that checking a config imports no detector, scheduler or
daemon (onnxruntime, SciPy, the solver's NumBa kernels: seconds of CPU at every ``mocapd check-config``); the
readers a rig needs (OpenCV for a video, the calibration files, the synthetic ring) are imported where it needs them.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from mocapd.errors import CalibrationError, ConfigError, InputError
from mocapd.service.config import Config
from mocapd.service.config.cameras import (
    AravisCamera,
    CameraConfig,
    ImagesCamera,
    SyntheticCamera,
    UvcCamera,
    VideoCamera,
)

if TYPE_CHECKING:
    from mocapd.core.camera import Camera
    from mocapd.core.skeleton import Skeleton

NO_RIG = (
    "no cameras and no IMU source: add [[cameras]] tables or an IMU source ([imu] ports, [imu.slimevr] enabled, "
    "[imu.bridge] enabled); `mocapd devices` prints them for what is plugged in; or try `mocapd demo` "
    "(`mocapd demo --imu-only`: a simulated suit alone)"
)


@dataclass(frozen=True)
class RigPlan:
    """The rig as checked: every camera calibrated at the size it will deliver, in ``[[cameras]]`` order."""

    cameras: list[Camera]
    synthetic: bool


def plan_rig(config: Config) -> RigPlan:
    """Check the rig of ``config`` against its calibration and files (no device is opened).

    Raises
    ------
    ConfigError
        One line per rule broken, naming the key and its value.
    """
    cams = config.cameras
    if not cams:
        if not config.imu.sources():
            raise ConfigError(NO_RIG)
        config.daemon.check_offsets([])  # daemon.offsets.cameras must be empty
        return RigPlan([], synthetic=False)  # an IMU-only rig: a suit (Xsens, SlimeVR, bridge) solved alone
    names = [c.name for c in cams]
    config.daemon.check_offsets(names)  # daemon.offsets.cameras must name cameras of the rig
    if all(isinstance(c, SyntheticCamera) for c in cams):
        if config.calibration.file:
            raise ConfigError(
                f"calibration.file = {config.calibration.file!r}: a synthetic rig is calibrated by its simulation"
            )
        from mocapd.core.synthetic import named_ring_rig

        return RigPlan(named_ring_rig(names), synthetic=True)
    calibrated = _calibration(config)
    problems: list[str] = []
    cameras: list[Camera] = []
    for i, cam in enumerate(cams):
        where = f"cameras[{i}]"
        found = calibrated.get(cam.name)
        if found is None:
            problems.append(
                f"{where}.name = {cam.name!r}: not in the calibration {config.calibration.file} "
                f"(it has {', '.join(sorted(calibrated)) or 'no camera'})"
            )
            continue
        if isinstance(cam, AravisCamera) and cam.interface and cam.interface not in _interfaces():
            problems.append(
                f"{where}.interface = {cam.interface!r}: no such network interface on this machine "
                f"(it has {', '.join(sorted(_interfaces()))})"
            )
            continue
        try:
            size = expected_size(cam)
        except (ConfigError, InputError) as exc:
            problems.append(f"{where}: {exc}")
            continue
        if size is not None and size != (found.width, found.height):
            problems.append(
                f"{where} ({cam.name}) delivers {size[0]}x{size[1]} images, but the calibration has it at "
                f"{found.width}x{found.height}"
            )
        cameras.append(found)
    if problems:
        raise ConfigError("\n".join(problems))
    return RigPlan(cameras, synthetic=False)


def _interfaces() -> set[str]:
    """The network interfaces of this machine (names only; nothing is sent)."""
    return {name for _, name in socket.if_nameindex()}


def _calibration(config: Config) -> dict[str, Camera]:
    path = config.calibration.file
    if not path:
        raise ConfigError("calibration.file is not set: real cameras need their calibration (docs/cameras.md)")
    from mocapd.io.calibration_files import core_cameras, read_any

    world_up = None if config.calibration.world_up == "auto" else config.calibration.world_up
    try:
        cameras = core_cameras(read_any(Path(path), world_up=world_up))
    except (OSError, CalibrationError, ValueError) as exc:
        raise ConfigError(f"calibration.file = {path!r}: {exc}") from exc
    return {c.name: c for c in cameras}


def expected_size(cam: CameraConfig) -> tuple[int, int] | None:
    """(width, height) the camera will deliver, when the config or its files say (None: known once opened)."""
    if isinstance(cam, AravisCamera):
        return (cam.region[2], cam.region[3]) if cam.region is not None else None
    if isinstance(cam, UvcCamera):
        return (cam.width, cam.height) if cam.width is not None and cam.height is not None else None
    if isinstance(cam, VideoCamera):
        return _video_size(cam.path)
    if isinstance(cam, ImagesCamera):
        return _images_size(cam.path)
    return None


def _video_size(path: str) -> tuple[int, int]:
    from mocapd.io.media_files import open_video

    cap = open_video(path, "video (path)")  # a FIFO, a device, a folder: one line, not a wait (issue 34)
    try:
        ok, frame = cap.read()
    finally:
        cap.release()
    if not ok or frame is None:
        raise InputError(f"path = {path!r}: cannot decode a frame (not a video OpenCV/FFmpeg reads?)")
    return int(frame.shape[1]), int(frame.shape[0])


def _images_size(path: str) -> tuple[int, int]:
    from mocapd.io.media_files import check_declared_size, picture_size, read_image
    from mocapd.io.video_source import IMAGE_SUFFIXES

    folder = Path(path)
    if not folder.is_dir():
        raise InputError(f"path = {path!r}: no such folder")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise InputError(f"path = {path!r}: holds no image ({', '.join(IMAGE_SUFFIXES)})")
    image = read_image(files[0], "image (path)")
    size = int(image.shape[1]), int(image.shape[0])
    # Every other picture's header, as the source checks each before decoding it: a decompression bomb, a FIFO or a
    # picture of another size further down the folder is said now, not when `run` reaches it (issue 45).
    for file in files[1:]:
        check_declared_size(picture_size(file, "image (path)"), file, "image (path)", size=size)
    return size


def rig_skeleton(config: Config) -> Skeleton:
    """The skeleton every person starts with (until body sizing from the cameras gives each their own), and the one
    a suit alone is solved on: ``[imu.body]`` (a height, 1.75 m by default, and any segment lengths given)."""
    return config.imu.body.spec().skeleton()
