"""``[[cameras]]``: every key of every source kind documented in the shipped config.toml (as the commented example
of its kind) and refused, naming itself, when given a bad value; every rule across keys exercised.

The shipped file describes no rig, so tests/test_config_schema.py (which walks the file's own keys) leaves the
camera tables to this module."""

from __future__ import annotations

import math
import re
import tomllib
from typing import Any, get_args

import pytest
from pydantic import BaseModel

from mocapd.errors import ConfigError
from mocapd.service.config import DEFAULT_CONFIG
from mocapd.service.config.cameras import CAMERA_KINDS, parse_cameras


def _examples() -> dict[str, dict[str, Any]]:
    """The commented ``# [[cameras]]`` example tables of the shipped file, uncommented and parsed, by kind."""
    text = DEFAULT_CONFIG.read_text(encoding="utf-8")
    blocks = re.split(r"^#\s*\[\[cameras\]\]", text, flags=re.M)[1:]
    out: dict[str, dict[str, Any]] = {}
    for block in blocks:
        lines = ["[[cameras]]" + block.splitlines()[0].split("#")[0]]
        for line in block.splitlines()[1:]:
            if not line.startswith("#") or not line[1:].strip() or line.startswith("# --"):
                break
            lines.append(line[2:] if line.startswith("# ") else line[1:])
        table = tomllib.loads("\n".join(lines))["cameras"][0]
        out[table["source"]] = table
    return out


EXAMPLES = _examples()


def test_every_source_kind_has_a_documented_example_with_every_key() -> None:
    assert set(EXAMPLES) == set(CAMERA_KINDS)
    for kind, model in CAMERA_KINDS.items():
        missing = sorted(set(model.model_fields) - set(EXAMPLES[kind]))
        assert not missing, f"source = {kind!r}: keys missing from the example in config.toml: {missing}"


@pytest.mark.parametrize("kind", sorted(CAMERA_KINDS))
def test_each_example_is_valid_once_its_alternatives_are_chosen(kind: str) -> None:
    table = dict(EXAMPLES[kind])
    if kind == "aravis":  # the example lists the three ways to open it: keep the first
        table.pop("serial")
        table.pop("device_id")
    (cam,) = parse_cameras([table])
    assert cam.source == kind


def _bad_values(model: type[BaseModel], key: str) -> list[Any]:
    """What a fuzzer tries on one key: wrong types, non-finite numbers, numbers beyond both bounds, huge ones."""
    field = model.model_fields[key]
    bad: list[Any] = [{"a": 1}]  # a table where a value belongs: wrong for every key
    annotation = str(field.annotation)
    if "float" in annotation or "int" in annotation:
        bad += [math.nan, math.inf, -math.inf, 10**400]
        if "str" not in annotation:  # a webcam's device is an index or a path: "1" is a path
            bad.append("1")
        for meta in field.metadata:
            for attr, step in (("ge", -1), ("gt", 0), ("le", 1), ("lt", 0)):
                bound = getattr(meta, attr, None)
                if bound is not None:
                    bad.append(bound + step if step else bound)
    if "bool" in annotation and "int" not in annotation:
        bad.append(1)
    if annotation.endswith("str") or "Literal" in annotation:
        bad += [7, "\x00" if "Literal" not in annotation else "NotAChoice", "x" * 5000]
    return bad


CASES = [
    (kind, key, value)
    for kind, model in CAMERA_KINDS.items()
    for key in model.model_fields
    if key not in ("name", "source", "features")
    for value in _bad_values(model, key)
]


@pytest.mark.parametrize(("kind", "key", "value"), CASES, ids=lambda v: repr(v)[:30])
def test_each_key_refuses_a_bad_value_and_names_itself(kind: str, key: str, value: Any) -> None:
    table = {k: v for k, v in EXAMPLES[kind].items() if k not in ("serial", "device_id")} | {key: value}
    with pytest.raises(ConfigError) as err:
        parse_cameras([table])
    assert f"cameras[0].{key}" in str(err.value) or f"cameras[0]: {key}" in str(err.value), str(err.value)


RULES: list[tuple[str, list[Any], str]] = [
    # (rule, [[cameras]] tables, what the message must say)
    ("aravis: one way to open", [{"name": "a", "source": "aravis"}], "set exactly one of address, serial"),
    ("aravis: two ways to open", [{"name": "a", "source": "aravis", "address": "10.0.0.2", "serial": "X"}],
     "set exactly one of address, serial"),
    ("aravis: empty region", [{"name": "a", "source": "aravis", "address": "10.0.0.2", "region": [0, 0, 0, 10]}],
     "width, height >= 1"),
    ("aravis: packet timeout beyond retention",
     [{"name": "a", "source": "aravis", "address": "10.0.0.2", "packet_timeout_ms": 200.0}],
     "packet_timeout_ms must be <= frame_retention_ms"),
    ("aravis: feature value a list",
     [{"name": "a", "source": "aravis", "address": "10.0.0.2", "features": {"Gain": [1]}}],
     "cameras[0].features.Gain"),
    ("aravis: feature value nan",
     [{"name": "a", "source": "aravis", "address": "10.0.0.2", "features": {"Gain": math.nan}}],
     "cameras[0].features.Gain"),
    ("aravis: feature value beyond 64 bits",
     [{"name": "a", "source": "aravis", "address": "10.0.0.2", "features": {"Gain": 2**64}}],
     "cameras[0].features.Gain"),
    ("uvc: empty path", [{"name": "a", "source": "uvc", "device": ""}], "give an index or a path"),
    ("uvc: fourcc length", [{"name": "a", "source": "uvc", "device": 0, "fourcc": "MJPEG"}], "must be 4 characters"),
    ("uvc: width without height", [{"name": "a", "source": "uvc", "device": 0, "width": 640}],
     "set width and height together"),
    ("bad name", [{"name": "a b", "source": "uvc", "device": 0}], "cameras[0].name = 'a b'"),
    ("duplicate names", [{"name": "a", "source": "uvc", "device": 0}, {"name": "a", "source": "uvc", "device": 1}],
     "cameras[1].name = 'a': already the name of cameras[0]"),
    ("synthetic among real", [{"name": "a", "source": "uvc", "device": 0}, {"name": "b", "source": "synthetic"}],
     "cannot be mixed"),
    ("unknown kind", [{"name": "a", "source": "gopro"}], "cameras[0].source = 'gopro': allowed: aravis, uvc"),
    ("not a table", ["cam1"], "cameras[0] must be a table"),
]  # fmt: skip


@pytest.mark.parametrize(("rule", "tables", "message"), RULES, ids=[r[0] for r in RULES])
def test_rules_across_keys_are_refused_with_a_clear_message(rule: str, tables: list[Any], message: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(message)):
        parse_cameras(tables)


def test_every_validator_of_the_camera_kinds_has_a_case() -> None:
    """A new rule on a camera kind without a case in RULES fails here."""
    covered = {"_one_way_to_open": "aravis: one way", "_check": "uvc:", "_feature_value": "feature value",
               "_name": "bad name"}  # fmt: skip
    found = set()
    for model in CAMERA_KINDS.values():
        found |= set(model.__pydantic_decorators__.model_validators) - {"_check_order"}
        for field in model.model_fields.values():
            for meta in [*field.metadata, *get_args(field.annotation)]:
                func = getattr(meta, "func", None)
                if func is not None:
                    found.add(func.__name__)
            for arg in get_args(field.annotation):
                for meta in getattr(arg, "__metadata__", ()):
                    func = getattr(meta, "func", None)
                    if func is not None:
                        found.add(func.__name__)
    assert found <= set(covered) | {"_no_nul", "as_tuple"}, found
    for name, rule in covered.items():
        assert any(r[0].startswith(rule) or rule in r[0] for r in RULES), name
