"""AravisCameraConfig validation and the helpers of mocapd.io.aravis_camera that need no camera."""

from __future__ import annotations

import pytest

from mocapd.errors import ConfigError
from mocapd.io.aravis_camera import AravisCameraConfig, AravisSource, load_aravis, local_address_for


def test_exactly_one_way_to_find_the_camera() -> None:
    with pytest.raises(ConfigError, match="exactly one of address, serial, device_id"):
        AravisCameraConfig("cam")
    with pytest.raises(ConfigError, match="exactly one"):
        AravisCameraConfig("cam", address="127.0.0.1", serial="X")
    assert AravisCameraConfig("cam", serial="X").serial == "X"


def test_bad_values_are_named() -> None:
    with pytest.raises(ConfigError, match="YUV"):
        AravisCameraConfig("cam", address="127.0.0.1", pixel_format="YUV422")
    with pytest.raises(ConfigError, match="n_buffers"):
        AravisCameraConfig("cam", address="127.0.0.1", n_buffers=1)
    with pytest.raises(ConfigError, match="give a region"):
        AravisSource(AravisCameraConfig("cam", address="127.0.0.1"))


def test_ring_follows_region_and_format() -> None:
    src = AravisSource(AravisCameraConfig("cam", address="127.0.0.1", pixel_format="BayerRG8", region=(0, 0, 64, 48)))
    assert src.ring.shape == (48, 64, 3)
    mono = AravisSource(AravisCameraConfig("m", address="127.0.0.1", region=(8, 8, 32, 16), ring_slots=4))
    assert mono.ring.shape == (16, 32, 1) and mono.ring.n_slots == 4


def test_aravis_is_installed_and_loopback_routes_to_itself() -> None:
    aravis = load_aravis()
    assert hasattr(aravis, "GvFakeCamera")
    assert local_address_for("127.0.0.1") == "127.0.0.1"
