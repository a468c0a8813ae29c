"""The [record] section: defaults, the shipped file, and every bad value named."""

from __future__ import annotations

import pytest

from mocapd.errors import ConfigError
from mocapd.service.config import load_config, parse_config
from mocapd.service.config.record import RecordConfig


def test_shipped_file_and_defaults() -> None:
    assert load_config().record == RecordConfig()
    cfg = parse_config({"record": {"enabled": True, "directory": "/data/takes", "flush_interval_s": 1, "fsync": False,
                                   "queue_size": 500}}).record  # fmt: skip
    assert cfg == RecordConfig(enabled=True, directory="/data/takes", flush_interval_s=1.0, fsync=False, queue_size=500)
    assert parse_config({"record": {"enabled": True}}).record.enabled


@pytest.mark.parametrize(
    ("table", "needle"),
    [
        ({"enable": True}, "unknown key record.enable; allowed: directory, enabled,"),
        ({"enabled": "yes"}, "record.enabled = 'yes'; allowed: true or false"),
        (
            {"video": True},
            "record.video = true; allowed: false (recording camera frames as video is not supported yet)",
        ),
        ({"directory": ""}, "record.directory = ''; allowed: a non-empty string"),
        ({"flush_interval_s": 1.5}, "record.flush_interval_s = 1.5; allowed: a number in (0, 1]"),
        ({"flush_interval_s": 0}, "record.flush_interval_s = 0; allowed: a number in (0, 1]"),
        ({"queue_size": 10}, "record.queue_size = 10; allowed: an integer in [100, 1000000]"),
        ({"queue_size": 1.5}, "record.queue_size = 1.5; allowed: an integer"),
    ],
)
def test_bad_values_are_named(table: dict[str, object], needle: str) -> None:
    with pytest.raises(ConfigError, match=None) as exc:
        parse_config({"record": table})
    assert needle in str(exc.value)
