"""Capture of GigE Vision / USB3 Vision cameras through Aravis 0.8 (PyGObject).

One :class:`AravisSource` per camera. Its capture thread blocks in ``ArvStream.timeout_pop_buffer`` (which
releases the GIL), views the buffer's memory through ctypes without copying (a numpy view made once per buffer of
the pool, instead of ``get_data()``'s copy to ``bytes``), copies it once into the camera's
:class:`~mocapd.pipeline.frame_ring.FrameRing` slot, pushes the buffer back to the pool and hands the frame
reference to asyncio. A Bayer frame is copied raw and demosaiced only if something reads it
(:func:`mocapd.io.pixels.capture_ring`).

Opening
    * by IP address (``address``): ``ArvGvDevice`` is created directly between the host interface address that
      routes to the camera and the camera's address. No discovery broadcast is sent. Use this on shared networks.
    * by serial number or Aravis device id (``serial`` / ``device_id``) of a GigE Vision camera on a named network
      ``interface``: mocapd's own discovery (:mod:`mocapd.io.gige_discovery`) broadcasts on that interface only,
      then the camera is opened by the address it reported;
    * by serial number or Aravis device id without an ``interface``: a USB3 Vision camera, looked up by Aravis
      with its GigE Vision interface disabled. Aravis' GigE discovery broadcasts on every interface of the host
      (0.8.26 cannot restrict it), so mocapd never lets it run (:func:`aravis_without_gige_discovery`).

Disappearance
    A camera is declared lost when the GigE heartbeat reports ``control-lost`` or when a free-running camera sends
    nothing for ``lost_after_s``. The source then raises :class:`~mocapd.errors.DeviceError` in its thread and
    :meth:`~mocapd.io.frame_source.ThreadedSource.run` reopens it with back-off.
"""

from __future__ import annotations

import ctypes
import logging
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.errors import ConfigError, DeviceError
from mocapd.io.frame_source import ThreadedSource
from mocapd.io.gige_discovery import find_camera
from mocapd.io.pixels import PixelFormat, capture_ring, pixel_format, store_raw
from mocapd.io.silence import SilenceClock
from mocapd.pipeline.frame_ring import FrameRef, FrameRing

log = logging.getLogger(__name__)


def load_aravis() -> Any:
    """Import Aravis 0.8 through GObject introspection.

    Raises
    ------
    DeviceError
        If PyGObject or the Aravis typelib is missing (run ``make setup``).
    """
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise DeviceError(
            f"Aravis 0.8 is not available ({exc}); run `make setup` (installs gir1.2-aravis-0.8 and PyGObject)"
        ) from exc
    return Aravis


def _warm_up_introspection() -> None:
    """Resolve the GI classes used by capture threads once, in the calling thread.

    PyGObject creates wrapper classes lazily on first attribute access; doing that from several capture threads at
    once corrupts reference counts (seen as ``g_atomic_ref_count_dec`` assertions and failed opens).
    """
    aravis = load_aravis()
    from gi.repository import Gio

    for name in (
        "Camera",
        "GvDevice",
        "Buffer",
        "BufferStatus",
        "GvStreamSocketBuffer",
        "Stream",
        "GvStream",
    ):
        getattr(aravis, name)
    Gio.InetAddress.new_from_string("127.0.0.1")


# Opening and configuring cameras is rare and goes through GenICam state shared inside Aravis/PyGObject:
# one camera at a time.
_OPEN_LOCK = threading.Lock()


class _Lib:
    """The few libaravis C functions called through ctypes."""

    def __init__(self) -> None:
        self.lib = ctypes.CDLL("libaravis-0.8.so.0")
        self.lib.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
        self.lib.arv_buffer_get_data.restype = ctypes.c_void_p
        get_pointer = ctypes.pythonapi.PyCapsule_GetPointer
        get_pointer.restype = ctypes.c_void_p
        get_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
        self._get_pointer = get_pointer

    def gobject_pointer(self, obj: Any) -> int:
        """Address of the C object behind a PyGObject wrapper."""
        return int(self._get_pointer(obj.__gpointer__, None))

    def buffer_memory(self, buffer_ptr: int, n_bytes: int) -> NDArray[np.uint8]:
        """Zero-copy numpy view, shape (n_bytes,), of an ArvBuffer's data."""
        size = ctypes.c_size_t()
        address = self.lib.arv_buffer_get_data(buffer_ptr, ctypes.byref(size))
        if not address:
            raise DeviceError("Aravis buffer has no data pointer")
        return np.ctypeslib.as_array((ctypes.c_uint8 * n_bytes).from_address(address))


_LIB: _Lib | None = None


def _lib() -> _Lib:
    global _LIB  # noqa: PLW0603 - one shared handle on libaravis per process
    if _LIB is None:
        _LIB = _Lib()
    return _LIB


@dataclass(frozen=True)
class AravisCameraConfig:
    """How to open and configure one camera. Exactly one of ``address``, ``serial``, ``device_id`` is set.

    Attributes
    ----------
    name : str
        mocapd's name for the camera (also the ring's name).
    address : str or None
        IPv4 address of a GigE Vision camera (no discovery needed).
    serial : str or None
        Serial number (needs discovery).
    device_id : str or None
        Aravis device id, as listed by ``mocapd devices`` or ``arv-tool-0.8`` (needs discovery).
    interface : str
        Network interface on which GigE Vision discovery may broadcast to find a camera by ``serial`` or
        ``device_id``; "" = none (the camera is then looked for among USB3 Vision devices only).
    pixel_format : str
        ``Mono8``, ``RGB8`` or ``BayerRG8``/``BayerBG8``/``BayerGR8``/``BayerGB8`` (demosaiced to RGB).
    region : (x, y, width, height) or None
        Sensor region of interest in pixels (after binning); None keeps the camera's.
    binning : (horizontal, vertical) or None
        Pixel binning factors; None keeps the camera's.
    frame_rate : float or None
        Acquisition frame rate in Hz (free-running mode); None keeps the camera's.
    exposure_us : float or None
        Exposure time in microseconds; None keeps the camera's.
    gain_db : float or None
        Analog gain in dB; None keeps the camera's.
    trigger : str or None
        Trigger source (``"Line0"``, ``"Software"``, ...) for triggered acquisition; None = free-running.
    packet_size : int or None
        GigE Vision stream packet size in bytes (jumbo frames: 8192 or 9000); 0 = negotiate automatically;
        None keeps the camera's.
    n_buffers : int
        Buffers in the Aravis pool (frames that can wait between the driver and the capture thread).
    ring_slots : int
        Frames kept in the ring buffer.
    pop_timeout_s : float
        How long the capture thread waits for one frame before checking for stop / loss, in seconds.
    lost_after_s : float
        A free-running camera that delivers nothing for this long is declared lost, in seconds.
    socket_frames : int
        GigE only: the stream socket's receive buffer holds this many frames, so a capture process descheduled
        for a few frame periods loses nothing (the kernel caps it at ``net.core.rmem_max``).
    packet_timeout_ms : float
        GigE only: how long a missing packet is waited for before a resend is requested (Aravis default 20).
    frame_retention_ms : float
        GigE only: how long an incomplete frame waits for resent packets before it is given up as incomplete
        (Aravis default 100). A loaded host (or a camera far away on the network) needs more.
    packet_delay_ns : int or None
        GigE only: inter-packet delay (GevSCPD) in ns, which spreads each frame's burst so that several cameras
        sharing one link do not overflow the switch or the NIC; None keeps the camera's.
    ptp : bool
        Enable IEEE 1588 PTP on the camera (``PtpEnable``, or ``GevIEEE1588`` on GigE Vision 2.0 cameras): its
        frame timestamps then come from the PTP clock. A camera without either feature fails to open.
    features : tuple of (str, value)
        Any other GenICam feature by name, set last, in order: a bool, int, float or str (enumeration entries
        by name).
    """

    name: str
    address: str | None = None
    serial: str | None = None
    device_id: str | None = None
    interface: str = ""
    pixel_format: str = "Mono8"
    region: tuple[int, int, int, int] | None = None
    binning: tuple[int, int] | None = None
    frame_rate: float | None = None
    exposure_us: float | None = None
    gain_db: float | None = None
    trigger: str | None = None
    packet_size: int | None = None
    n_buffers: int = 8
    ring_slots: int = 16
    pop_timeout_s: float = 0.2
    lost_after_s: float = 3.0
    socket_frames: int = 4
    packet_timeout_ms: float = 20.0
    frame_retention_ms: float = 100.0
    packet_delay_ns: int | None = None
    ptp: bool = False
    features: tuple[tuple[str, bool | int | float | str], ...] = ()

    def __post_init__(self) -> None:
        chosen = [k for k in ("address", "serial", "device_id") if getattr(self, k)]
        if len(chosen) != 1:
            raise ConfigError(
                f"camera {self.name!r}: set exactly one of address, serial, device_id (got {chosen or 'none'})"
            )
        pixel_format(self.pixel_format)
        if self.n_buffers < 2 or self.ring_slots < 2:
            raise ConfigError(f"camera {self.name!r}: n_buffers and ring_slots must be >= 2")
        if not (0 < self.packet_timeout_ms <= self.frame_retention_ms):
            raise ConfigError(
                f"camera {self.name!r}: need 0 < packet_timeout_ms <= frame_retention_ms, got "
                f"{self.packet_timeout_ms} and {self.frame_retention_ms}"
            )


def local_address_for(address: str) -> str:
    """The host address the kernel would use to reach ``address`` (no packet is sent).

    Raises
    ------
    DeviceError
        If no route leads to ``address``.
    """
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect((address, 3956))  # GVCP port; UDP connect() only selects a route
        except OSError as exc:
            raise DeviceError(f"no route to camera address {address}: {exc}") from exc
        return str(s.getsockname()[0])


def aravis_without_gige_discovery() -> Any:
    """Aravis with its GigE Vision interface disabled (for the whole process): listing or opening devices by
    name then never broadcasts. GigE Vision cameras are opened by address, or found by
    :mod:`mocapd.io.gige_discovery` on one named interface.

    Raises
    ------
    DeviceError
        If Aravis is not available.
    """
    aravis = load_aravis()
    aravis.disable_interface("GigEVision")
    return aravis


def open_camera(config: AravisCameraConfig) -> Any:
    """Open an ``Aravis.Camera`` as ``config`` says (blocking; GigE discovery on ``config.interface`` waits up to
    :data:`~mocapd.io.gige_discovery.DEFAULT_TIMEOUT_S`).

    Raises
    ------
    DeviceError
        If the camera cannot be found or opened; the message names how it was looked for.
    """
    aravis = aravis_without_gige_discovery()
    from gi.repository import Gio, GLib

    what = config.address or config.device_id or config.serial
    try:
        if config.address:
            return _open_gige(aravis, Gio, config, local_address_for(config.address), config.address)
        if config.interface:
            found = find_camera(config.interface, serial=config.serial or "", device_id=config.device_id or "")
            what = f"{what} at {found.address} on {config.interface}"
            return _open_gige(aravis, Gio, config, found.interface.address, found.address)
        if config.device_id:
            return aravis.Camera.new(config.device_id)
        aravis.update_device_list()
        for i in range(aravis.get_n_devices()):
            if aravis.get_device_serial_nbr(i) == config.serial:
                return aravis.Camera.new(aravis.get_device_id(i))
    except GLib.Error as exc:
        raise DeviceError(f"camera {config.name!r} ({what}) cannot be opened: {exc.message}") from exc
    raise DeviceError(
        f"camera {config.name!r}: no USB3 Vision device with serial {config.serial!r} (a GigE Vision camera needs "
        "its address, or the network interface to discover it on)"
    )


def _open_gige(aravis: Any, gio: Any, config: AravisCameraConfig, local: str, remote: str) -> Any:
    remote_address = gio.InetAddress.new_from_string(remote)
    if remote_address is None:
        raise ConfigError(f"camera {config.name!r}: {remote!r} is not an IPv4 address")
    device = aravis.GvDevice.new(gio.InetAddress.new_from_string(local), remote_address)
    return aravis.Camera.new_with_device(device)


def configure_camera(camera: Any, config: AravisCameraConfig) -> tuple[int, int]:
    """Apply ``config`` to an open camera and return the image size (width, height) it will deliver.

    Raises
    ------
    DeviceError
        If the camera rejects a setting (the message names the setting).
    """
    from gi.repository import GLib

    steps: list[tuple[str, Any]] = [("pixel format", lambda: camera.set_pixel_format_from_string(config.pixel_format))]
    if config.binning is not None:
        steps.append(("binning", lambda: camera.set_binning(*config.binning)))
    if config.region is not None:
        steps.append(("region", lambda: camera.set_region(*config.region)))
    if config.trigger is None:
        steps.append(("free-running mode", camera.clear_triggers))
        if config.frame_rate is not None:
            steps.append(("frame rate", lambda: camera.set_frame_rate(config.frame_rate)))
    else:
        steps.append(("trigger", lambda: camera.set_trigger(config.trigger)))
    if config.exposure_us is not None:
        steps.append(("exposure", lambda: camera.set_exposure_time(config.exposure_us)))
    if config.gain_db is not None:
        steps.append(("gain", lambda: camera.set_gain(config.gain_db)))
    if config.packet_size is not None and camera.is_gv_device():
        if config.packet_size == 0:
            steps.append(("packet size", camera.gv_auto_packet_size))
        else:
            steps.append(("packet size", lambda: camera.gv_set_packet_size(config.packet_size)))
    if config.packet_delay_ns is not None and camera.is_gv_device():
        steps.append(("inter-packet delay", lambda: camera.gv_set_packet_delay(config.packet_delay_ns)))
    if config.ptp:
        steps.append(("PTP", lambda: _enable_ptp(camera, config.name)))
    for name, value in config.features:
        steps.append((f"feature {name} = {value!r}", _feature_setter(camera, config.name, name, value)))
    for what, step in steps:
        try:
            step()
        except GLib.Error as exc:
            raise DeviceError(f"camera {config.name!r} rejected {what}: {exc.message}") from exc
    region = camera.get_region()
    return int(region.width), int(region.height)


PTP_FEATURES = ("PtpEnable", "GevIEEE1588")  # SFNC 2.x name first, then GigE Vision 2.0's


def _enable_ptp(camera: Any, name: str) -> None:
    for feature in PTP_FEATURES:
        if camera.is_feature_available(feature):
            camera.set_boolean(feature, True)
            return
    raise DeviceError(f"camera {name!r} offers no PTP (none of {', '.join(PTP_FEATURES)}); set ptp = false")


def _feature_setter(camera: Any, name: str, feature: str, value: bool | int | float | str) -> Any:
    """The call that sets one GenICam feature by name, chosen by the value's type."""

    def apply() -> None:
        if not camera.is_feature_available(feature):
            raise DeviceError(f"camera {name!r} has no GenICam feature {feature!r} (or it is not available now)")
        if isinstance(value, bool):
            camera.set_boolean(feature, value)
        elif isinstance(value, int):
            camera.set_integer(feature, value)
        elif isinstance(value, float):
            camera.set_float(feature, value)
        else:
            camera.set_string(feature, value)

    return apply


class AravisSource(ThreadedSource):
    """One Aravis camera captured into a ring buffer by its own thread.

    Parameters
    ----------
    config : AravisCameraConfig
    ring : FrameRing or None
        Ring to fill; by default one is made from the configured region and pixel format (a region must then be
        given) by :func:`~mocapd.io.pixels.capture_ring`. An eager ring of a Bayer camera gets its frames
        demosaiced at capture.
    """

    def __init__(self, config: AravisCameraConfig, ring: FrameRing | None = None, **kw: Any) -> None:
        fmt = pixel_format(config.pixel_format)
        if ring is None:
            if config.region is None:
                raise ConfigError(f"camera {config.name!r}: give a region (x, y, width, height) or a ring")
            _, _, w, h = config.region
            ring = capture_ring(config.name, config.ring_slots, h, w, fmt)
        super().__init__(config.name, ring, **kw)
        _warm_up_introspection()
        self.config = config
        self.format: PixelFormat = fmt
        self._camera: Any = None
        self._stream: Any = None
        self._views: dict[int, NDArray[np.uint8]] = {}
        self._control_lost = threading.Event()
        self._lost_handler = 0  # the "control-lost" signal handler's id on the open device
        # Objects of a closed opening, released on this capture thread at the next opening (see _close).
        self._retired: tuple[Any, ...] = ()
        self._size = (0, 0)
        self._last_frame_ns = 0
        # Silence counted only while the capture thread was there to hear it (a paused process is not a lost
        # camera: its frames wait in the socket buffer); checked at every pop time-out.
        self._silence = SilenceClock(0, round(self.config.pop_timeout_s * 1e9), round(self.config.lost_after_s * 1e9))
        self._stream_base = (0, 0)  # counters before this opening, added to the stream's own
        self._success = load_aravis().BufferStatus.SUCCESS  # looked up once, not per frame

    def release(self) -> None:
        """Free the camera and stream of the last opening now, once :meth:`run` has returned, rather than at the
        next opening or when this source is freed. Freeing a GigE camera tells it that it is no longer controlled,
        and Aravis waits out its GVCP time-outs (about 5 s) for the answer of a camera that is gone: a program that
        stops the cameras itself (the fake ones of mocapd.sim.fake_rig) releases its sources first."""
        self._retired = ()

    def _open(self) -> None:
        self._retired = ()  # the last opening's camera and stream end here, on the capture thread
        with _OPEN_LOCK:
            self._open_locked()
        self._last_frame_ns = time.monotonic_ns()
        self._silence = SilenceClock(self._last_frame_ns, round(self.config.pop_timeout_s * 1e9),
                                     round(self.config.lost_after_s * 1e9))  # fmt: skip

    def _open_locked(self) -> None:
        aravis = load_aravis()
        from gi.repository import GLib

        self._control_lost.clear()
        camera = open_camera(self.config)
        self._camera = camera
        width, height = configure_camera(camera, self.config)
        h, w, c = self.ring.shape
        if (height, width, c) != (h, w, self.format.channels):
            raise DeviceError(f"camera {self.name!r} delivers {width}x{height} {self.format.name}, ring is {w}x{h}x{c}")
        self._size = (width, height)
        try:
            self._lost_handler = camera.get_device().connect("control-lost", lambda *_: self._control_lost.set())
            stream = camera.create_stream(None, None)
            if stream is None:
                raise DeviceError(f"camera {self.name!r}: Aravis could not create a stream")
            payload = camera.get_payload()
            if camera.is_gv_device():
                # A frame arrives as a burst of packets; a receive buffer of several frames rides out scheduling
                # stalls of the stream thread on a loaded machine.
                stream.set_property("socket-buffer", aravis.GvStreamSocketBuffer.FIXED)
                stream.set_property("socket-buffer-size", min(payload * self.config.socket_frames, 1 << 30))
                stream.set_property("packet-timeout", round(self.config.packet_timeout_ms * 1000))
                stream.set_property("frame-retention", round(self.config.frame_retention_ms * 1000))
            lib = _lib()
            self._views.clear()
            for _ in range(self.config.n_buffers):
                buffer = aravis.Buffer.new_allocate(payload)
                pointer = lib.gobject_pointer(buffer)
                self._views[pointer] = lib.buffer_memory(pointer, payload)
                stream.push_buffer(buffer)
            self._stream = stream
            self._stream_base = (self.counters.missing_frames, self.counters.resent_packets)
            camera.start_acquisition()
        except GLib.Error as exc:
            raise DeviceError(f"camera {self.name!r} cannot start streaming: {exc.message}") from exc

    def _update_stream_counters(self) -> None:
        stream = self._stream
        base_missing, base_resent = self._stream_base
        self.counters.missing_frames = base_missing + int(stream.get_info_uint64_by_name("n_missing_frames"))
        self.counters.resent_packets = base_resent + int(stream.get_info_uint64_by_name("n_resent_packets"))

    def _grab(self) -> FrameRef | None:
        buffer = self._stream.timeout_pop_buffer(int(self.config.pop_timeout_s * 1e6))
        now = time.monotonic_ns()
        if buffer is None:
            self.counters.timeouts += 1
            self._check_alive(now)
            return None
        try:
            if buffer.get_status() != self._success:
                self.counters.bad_buffers += 1
                return None
            self._last_frame_ns = now
            self._silence.heard(now)
            view = self._views.get(_lib().gobject_pointer(buffer))
            if view is None:  # not one of ours: never expected, count rather than crash
                self.counters.bad_buffers += 1
                return None
            width, height = self._size
            store_raw(self.format, view, height, width, self.ring)
            ref = self.ring.publish(now, int(buffer.get_timestamp()), int(buffer.get_frame_id()))
            # Aravis' system timestamp (host wall clock when the frame's leader packet arrived) to publication:
            # the frame's transfer plus mocapd's capture path.
            self.latency.add(time.time_ns() - int(buffer.get_system_timestamp()))
            self.convert.add(time.monotonic_ns() - now)
        finally:
            self._stream.push_buffer(buffer)
        self.counters.frames += 1
        self._update_stream_counters()
        return ref

    def _check_alive(self, now: int) -> None:
        if self._control_lost.is_set():
            raise DeviceError(f"camera {self.name!r} lost its control connection (heartbeat)")
        self._silence.heard(self._last_frame_ns)
        silent_s = self._silence.silent_ns(now) / 1e9
        if self.config.trigger is None and silent_s > self.config.lost_after_s:
            self._control_lost.set()  # treat as gone: do not wait for protocol time-outs when closing
            raise DeviceError(f"camera {self.name!r} sent no frame for {silent_s:.1f} s")

    def _close(self) -> None:
        from gi.repository import GLib

        if self._stream is not None:
            self._update_stream_counters()
        if self._camera is not None and not self._control_lost.is_set():
            try:
                with _OPEN_LOCK:
                    self._camera.stop_acquisition()
            except GLib.Error as exc:  # the camera is gone: nothing left to stop
                log.debug("camera %s: stop_acquisition failed: %s", self.name, exc.message)
        # Aravis emits "control-lost" on the device's heartbeat thread, and the Python callback holds a reference
        # to the device while it runs. Were that the last reference (this thread dropped its own meanwhile), the
        # device would be finalized on the heartbeat thread, whose finalizer joins the heartbeat thread itself:
        # GLib aborts the process ("Resource deadlock avoided" in pthread_join), seen on camera unplugs. So the
        # handler is disconnected and the objects are kept until the next opening releases them on this thread.
        if self._camera is not None and self._lost_handler:
            self._camera.get_device().disconnect(self._lost_handler)
        self._lost_handler = 0
        self._retired = (self._camera, self._stream)
        self._stream = None
        self._camera = None
        self._views.clear()
