"""V4L2 capture devices listed from a sysfs tree the test builds (the layout of /sys/class/video4linux)."""

from __future__ import annotations

from pathlib import Path

from mocapd.io.v4l_devices import VideoDevice, list_video_devices


def _node(sysfs: Path, name: str, label: str, index: int, usb: Path | None = None) -> None:
    node = sysfs / name
    node.mkdir(parents=True)
    (node / "name").write_text(label + "\n")
    (node / "index").write_text(f"{index}\n")
    if usb is not None:
        (node / "device").symlink_to(usb)


def _usb_device(root: Path, port: str, vendor: str, product: str, serial: str | None) -> Path:
    device = root / "devices" / "usb1" / port
    interface = device / f"{port}:1.0"
    interface.mkdir(parents=True)
    (device / "idVendor").write_text(vendor + "\n")
    (device / "idProduct").write_text(product + "\n")
    if serial is not None:
        (device / "serial").write_text(serial + "\n")
    return interface


def test_capture_nodes_with_usb_ids_and_stable_paths(tmp_path: Path) -> None:
    sysfs, dev, by_id = tmp_path / "class" / "video4linux", tmp_path / "dev", tmp_path / "dev" / "v4l" / "by-id"
    c920 = _usb_device(tmp_path, "1-2", "046d", "082d", "ABCDEF01")
    cheap = _usb_device(tmp_path, "1-3", "0c45", "6366", None)
    _node(sysfs, "video0", "HD Pro Webcam C920", 0, c920)
    _node(sysfs, "video1", "HD Pro Webcam C920", 1, c920)  # its metadata node: no images
    _node(sysfs, "video10", "Loopback video", 0)  # not USB (v4l2loopback)
    _node(sysfs, "video2", "USB 2.0 Camera: USB Camera", 0, cheap)
    (sysfs / "video3").mkdir()  # being registered: no name yet
    by_id.mkdir(parents=True)
    for n in (0, 1, 2, 10):
        (dev / f"video{n}").touch()
    (by_id / "usb-046d_HD_Pro_Webcam_C920_ABCDEF01-video-index0").symlink_to(dev / "video0")
    (by_id / "usb-046d_HD_Pro_Webcam_C920_ABCDEF01-video-index1").symlink_to(dev / "video1")

    assert list_video_devices(sysfs, by_id, dev) == [
        VideoDevice(str(dev / "video0"), "HD Pro Webcam C920",
                    str(by_id / "usb-046d_HD_Pro_Webcam_C920_ABCDEF01-video-index0"), "046d:082d", "ABCDEF01"),
        VideoDevice(str(dev / "video2"), "USB 2.0 Camera: USB Camera", "", "0c45:6366", ""),
        VideoDevice(str(dev / "video10"), "Loopback video", "", "", ""),
    ]  # fmt: skip


def test_no_video4linux_class_means_no_devices(tmp_path: Path) -> None:
    assert list_video_devices(tmp_path / "absent", tmp_path / "absent-by-id") == []
