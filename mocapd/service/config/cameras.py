"""``[[cameras]]``, ``[calibration]`` and ``[synthetic]``: what the daemon captures with.

Each ``[[cameras]]`` entry has a ``name`` and a ``source`` kind with that kind's own settings, flat in the same
table::

    [[cameras]]
    name = "cam1"
    source = "aravis"            # GigE Vision / USB3 Vision through Aravis
    address = "192.168.10.11"
    pixel_format = "BayerRG8"
    frame_rate = 60.0

Kinds: ``aravis`` (:class:`AravisCamera`), ``uvc`` (USB webcams through OpenCV, :class:`UvcCamera`), ``video``
and ``images`` (replaying footage through the live pipeline), ``synthetic`` (the simulated rig of
``[synthetic]``: people of recorded motion in a ring of cameras, their detector output simulated).

This module checks what can be checked from the file alone (types, ranges, one way of opening each camera, unique
names). What needs the file system or the calibration (a camera missing from the calibration, an image size that
disagrees with it, an unreadable video) is checked by :mod:`mocapd.service.rig_plan`, which ``mocapd check-config``
and ``mocapd run`` both call.
"""

from __future__ import annotations

import functools
import math
import re
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import AfterValidator, Field, PlainValidator, model_validator

from mocapd.errors import ConfigError
from mocapd.service.config.schema import MAX_TEXT, PathStr, Section, Seq, Text, validate

if TYPE_CHECKING:  # the watch's module loads the cameras' model (NumBa): imported for a default or its options
    from mocapd.core.camera_watch import WatchOptions


@functools.cache
def _watch() -> WatchOptions:
    from mocapd.core.camera_watch import WatchOptions

    return WatchOptions()


_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,32}$")


def _feature_value(value: object) -> bool | int | float | str:
    ok = (
        isinstance(value, bool)
        or (isinstance(value, int) and -(2**63) <= value < 2**63)  # GenICam integers are 64-bit
        or (isinstance(value, float) and math.isfinite(value))
        or (isinstance(value, str) and len(value) <= MAX_TEXT and "\x00" not in value)
    )
    if not ok:
        raise ValueError(
            "a GenICam feature value must be true/false, a 64-bit integer, a finite number or a string of at most "
            f"{MAX_TEXT} characters"
        )
    return value  # type: ignore[return-value]


def _name(value: str) -> str:
    if not _NAME.match(value):
        raise ValueError("must be 1 to 32 letters, digits, '_', '.' or '-'")
    return value


#: GenICam feature values settable by name (``[cameras.features]``)
FeatureValue = Annotated[bool | int | float | str, PlainValidator(_feature_value)]
Name = Annotated[str, AfterValidator(_name)]


class _Camera(Section):
    name: Name
    """mocapd's name for the camera: the calibration's name for it, and the key of daemon.offsets.cameras."""


class _Captured(_Camera):
    """A camera whose frames mocapd captures (every kind but the simulated one)."""

    ring_slots: int = Field(8, ge=2, le=256)
    """Frames kept in the camera's ring buffer."""


class AravisCamera(_Captured):
    """A GigE Vision or USB3 Vision camera opened through Aravis."""

    source: Literal["aravis"]
    lost_after_s: float = Field(3.0, gt=0.0, le=60.0)
    """A camera that delivers nothing for this long is declared lost and reopened with back-off (s)."""
    address: Text = ""
    """IPv4 address of a GigE Vision camera: opened directly, no discovery broadcast."""
    serial: Text = ""
    """Serial number: found by discovery (USB3 Vision; GigE Vision only on ``interface``)."""
    device_id: Text = ""
    """Aravis device id as ``mocapd devices`` or ``arv-tool-0.8`` lists it: found by discovery."""
    interface: Text = ""
    """Network interface GigE Vision discovery may broadcast on (``serial``/``device_id`` of a GigE camera);
    "" = no GigE discovery at all (USB3 Vision cameras need none)."""
    pixel_format: Literal["Mono8", "RGB8", "BayerRG8", "BayerBG8", "BayerGR8", "BayerGB8"] = "Mono8"
    """Mono8, RGB8, BayerRG8, BayerBG8, BayerGR8 or BayerGB8 (Bayer is demosaiced by mocapd)."""
    frame_rate: float | None = Field(None, gt=0.0, le=1000.0)
    exposure_us: float | None = Field(None, gt=0.0, le=10_000_000.0)
    gain_db: float | None = Field(None, ge=-50.0, le=100.0)
    region: Annotated[Seq[Annotated[int, Field(ge=0, le=65535)]], Field(min_length=4, max_length=4)] | None = None
    """[x, y, width, height] in pixels (after binning); unset keeps the camera's."""
    binning: Annotated[Seq[Annotated[int, Field(ge=1, le=16)]], Field(min_length=2, max_length=2)] | None = None
    """[horizontal, vertical]."""
    packet_size: int | None = Field(None, ge=0, le=16_384)
    """GigE Vision stream packet size in bytes (0 = negotiate; jumbo frames 8192/9000)."""
    packet_delay_ns: int | None = Field(None, ge=0, le=1_000_000_000)
    """GigE Vision inter-packet delay in ns (spreads the bursts of several cameras on one link)."""
    trigger: Text = ""
    """Hardware/software trigger source (Line0, Line1, Software...); "" = free-running."""
    ptp: bool = False
    """Enable IEEE 1588 PTP on the camera (GevIEEE1588 / PtpEnable) and stamp frames with its clock."""
    features: dict[Text, FeatureValue] = Field(default_factory=dict, max_length=256)
    """Any other GenICam feature by name, set after the ones above: {ExposureAuto = "Off", ...}."""
    n_buffers: int = Field(8, ge=2, le=256)
    socket_frames: int = Field(4, ge=1, le=64)
    packet_timeout_ms: float = Field(20.0, gt=0.0, le=10_000.0)
    frame_retention_ms: float = Field(100.0, gt=0.0, le=10_000.0)

    @model_validator(mode="after")
    def _one_way_to_open(self) -> AravisCamera:
        chosen = [k for k in ("address", "serial", "device_id") if getattr(self, k)]
        if len(chosen) != 1:
            raise ValueError(f"set exactly one of address, serial, device_id (got {chosen or 'none'})")
        if self.region is not None and min(self.region[2:]) < 1:
            raise ValueError(f"region = {list(self.region)}: must be [x, y, width, height] with width, height >= 1")
        if self.packet_timeout_ms > self.frame_retention_ms:
            raise ValueError("packet_timeout_ms must be <= frame_retention_ms")
        return self


class UvcCamera(_Captured):
    """A USB webcam (UVC) through OpenCV."""

    source: Literal["uvc"]
    device: Annotated[int, Field(ge=0, le=255)] | PathStr
    """Device index (0 = /dev/video0) or a path (/dev/video2, /dev/v4l/by-id/...)."""
    width: int | None = Field(None, ge=16, le=16_384)
    height: int | None = Field(None, ge=16, le=16_384)
    fps: float | None = Field(None, gt=0.0, le=1000.0)
    fourcc: Text = ""
    """Pixel format the camera sends, 4 characters: MJPG (most webcams above 640x480 at 30 fps), YUYV ...;
    "" = the driver's default."""

    @model_validator(mode="after")
    def _check(self) -> UvcCamera:
        if isinstance(self.device, int) and self.device < 0:
            raise ValueError(f"device = {self.device}: an index must be >= 0")
        if isinstance(self.device, str) and not self.device:
            raise ValueError('device = "": give an index or a path')
        if self.fourcc and len(self.fourcc) != 4:
            raise ValueError(f"fourcc = {self.fourcc!r}: must be 4 characters (MJPG, YUYV, ...)")
        if (self.width is None) != (self.height is None):
            raise ValueError("set width and height together")
        return self


class VideoCamera(_Captured):
    """A video file replayed through the live pipeline at its own frame rate."""

    source: Literal["video"]
    path: PathStr
    loop: bool = True
    """Start again at the end (a daemon keeps running); false: the camera ends with the file."""


class ImagesCamera(_Captured):
    """A folder of images (sorted by name) replayed as a camera."""

    source: Literal["images"]
    path: PathStr
    fps: float = Field(30.0, gt=0.0, le=1000.0)
    loop: bool = True


class SyntheticCamera(_Camera):
    """A camera of the simulated rig (``[synthetic]``): its detector output computed from recorded motion."""

    source: Literal["synthetic"]


class ZenohCamera(_Camera):
    """A camera of a camera host (``mocapd detect-host``): its detections arrive over Zenoh ([zenoh]) on
    ``mocapd/<rig>/<name>/detections``. Calibrated like any camera."""

    source: Literal["zenoh"]
    host: Name
    """The camera host's name ([zenoh] host of its ``mocapd detect-host``): whose clock its times are on."""


CameraConfig = AravisCamera | UvcCamera | VideoCamera | ImagesCamera | SyntheticCamera | ZenohCamera
CAMERA_KINDS: dict[str, type[_Camera]] = {
    "aravis": AravisCamera,
    "uvc": UvcCamera,
    "video": VideoCamera,
    "images": ImagesCamera,
    "synthetic": SyntheticCamera,
    "zenoh": ZenohCamera,
}


class CameraWatchConfig(Section):
    """``[calibration.watch]``: the bumped-camera watch (:mod:`mocapd.core.camera_watch`, issue 43)."""

    ordered = (("window_s", "<", "baseline_s"),)

    enabled: bool = True
    rate_hz: float = Field(default_factory=lambda: _watch().rate_hz, gt=0.0, le=240.0)
    screen_hz: float = Field(default_factory=lambda: _watch().screen_hz, gt=0.0, le=240.0)
    window_s: float = Field(default_factory=lambda: _watch().window_s, gt=0.0, le=60.0)
    baseline_s: float = Field(default_factory=lambda: _watch().baseline_s, gt=0.0, le=3600.0)
    min_baseline_s: float = Field(default_factory=lambda: _watch().min_baseline_s, ge=0.0, le=3600.0)
    hold_s: float = Field(default_factory=lambda: _watch().hold_s, gt=0.0, le=60.0)
    margin_px: float = Field(default_factory=lambda: _watch().margin_px, ge=0.0, le=1000.0)
    ratio: float = Field(default_factory=lambda: _watch().ratio, ge=0.0, le=10.0)
    others_ratio: float = Field(default_factory=lambda: _watch().others_ratio, gt=0.0, le=1.0)
    tie_ratio: float = Field(default_factory=lambda: _watch().tie_ratio, gt=0.0, le=1.0)
    min_confidence: float = Field(default_factory=lambda: _watch().min_confidence, ge=0.0, le=1.0)
    min_keypoints: int = Field(default_factory=lambda: _watch().min_keypoints, ge=3, le=1000)
    down_weight: float = Field(default_factory=lambda: _watch().down_weight, ge=0.0, le=1.0)
    reestimate_points: int = Field(default_factory=lambda: _watch().reestimate_points, ge=0, le=1_000_000)
    apply: bool = Field(default_factory=lambda: _watch().apply)
    max_turn_deg: float = Field(default_factory=lambda: _watch().max_turn_deg, gt=0.0, le=180.0)

    def options(self) -> WatchOptions:
        from mocapd.core.camera_watch import WatchOptions

        return self.build(WatchOptions)


class CalibrationConfig(Section):
    """``[calibration]``: where the cameras' intrinsics and extrinsics come from."""

    file: PathStr = ""
    """A calibration in any format ``mocapd calibrate convert`` reads (mocapd TOML, Pose2Sim TOML, Qualisys
    .qca.txt, OpenCV YAML); every camera of [[cameras]] must be in it under its name, at the image size it
    delivers. "" = none (only a synthetic rig needs none)."""
    world_up: Literal["auto", "y", "z"] = "auto"
    """The file's world up axis: auto = the format's (Z for Qualisys/Pose2Sim, Y for mocapd/OpenCV)."""
    save_to: PathStr = ""
    """Where ``POST /calibration/save`` (``mocapd calibrate save``) writes the cameras the daemon runs with, as
    mocapd's calibration TOML (a .toml name; the old file backed up beside it). "" = the calibration file."""
    watch: CameraWatchConfig = Field(default_factory=CameraWatchConfig)
    """The bumped-camera watch: per camera, the people's reprojection residuals against the other cameras."""


class SyntheticConfig(Section):
    """``[synthetic]``: the simulated rig that ``source = "synthetic"`` cameras belong to."""

    ordered = (("suits", "<=", "people"),)

    people: int = Field(2, ge=1, le=4)
    suits: int = Field(1, ge=0, le=4)
    """How many of the people (the first ones) wear 13 simulated Xsens IMUs on pseudo-terminals."""
    camera_rate_hz: float = Field(30.0, ge=1.0, le=240.0)
    detection_delay_s: float = Field(0.05, ge=0.0, le=1.0)
    noise_px: float = Field(1.0, ge=0.0, le=50.0)
    imu_rate_hz: int = Field(100, ge=60, le=120)
    seed: int = Field(0, ge=0, le=2**31)
    motion: Literal["recorded", "procedural"] = "recorded"


def parse_cameras(value: object) -> tuple[CameraConfig, ...]:
    """The ``[[cameras]]`` array: each entry validated against its ``source`` kind; names unique; a synthetic
    camera only beside other synthetic cameras."""
    if not isinstance(value, list):
        raise ConfigError(f"cameras must be an array of tables ([[cameras]]), got {value!r}")
    cameras: list[CameraConfig] = []
    for i, entry in enumerate(value):
        where = f"cameras[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where} must be a table, got {entry!r}")
        kind = entry.get("source")
        model = CAMERA_KINDS.get(kind) if isinstance(kind, str) else None
        if model is None:
            allowed = ", ".join(CAMERA_KINDS)
            raise ConfigError(f"{where}.source = {kind!r}: allowed: {allowed}")
        cameras.append(validate(model, entry, where))  # type: ignore[arg-type]
    seen: dict[str, int] = {}
    for i, cam in enumerate(cameras):
        if cam.name in seen:
            raise ConfigError(f"cameras[{i}].name = {cam.name!r}: already the name of cameras[{seen[cam.name]}]")
        seen[cam.name] = i
    kinds = {c.source for c in cameras}
    if "synthetic" in kinds and len(kinds) > 1:
        raise ConfigError(
            f"cameras: a synthetic camera cannot be mixed with real ones (sources {sorted(kinds)}); "
            "the simulated rig has its own calibration"
        )
    return tuple(cameras)


def describe(camera: CameraConfig) -> str:
    """How a camera is opened, for messages: ``aravis 192.168.10.11``, ``uvc /dev/video0``."""
    how: Any
    if isinstance(camera, AravisCamera):
        how = camera.address or camera.serial or camera.device_id
    elif isinstance(camera, UvcCamera):
        how = camera.device
    elif isinstance(camera, VideoCamera | ImagesCamera):
        how = camera.path
    elif isinstance(camera, ZenohCamera):
        how = f"from host {camera.host}"
    else:
        how = "simulated"
    return f"{camera.source} {how}"
