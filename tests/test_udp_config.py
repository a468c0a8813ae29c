"""The [udp] section: defaults, the shipped file, and bad values rejected with the key, the value and what is
allowed; non-loopback destinations only with udp.allow_remote."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from mocapd.errors import ConfigError
from mocapd.service.cli import main
from mocapd.service.config import load_config, parse_config
from mocapd.service.config.udp import Destination, UdpConfig


def udp(table: dict[str, Any]) -> UdpConfig:
    return parse_config({"udp": table}).udp


def test_shipped_file_and_defaults() -> None:
    cfg = load_config()
    assert cfg.udp == UdpConfig() == parse_config({"udp": {}}).udp
    assert not cfg.udp.mvn.enabled and not cfg.udp.vmc.enabled and not cfg.udp.allow_remote
    assert cfg.udp.mvn.destinations == (Destination("127.0.0.1", 9763),)
    assert cfg.udp.vmc.destinations == (Destination("127.0.0.1", 39539),)


def test_a_full_section_parses() -> None:
    u = udp({
        "mvn": {"enabled": True, "destinations": ["127.0.0.1:9000", "localhost:9001"], "rate_divisor": 2,
                "subjects": ["suit:a", "track:2"], "character_ids": {"suit:a": 3}, "max_datagram_bytes": 300},
        "vmc": {"enabled": True, "destinations": ["127.0.0.2:39539", "127.0.0.1:39541"],
                "subjects": ["suit:a", "suit:b"]},
    })  # fmt: skip
    assert u.mvn.destinations == (Destination("127.0.0.1", 9000), Destination("127.0.0.1", 9001))
    assert u.mvn.rate_divisor == 2 and u.mvn.subjects == ("suit:a", "track:2")
    assert u.mvn.character_ids == {"suit:a": 3} and u.mvn.max_datagram_bytes == 300
    assert u.vmc.subjects == ("suit:a", "suit:b") and str(u.vmc.destinations[0]) == "127.0.0.2:39539"


def test_remote_destinations_need_allow_remote() -> None:
    remote = {"mvn": {"destinations": ["192.168.1.20:9763"]}}
    with pytest.raises(
        ConfigError, match=r"udp.mvn.destinations = .*192\.168\.1\.20:9763.*not a loopback.*udp\.allow_remote = true"
    ):
        udp(remote)
    assert udp({"allow_remote": True, **remote}).mvn.destinations == (Destination("192.168.1.20", 9763),)


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ({"mvm": {}}, r"unknown key udp.mvm; allowed: allow_remote, mvn, rokoko, vmc, vrchat$"),
        ({"mvn": {"port": 1}}, r"unknown key udp.mvn.port; allowed: character_ids, destinations,"),
        ({"vmc": {"character_ids": {}}}, r"unknown key udp.vmc.character_ids; allowed: destinations,"),
        ({"allow_remote": "yes"}, r"udp.allow_remote = 'yes'; allowed: true or false"),
        ({"mvn": {"enabled": 1}}, r"udp.mvn.enabled = 1; allowed: true or false"),
        ({"mvn": []}, r"udp.mvn = \[\]; allowed: a table"),
        ({"mvn": {"destinations": "127.0.0.1:9763"}}, r"destinations = '127.0.0.1:9763'; allowed: a non-empty array"),
        ({"mvn": {"destinations": []}}, r"destinations = \[\]; allowed: a non-empty array of at most 64 items"),
        ({"mvn": {"destinations": ["127.0.0.1"]}}, r"udp.mvn.destinations\[0\] = '127.0.0.1': allowed: \"host:port\""),
        ({"mvn": {"destinations": ["example.com:9763"]}}, r"'example.com:9763': allowed: \"host:port\" with an IPv4"),
        ({"mvn": {"destinations": ["127.0.0.1:0"]}}, r"port '0'; allowed"),
        ({"mvn": {"destinations": ["127.0.0.1:70000"]}}, r"port '70000'; allowed"),
        ({"mvn": {"destinations": ["127.0.0.1:x"]}}, r"udp.mvn.destinations\[0\] = '127.0.0.1:x'"),
        ({"allow_remote": True, "vmc": {"destinations": ["255.255.255.255:1"]}}, r"broadcast, multicast"),
        ({"allow_remote": True, "vmc": {"destinations": ["239.1.1.1:1"]}}, r"broadcast, multicast"),
        ({"vmc": {"destinations": ["0.0.0.0:1"]}}, r"0.0.0.0 are not allowed"),
        ({"mvn": {"destinations": ["127.0.0.1:1", "localhost:1"]}}, r"lists '127.0.0.1:1' twice"),
        ({"mvn": {"rate_divisor": 0}}, r"udp.mvn.rate_divisor = 0; allowed: an integer in \[1, 1000\]"),
        ({"vmc": {"rate_divisor": 1.5}}, r"udp.vmc.rate_divisor = 1.5; allowed: an integer"),
        ({"mvn": {"max_datagram_bytes": 100}}, r"max_datagram_bytes = 100; allowed: an integer in \[256, 65507\]"),
        ({"mvn": {"subjects": "everyone"}}, r"udp.mvn.subjects = 'everyone'; allowed: \"all\" or a non-empty array"),
        ({"mvn": {"subjects": ["suit:a", "suit:a"]}}, r"lists 'suit:a' twice"),
        ({"mvn": {"subjects": [""]}}, r"^udp.mvn.subjects\[0\] = ''; allowed: a non-empty string"),
        ({"mvn": {"subjects": []}}, r"udp.mvn.subjects = \[\]; allowed: \"all\" or a non-empty array"),
        ({"mvn": {"character_ids": {"suit:a": 256}}}, r'character_ids."suit:a" = 256; allowed: an integer in \[0, 255\]'),  # noqa: E501
        ({"mvn": {"character_ids": {"suit:a": 1, "suit:b": 1}}}, r"gives two subjects the same id"),
        ({"mvn": {"character_ids": [1]}}, r"udp.mvn.character_ids = \[1\]; allowed: a table"),
        ({"vmc": {"subjects": ["suit:a", "suit:b"]}}, r"has 2 entries for the 1 of udp.vmc.destinations"),
    ],
)  # fmt: skip
def test_bad_values_are_rejected_with_clear_messages(table: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_config({"udp": table})


def test_udp_is_a_known_section() -> None:
    with pytest.raises(ConfigError, match=r"udp.mvn.rate_divisor"):
        parse_config({"udp": {"mvn": {"rate_divisor": -1}}})
    with pytest.raises(ConfigError, match=r"udp = 3; allowed: a table"):
        parse_config({"udp": 3})


def test_mocapd_refuses_to_start_with_a_remote_destination(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "remote.toml"
    path.write_text('[udp.vmc]\nenabled = true\ndestinations = ["10.0.0.7:39539"]\n', encoding="utf-8")
    assert main(["run", "--config", str(path), "--http-port", "0"]) == 2
    err = capsys.readouterr().err
    assert "udp.vmc.destinations = ['10.0.0.7:39539']: '10.0.0.7:39539' is not a loopback address" in err
    assert "udp.allow_remote = true" in err
    assert main(["check-config", str(path)]) == 2
