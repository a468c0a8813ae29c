"""The camera keys of config.toml: ``[record] frames*`` and ``[websocket] camera*`` parse, default as shipped,
and bad values are named."""

from __future__ import annotations

from collections.abc import Mapping

import pytest

from mocapd.errors import ConfigError
from mocapd.service.config import load_config
from mocapd.service.config.record import RecordConfig
from mocapd.service.config.schema import validate
from mocapd.service.config.websocket import WebSocketConfig


def parse_record_config(table: Mapping[str, object]) -> RecordConfig:
    return validate(RecordConfig, table, "record")


def parse_websocket_config(table: Mapping[str, object]) -> WebSocketConfig:
    return validate(WebSocketConfig, table, "websocket")


def test_shipped_defaults() -> None:
    cfg = load_config()
    assert (cfg.record.frames, cfg.record.frames_hz, cfg.record.frames_width, cfg.record.frames_quality) == (
        False, 2.0, 320, 70,
    )  # fmt: skip
    ws = cfg.websocket
    assert (ws.cameras, ws.camera_rate_hz, ws.camera_width, ws.camera_quality) == (True, 4.0, 320, 70)


def test_values_are_parsed_and_bad_ones_named() -> None:
    r = parse_record_config({"frames": True, "frames_hz": 5, "frames_width": 640, "frames_quality": 90})
    assert (r.frames, r.frames_hz, r.frames_width, r.frames_quality) == (True, 5.0, 640, 90)
    w = parse_websocket_config({"cameras": False, "camera_rate_hz": 2, "camera_width": 160, "camera_quality": 50})
    assert (w.cameras, w.camera_rate_hz, w.camera_width, w.camera_quality) == (False, 2.0, 160, 50)
    for table, parse, key in (
        ({"frames": "yes"}, parse_record_config, "record.frames"),
        ({"frames_hz": 0}, parse_record_config, "record.frames_hz"),
        ({"frames_width": 8}, parse_record_config, "record.frames_width"),
        ({"frames_quality": 101}, parse_record_config, "record.frames_quality"),
        ({"cameras": 1}, parse_websocket_config, "websocket.cameras"),
        ({"camera_rate_hz": 100}, parse_websocket_config, "websocket.camera_rate_hz"),
        ({"camera_width": 10_000}, parse_websocket_config, "websocket.camera_width"),
    ):
        with pytest.raises(ConfigError, match=key):
            parse(table)
