"""Serve a video file as a real GigE Vision camera on loopback (Aravis' fake GigE Vision camera).

Each process serves one camera at one address; clients (mocapd, ``arv-viewer``) open it by IP and receive the
video's frames, one per acquisition period, through the real GVCP/GVSP protocol stack::

    python -m mocapd.sim.fake_gige --video cam01.mp4 --address 127.0.0.1 --serial CAM01 [--max-frames 60]

(:func:`server_command` starts it through :mod:`mocapd.io.lifecycle`, whose stop signals are handled from the
process's first line.)

The client chooses pixel format (Mono8, RGB8, Bayer*8), region and frame rate; frames are converted from the
decoded video (RGB) into that format, cropped to the region, and looped. Frame ``k`` sent (k = 0, 1, ...) is
video frame ``k % n_frames``.

Why ctypes: ``ArvFakeCamera.set_fill_pattern`` through GObject introspection crashes, because its callback is
annotated ``scope call`` and PyGObject frees it on return while the camera keeps calling it. We call the C
function ``arv_fake_camera_set_fill_pattern`` directly with a ``CFUNCTYPE`` object kept alive for the camera's
lifetime. The fake camera sends ``payload`` bytes from the buffer's data pointer, so the callback writes there.

Several cameras need one address each. Never run Aravis discovery on a shared network (it broadcasts on every
interface): run multi-camera set-ups inside a private network namespace, ``unshare -rn``, after
:func:`add_loopback_aliases`.

Prints one JSON line ``{"ready": true, "address": ..., "serial": ..., "n_frames": ..., "width": ..., ...}`` on
stdout when serving, then serves until a stop signal (SIGTERM, SIGINT, SIGHUP).
"""

from __future__ import annotations

import argparse
import ctypes
import json
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.errors import DeviceError, InputError, MocapdError
from mocapd.io import lifecycle
from mocapd.io.aravis_camera import load_aravis
from mocapd.io.pixels import PIXEL_FORMATS, PixelFormat, from_rgb

# GenICam PFNC codes of the formats the fake camera offers.
_PFNC = {
    0x01080001: "Mono8",
    0x02180014: "RGB8",
    0x01080009: "BayerRG8",
    0x0108000B: "BayerBG8",
    0x01080008: "BayerGR8",
    0x0108000A: "BayerGB8",
}

_FILL = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint32)


def load_video_rgb(path: Path, max_frames: int | None = None, size: tuple[int, int] | None = None) -> list[Any]:
    """Decode a video into RGB frames, each shape (h, w, 3) uint8.

    Parameters
    ----------
    path : Path
    max_frames : int or None
        Keep only the first frames (the fake camera loops over them).
    size : (width, height) or None
        Resize every frame (INTER_AREA) to this size.
    """
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputError(f"cannot open video {path}")
    frames: list[Any] = []
    try:
        while max_frames is None or len(frames) < max_frames:
            ok, bgr = cap.read()
            if not ok:
                break
            if size is not None:
                bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
            frames.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    finally:
        cap.release()
    if not frames:
        raise InputError(f"video {path} has no decodable frame")
    return frames


def video_frame_index(elapsed_ns: int, fps: float, n: int, bounce: bool) -> int:
    """The frame of an ``n``-frame video due ``elapsed_ns`` after its start at ``fps``, looped (0 … n-1, 0 …) or,
    with ``bounce``, played forwards then backwards (0 … n-1 … 1, 0 …)."""
    k = int(elapsed_ns * fps // 1_000_000_000)
    if not bounce or n < 2:
        return k % n
    m = k % (2 * n - 2)
    return m if m < n else 2 * n - 2 - m


class _CLib:
    def __init__(self) -> None:
        lib = ctypes.CDLL("libaravis-0.8.so.0")
        lib.arv_fake_camera_set_fill_pattern.argtypes = [ctypes.c_void_p, _FILL, ctypes.c_void_p]
        lib.arv_fake_camera_get_payload.argtypes = [ctypes.c_void_p]
        lib.arv_fake_camera_get_payload.restype = ctypes.c_size_t
        lib.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
        lib.arv_buffer_get_data.restype = ctypes.c_void_p
        for name in ("width", "height", "x", "y"):
            fn = getattr(lib, f"arv_buffer_get_image_{name}")
            fn.argtypes = [ctypes.c_void_p]
            fn.restype = ctypes.c_int
        self.lib = lib
        capsule = ctypes.pythonapi.PyCapsule_GetPointer
        capsule.restype = ctypes.c_void_p
        capsule.argtypes = [ctypes.py_object, ctypes.c_char_p]
        self.capsule = capsule


class FakeGigECamera:
    """A fake GigE Vision camera serving ``frames`` at ``address`` (IPv4 of a local interface).

    Parameters
    ----------
    frames : list of ndarray, each shape (h, w, 3) uint8 RGB
        Frames to serve, looped.
    address : str
        Local IPv4 address to serve on (e.g. 127.0.0.1, or a lo alias inside a network namespace).
    serial : str
        Serial number the camera reports.
    video_fps : float or None
        Real pace: the frame sent at host time t is video frame ``floor((t - t_first) * video_fps) % n`` (the
        video plays at its own rate whatever the acquisition rate, and a send the camera misses skips frames as
        a real camera would). None: the k-th frame sent is video frame ``k % n``.
    epoch_ns : int or None
        ``t_first`` above, on the host's ``time.monotonic_ns()`` clock: cameras given the same epoch show the
        same instant of their (synchronised) videos, as real cameras filming one scene do. None: the first send.
    bounce : bool
        With ``video_fps``: play the video forwards then backwards (0 … n-1 … 1, 0 …) instead of jumping back to
        its start, so people in a short clip never teleport (tracking would lose them at every loop).
    """

    def __init__(
        self,
        frames: list[Any],
        address: str,
        serial: str,
        video_fps: float | None = None,
        epoch_ns: int | None = None,
        bounce: bool = False,
    ) -> None:
        aravis = load_aravis()
        self.frames = frames
        self.video_fps = video_fps
        self.bounce = bounce
        self._t0_ns = epoch_ns
        self.n_sent = 0
        self.errors = 0
        self._cache: dict[tuple[str, int, int, int, int], list[NDArray[np.uint8]]] = {}
        self._c = _CLib()
        self._gv = aravis.GvFakeCamera.new(address, serial)
        if self._gv is None or not self._gv.is_running():
            raise DeviceError(f"cannot serve a fake GigE camera on {address} (is that a local address?)")
        self._fake = self._gv.get_fake_camera()
        self._fake_ptr = int(self._c.capsule(self._fake.__gpointer__, None))
        self._callback = _FILL(self._fill)  # kept alive as long as the camera: C holds only the pointer
        self._c.lib.arv_fake_camera_set_fill_pattern(self._fake_ptr, self._callback, None)

    def prepare(self, fmt_name: str) -> None:
        """Encode the whole frames in ``fmt_name`` now, so the first acquisition does not stall on it."""
        h, w, _ = self.frames[0].shape
        self._encoded(PIXEL_FORMATS[fmt_name], 0, 0, w, h)

    def _encoded(self, fmt: PixelFormat, x: int, y: int, w: int, h: int) -> list[NDArray[np.uint8]]:
        key = (fmt.name, x, y, w, h)
        if key not in self._cache:
            out = []
            for rgb in self.frames:
                canvas = np.zeros((h, w, 3), np.uint8)
                crop = rgb[y : y + h, x : x + w]
                canvas[: crop.shape[0], : crop.shape[1]] = crop
                out.append(from_rgb(canvas, fmt))
            self._cache[key] = out
        return self._cache[key]

    def _fill(self, buffer: int, _data: int, _exposure_us: int, _gain: int, pixel_format: int) -> None:
        # Called by the fake camera's streaming thread for every frame; must never raise into C.
        lib = self._c.lib
        try:
            fmt = PIXEL_FORMATS[_PFNC[pixel_format]]
            w, h = lib.arv_buffer_get_image_width(buffer), lib.arv_buffer_get_image_height(buffer)
            x, y = lib.arv_buffer_get_image_x(buffer), lib.arv_buffer_get_image_y(buffer)
            frame = self._encoded(fmt, x, y, w, h)[self._index()]
            payload = lib.arv_fake_camera_get_payload(self._fake_ptr)
            address = lib.arv_buffer_get_data(buffer, None)
            ctypes.memmove(address, frame.ctypes.data, min(payload, frame.nbytes))
            self.n_sent += 1
        except KeyError:
            self.errors += 1  # a pixel format we cannot produce: the client gets the buffer as it was

    def _index(self) -> int:
        if self.video_fps is None:
            return self.n_sent % len(self.frames)
        now = time.monotonic_ns()
        if self._t0_ns is None:
            self._t0_ns = now
        return video_frame_index(now - self._t0_ns, self.video_fps, len(self.frames), self.bounce)

    def close(self) -> None:
        self._c.lib.arv_fake_camera_set_fill_pattern(self._fake_ptr, _FILL(), None)  # NULL callback
        self._gv = None


def server_command(
    video: Path | str,
    address: str,
    max_frames: int,
    prepare: str,
    serial: str | None = None,
    size: str | None = None,
    video_fps: float | None = None,
    epoch_ns: int | None = None,
    bounce: bool = False,
) -> list[str]:
    """The command line that runs one fake camera server (this module) in its own process."""
    cmd = lifecycle.child_command("mocapd.sim.fake_gige:main", "--video", str(video), "--address", address,
                                  "--max-frames", str(max_frames), "--prepare", prepare)  # fmt: skip
    if serial is not None:
        cmd += ["--serial", serial]
    if size is not None:
        cmd += ["--size", size]
    if video_fps is not None:
        cmd += ["--video-fps", f"{video_fps:g}"]
    if epoch_ns is not None:
        cmd += ["--epoch-ns", str(epoch_ns)]
    if bounce:
        cmd += ["--bounce"]
    return cmd


def add_loopback_aliases(n: int) -> list[str]:
    """Bring lo up and give it the addresses 127.0.0.1 .. 127.0.0.n (inside a private network namespace!).

    Returns
    -------
    list of str
        The ``n`` addresses.
    """
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    addresses = [f"127.0.0.{i + 1}" for i in range(n)]
    for a in addresses[1:]:
        subprocess.run(["ip", "addr", "add", f"{a}/8", "dev", "lo"], check=True)
    return addresses


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--video", type=Path, required=True, help="video file to serve")
    parser.add_argument("--address", default="127.0.0.1", help="local IPv4 address to serve on")
    parser.add_argument("--serial", default="MOCAPD-FAKE", help="serial number reported by the camera")
    parser.add_argument("--max-frames", type=int, default=None, help="serve only the first N frames (looped)")
    parser.add_argument("--size", default=None, help="resize frames to WIDTHxHEIGHT")
    parser.add_argument("--prepare", default="RGB8", help="pixel format to pre-encode the full frames in")
    parser.add_argument(
        "--video-fps", type=float, default=None, help="real pace: send the video frame due at the emission time"
    )
    parser.add_argument("--epoch-ns", type=int, default=None, help="time.monotonic_ns() of video frame 0")
    parser.add_argument("--bounce", action="store_true", help="with --video-fps: play forwards then backwards")
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x")) if args.size else None
    try:
        frames = load_video_rgb(args.video, args.max_frames, size)  # type: ignore[arg-type]
        camera = FakeGigECamera(frames, args.address, args.serial, args.video_fps, args.epoch_ns, args.bounce)
    except MocapdError as exc:  # no Aravis, a video that does not decode: the cause, one line (the parent shows it)
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 2
    camera.prepare(args.prepare)
    stop = threading.Event()
    h, w, _ = frames[0].shape
    print(
        json.dumps(
            {
                "ready": True,
                "address": args.address,
                "serial": args.serial,
                "n_frames": len(frames),
                "width": w,
                "height": h,
            }
        ),
        flush=True,
    )
    with lifecycle.on_stop(lambda _signum: stop.set()):
        stop.wait()
    camera.close()
    print(json.dumps({"stopped": True, "frames_sent": camera.n_sent, "errors": camera.errors}), flush=True)
    return 0


if __name__ == "__main__":
    lifecycle.child_main(["mocapd.sim.fake_gige:main", *sys.argv[1:]])
