"""The [record] section: defaults, the shipped file, and every bad value named."""

from __future__ import annotations

import pytest

from mocapd.errors import ConfigError
from mocapd.service.config import load_config, parse_config
from mocapd.service.config.record import RecordConfig, parse_record_config


def test_shipped_file_and_defaults() -> None:
    assert load_config().record == RecordConfig()
    cfg = parse_record_config({"enabled": True, "directory": "/data/takes", "flush_interval_s": 1, "fsync": False,
                               "queue_size": 500})  # fmt: skip
    assert cfg == RecordConfig(True, "/data/takes", 1.0, False, 500, False)
    assert parse_config({"record": {"enabled": True}}).record.enabled


@pytest.mark.parametrize(
    ("table", "needle"),
    [
        ({"enable": True}, "unknown key"),
        ({"enabled": "yes"}, "record.enabled"),
        ({"video": True}, "not supported"),
        ({"directory": ""}, "record.directory"),
        ({"flush_interval_s": 1.5}, "(0, 1]"),
        ({"flush_interval_s": 0}, "(0, 1]"),
        ({"queue_size": 10}, "record.queue_size"),
        ({"queue_size": 1.5}, "record.queue_size"),
    ],
)
def test_bad_values_are_named(table: dict[str, object], needle: str) -> None:
    with pytest.raises(ConfigError, match=None) as exc:
        parse_record_config(table)
    assert needle in str(exc.value)
