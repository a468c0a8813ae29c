"""``[imu.slimevr]`` and ``[udp.vrchat]``: defaults, the merged IMU assignment, and every refusal naming its key."""

from __future__ import annotations

from typing import Any

import pytest

from mocapd.errors import ConfigError
from mocapd.service.config import load_config, parse_config
from mocapd.service.config.udp import Destination

MAC0 = "A1:B2:C3:D4:E5:F6/0"


def test_shipped_defaults_are_off_and_on_loopback() -> None:
    c = load_config()
    assert not c.imu.slimevr.enabled and c.imu.slimevr.host == "127.0.0.1" and c.imu.slimevr.port == 6969
    v = c.udp.vrchat
    assert not v.enabled and v.destination == Destination("127.0.0.1", 9000) and v.subject == ""  # "": the first
    assert v.trackers[0] == "hip" and len(v.trackers) == 9 and v.user_height_m == 0.0  # 0: no scaling


def test_slimevr_assignment_joins_the_imu_assignment() -> None:
    c = parse_config({"imu": {"assignment": {"00B421E6": "Head"},
                              "slimevr": {"enabled": True, "host": "0.0.0.0", "port": 0,
                                          "assignment": {MAC0.lower(): "Hips"}}}})  # fmt: skip
    assert c.imu.sensors == {"00B421E6": "Head", MAC0: "Hips"}  # one assignment, whatever the transport
    assert c.imu.assignment == {"00B421E6": "Head"}
    assert c.imu.slimevr.assignment == {MAC0: "Hips"} and c.imu.slimevr.host == "0.0.0.0"


@pytest.mark.parametrize(
    ("table", "match"),
    [
        ({"slimevr": {"enabled": 1}}, "imu.slimevr.enabled"),
        ({"slimevr": {"host": "tracker.local"}}, "imu.slimevr.host"),
        ({"slimevr": {"port": 70000}}, "imu.slimevr.port"),
        ({"slimevr": {"colour": "red"}}, "imu.slimevr"),
        ({"slimevr": {"assignment": {"00B421E6": "Hips"}}}, "are Xsens ids"),
        ({"slimevr": {"assignment": {"A1:B2:C3/0": "Hips"}}}, "SlimeVR"),
        ({"slimevr": {"assignment": {MAC0: "Tail"}}}, "is not a bone"),
        ({"assignment": {"00B421E6": "Hips"}, "slimevr": {"assignment": {MAC0: "Hips"}}}, "more than one sensor"),
        ({"assignment": {MAC0: "Head"}, "slimevr": {"assignment": {MAC0: "Hips"}}}, "in both"),
        ({"imu_set": "6", "slimevr": {"assignment": {MAC0: "Hips"}}}, "6-sensor set"),
    ],
)
def test_bad_slimevr_settings_are_refused(table: dict[str, Any], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        parse_config({"imu": table})


def test_vrchat_settings() -> None:
    c = parse_config({"udp": {"vrchat": {"enabled": True, "destination": "127.0.0.2:9001", "subject": "suit:alice",
                                         "trackers": ["left_foot", "hip"], "user_height_m": 1.62,
                                         "rate_divisor": 2}}})  # fmt: skip
    v = c.udp.vrchat
    assert (v.destination, v.subject, v.trackers, v.user_height_m, v.rate_divisor) == (
        Destination("127.0.0.2", 9001), "suit:alice", ("left_foot", "hip"), 1.62, 2)  # fmt: skip
    remote = parse_config({"udp": {"allow_remote": True, "vrchat": {"destination": "192.0.2.7:9000"}}})
    assert remote.udp.vrchat.destination == Destination("192.0.2.7", 9000)


@pytest.mark.parametrize(
    ("table", "match"),
    [
        ({"destination": "192.0.2.7:9000"}, "not a loopback address"),
        ({"destination": "127.0.0.1"}, "udp.vrchat.destination"),
        ({"subject": 3}, "udp.vrchat.subject"),
        ({"subject": "all"}, "udp.vrchat.subject"),
        ({"trackers": ["hip", "tail"]}, "udp.vrchat.trackers"),
        ({"trackers": []}, "udp.vrchat.trackers"),
        ({"trackers": ["hip", "hip"]}, "udp.vrchat.trackers"),
        ({"user_height_m": 3.0}, "udp.vrchat.user_height_m"),
        ({"user_height_m": True}, "udp.vrchat.user_height_m"),
        ({"rate_divisor": 0}, "udp.vrchat.rate_divisor"),
        ({"enabled": "yes"}, "udp.vrchat.enabled"),
        ({"port": 9000}, "udp.vrchat"),
    ],
)
def test_bad_vrchat_settings_are_refused(table: dict[str, Any], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        parse_config({"udp": {"vrchat": table}})
