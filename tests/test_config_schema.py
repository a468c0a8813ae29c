"""Every key of the shipped config.toml against its rule, in one table generated from the file itself.

For each key of ``mocapd/config.toml`` the schema must have a field (found through pydantic's JSON schema of
:class:`~mocapd.service.config.Config`, not through mocapd's own helpers), and each field of the schema must be
in the file. Each key is then given the values a fuzzer would try: wrong types, nan and ±inf, just below and
just above its range, 2**63, 10**400, arrays and tables one entry too large, a NUL in strings; each must be
refused with a message naming the key, and the range's own ends must be accepted. Every number must have both
bounds and every string, array and table a largest size (so no key can ask the daemon for more than it can
allocate). Rules across keys (``ordered`` pairs and model validators) and format rules (field validators)
are exercised from tables below, and a rule that no table exercises fails the test. Non-UTF-8 bytes are tried in
each string of the file itself.
"""

from __future__ import annotations

import copy
import math
import re
import tomllib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated, Any, NamedTuple, get_args, get_origin

import pytest
from pydantic import AfterValidator, BaseModel, BeforeValidator, PlainValidator, WrapValidator

from mocapd.core.keypoints import FORMATS
from mocapd.errors import ConfigError
from mocapd.protocols.ws_stream import ENCODINGS, STREAM_CONVENTIONS
from mocapd.service.config import DEFAULT_CONFIG, Config, config_document, load_config, parse_config
from mocapd.service.config.detector import ModelSection
from mocapd.service.config.schema import Section
from mocapd.service.config.websocket import WebSocketConfig

SHIPPED_TEXT = DEFAULT_CONFIG.read_text(encoding="utf-8")
SHIPPED: dict[str, Any] = tomllib.loads(SHIPPED_TEXT)
SCHEMA = Config.model_json_schema()
Path_ = tuple[str, ...]


class Leaf(NamedTuple):
    """A key of the shipped file (or a documented, commented-out one) and its JSON schema."""

    path: Path_
    value: Any
    schema: dict[str, Any]

    @property
    def key(self) -> str:
        return ".".join(self.path)


def resolve(s: dict[str, Any]) -> dict[str, Any]:
    """Follow ``$ref`` and drop the ``null`` branch of an optional value (TOML has no null)."""
    while "$ref" in s:
        s = SCHEMA["$defs"][s["$ref"].rsplit("/", 1)[-1]]
    if "anyOf" in s:
        branches = [b for b in s["anyOf"] if b.get("type") != "null"]
        if len(branches) == 1:
            return {**resolve(branches[0]), "nullable": True}
    return s


def is_table(s: dict[str, Any]) -> bool:
    return "properties" in s


def commented_keys() -> dict[Path_, None]:
    """Keys documented as comments (``# key = ...``) in a table whose schema has that key: keys with no default."""
    out: dict[Path_, None] = {}
    table: Path_ = ()
    for line in SHIPPED_TEXT.splitlines():
        header = re.match(r"^\[([A-Za-z0-9_.]+)\]", line)
        if header:
            table = tuple(header.group(1).split("."))
            continue
        m = re.match(r"^#\s*([a-z_][a-z0-9_]*)\s*=", line)
        if m and (schema := schema_at(table)) is not None and m.group(1) in schema.get("properties", {}):
            out[(*table, m.group(1))] = None
    return out


def schema_at(path: Path_) -> dict[str, Any] | None:
    s = resolve(SCHEMA)
    for part in path:
        props = s.get("properties", {})
        if part not in props:
            return None
        s = resolve(props[part])
    return s


def leaves_of(doc: dict[str, Any], schema: dict[str, Any], path: Path_, missing: list[str]) -> Iterator[Leaf]:
    for key, value in doc.items():
        props = schema.get("properties", {})
        if key not in props:
            missing.append(".".join((*path, key)))
            continue
        sub = resolve(props[key])
        if is_table(sub) and isinstance(value, dict):
            yield from leaves_of(value, sub, (*path, key), missing)
        else:
            yield Leaf((*path, key), value, sub)


def schema_keys(schema: dict[str, Any], path: Path_ = ()) -> Iterator[Path_]:
    for key, raw in schema.get("properties", {}).items():
        sub = resolve(raw)
        if is_table(sub):
            yield from schema_keys(sub, (*path, key))
        else:
            yield (*path, key)


#: the shipped file documents [[cameras]] as commented example tables, one per source kind, and has none: their
#: keys are checked (documented, ranged, refused when bad) by tests/test_config_cameras.py
DOCUMENTED_ELSEWHERE = {("cameras",)}

_MISSING: list[str] = []
LEAVES = list(leaves_of(SHIPPED, resolve(SCHEMA), (), _MISSING))
for _p in commented_keys():
    _s = schema_at(_p)
    assert _s is not None
    LEAVES.append(Leaf(_p, None, _s))


def test_every_key_of_the_shipped_file_has_a_rule_and_every_rule_a_documented_key() -> None:
    assert _MISSING == [], f"keys of config.toml without a field in the schema: {_MISSING}"
    documented = {leaf.path for leaf in LEAVES} | DOCUMENTED_ELSEWHERE
    undocumented = [".".join(p) for p in schema_keys(resolve(SCHEMA)) if p not in documented]
    assert undocumented == [], f"schema fields missing from mocapd/config.toml: {undocumented}"
    assert len(LEAVES) > 150


def test_the_shipped_file_is_the_defaults() -> None:
    """The header of config.toml says so: a file that leaves a key out gets the value shown."""
    assert load_config() == parse_config({})


# ---------------------------------------------------------------------------------------------- values


def bounds(s: dict[str, Any]) -> tuple[float, bool, float, bool]:
    """(low, low included, high, high included) of a number; the test fails where a bound is missing."""
    lo, lo_in = (s["minimum"], True) if "minimum" in s else (s.get("exclusiveMinimum"), False)
    hi, hi_in = (s["maximum"], True) if "maximum" in s else (s.get("exclusiveMaximum"), False)
    assert lo is not None and hi is not None, f"a number without both bounds: {s}"
    return lo, lo_in, hi, hi_in


def max_size(s: dict[str, Any], kind: str) -> int:
    keys = {"array": ("maxItems", "maxLength"), "object": ("maxProperties",), "string": ("maxLength",)}[kind]
    n = next((s[k] for k in keys if k in s), None)
    assert n is not None, f"an unbounded {kind}: {s}"
    return int(n)


def valid_example(s: dict[str, Any]) -> Any:
    """A value the schema accepts (for array items and table entries)."""
    if "enum" in s or "const" in s:
        return s.get("enum", [s.get("const")])[0]
    if "examples" in s:  # a string of a format (e.g. a Zenoh endpoint) shows a valid one in its schema
        return s["examples"][0]
    kind = s.get("type")
    if kind in ("integer", "number"):
        lo, lo_in, hi, _ = bounds(s)
        v = min(max(0, lo), hi)
        if v == lo and not lo_in:
            v = lo + 1 if kind == "integer" else math.nextafter(lo, math.inf)
        return int(v) if kind == "integer" else float(v)
    examples: dict[str, Callable[[], Any]] = {
        "boolean": lambda: False,
        "array": lambda: [valid_example(resolve(i)) for i in s.get("prefixItems", [s.get("items")])],
        "object": lambda: {},
    }
    return examples[kind]() if kind in examples else "x"  # a string, or an untyped value (given by FORMAT_CASES)


def accepts(s: dict[str, Any], value: Any) -> bool:
    """Whether a value of schema ``s`` (a number, a boolean or a choice) may be ``value`` (False where this
    test cannot say)."""
    if "enum" in s or "const" in s:
        return any(type(value) is type(a) and value == a for a in s.get("enum", [s.get("const")]))
    if s.get("type") == "boolean":
        return type(value) is bool
    kinds = {"integer": (int,), "number": (int, float)}.get(s.get("type", ""), ())
    if type(value) not in kinds or (type(value) is float and not math.isfinite(value)):
        return False
    lo, lo_in, hi, hi_in = bounds(s)
    return bool((lo <= value if lo_in else lo < value) and (value <= hi if hi_in else value < hi))


def bad_values(s: dict[str, Any], sample: Any = None) -> list[Any]:
    """What a fuzzer would try for a value of schema ``s`` (``sample``: a valid value of its items)."""
    if "anyOf" in s:  # e.g. a number or "auto": what each branch's fuzzer tries and no branch accepts
        branches = [resolve(b) for b in s["anyOf"]]
        tried = [v for b in branches for v in bad_values(b, sample)]
        unique_tried = list({repr((type(v), v)): v for v in tried}.values())
        return [v for v in unique_tried if not any(accepts(b, v) for b in branches)]
    out: list[Any] = [] if s.get("nullable") else [None]
    if "enum" in s or "const" in s:
        allowed = s.get("enum", [s.get("const")])
        choices = ["surely-not-allowed", 12345, 1.5, True, False, [], {}]
        return out + [c for c in choices if not any(type(c) is type(a) and c == a for a in allowed)]
    makers: dict[str, Callable[[], list[Any]]] = {
        "boolean": lambda: [1, 0, "true", 1.5, []],
        "integer": lambda: _bad_integers(s),
        "number": lambda: _bad_numbers(s),
        "string": lambda: _bad_strings(s),
        "array": lambda: _bad_arrays(s, sample),
        "object": lambda: _bad_tables(s),
    }
    assert s.get("type") in makers, f"no rule to exercise for schema {s}"
    return out + makers[s["type"]]()


def _bad_integers(s: dict[str, Any]) -> list[Any]:
    lo, lo_in, hi, hi_in = bounds(s)
    lo, hi = (lo if lo_in else lo + 1), (hi if hi_in else hi - 1)
    assert hi < 2**63, "an integer that may reach 2**63 cannot be a size the daemon allocates"
    return [lo - 1, hi + 1, 2**63, -(2**63) - 1, 10**400, float(lo), str(lo), True, math.nan, math.inf]


def _bad_numbers(s: dict[str, Any]) -> list[Any]:
    lo, lo_in, hi, hi_in = bounds(s)
    below = math.nextafter(lo, -math.inf) if lo_in else lo
    above = math.nextafter(hi, math.inf) if hi_in else hi
    huge = [v for v in (2**63, -(2**63)) if not lo <= v <= hi]
    return [below, above, math.nan, math.inf, -math.inf, 10**400, "1.0", True, [], *huge]


def _bad_strings(s: dict[str, Any]) -> list[Any]:
    n = max_size(s, "string")
    return [1, True, 1.5, [], "x" * (n + 1), "a\x00b", *([""] if s.get("minLength") else [])]


def _bad_arrays(s: dict[str, Any], sample: Any) -> list[Any]:
    n = max_size(s, "array")
    if "prefixItems" in s:
        items = [resolve(i) for i in s["prefixItems"]]
        good = [valid_example(i) for i in items]
        wrong = [[b, *good[1:]] for b in bad_values(items[0]) if b is not None]
        return ["x", 3, {}, [], good[:-1], [*good, good[0]], *wrong]
    item = resolve(s["items"])
    good = sample if sample is not None else valid_example(item)
    typed = "type" in item or "enum" in item  # an untyped item (a destination) has its FORMAT_CASES
    wrong = [[b] for b in bad_values(item) if b is not None][:6] if typed else []
    return ["x", 3, {}, [good] * (n + 1), *wrong]


def _bad_tables(s: dict[str, Any]) -> list[Any]:
    n = max_size(s, "object")
    value = resolve(s["additionalProperties"])
    entries = [{"K0": b} for b in bad_values(value) if b is not None][:6]
    return [3, "x", [], {f"{i:08X}": valid_example(value) for i in range(n + 1)}, *entries]


def ends(s: dict[str, Any]) -> list[Any]:
    """The values at the ends of a number's range (accepted)."""
    if "anyOf" in s:
        return [v for b in s["anyOf"] for v in ends(resolve(b))]
    kind = s.get("type")
    if kind not in ("integer", "number") or "enum" in s:
        return []
    lo, lo_in, hi, hi_in = bounds(s)
    if kind == "integer":
        return [lo if lo_in else lo + 1, hi if hi_in else hi - 1]
    return [lo if lo_in else math.nextafter(lo, math.inf), hi if hi_in else math.nextafter(hi, -math.inf)]


def shipped(path: Path_) -> Any:
    value: Any = SHIPPED
    for part in path:
        value = value[part]
    return value


def with_value(path: Path_, value: Any, base: dict[str, Any] | None = None) -> dict[str, Any]:
    doc = copy.deepcopy(SHIPPED if base is None else base)
    table = doc
    for part in path[:-1]:
        table = table.setdefault(part, {})
    table[path[-1]] = value
    return doc


def rejection(doc: dict[str, Any]) -> str | None:
    try:
        parse_config(doc)
    except ConfigError as exc:
        return str(exc)
    return None


@pytest.mark.parametrize("leaf", LEAVES, ids=lambda leaf: leaf.key)
def test_each_key_refuses_what_a_fuzzer_tries_and_names_itself(leaf: Leaf) -> None:
    sample = leaf.value[0] if isinstance(leaf.value, list) and leaf.value else None
    accepted, unnamed = [], []
    for bad in bad_values(leaf.schema, sample):
        message = rejection(with_value(leaf.path, bad))
        if message is None:
            accepted.append(bad)
        elif leaf.key not in message:
            unnamed.append((bad, message))
    assert accepted == [], f"{leaf.key} accepted {accepted}"
    assert unnamed == [], f"{leaf.key}: messages that do not name the key: {unnamed}"
    for good in ends(leaf.schema):
        message = rejection(with_value(leaf.path, good)) or ""
        assert f"{leaf.key} = " not in message or "; allowed" not in message, message


# ---------------------------------------------------------------------------------------------- rules across keys


def models_in(tp: Any) -> Iterator[type[BaseModel]]:
    """Every model class inside an annotation (nested Annotated, unions, tuples, dicts)."""
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        yield tp
        return
    for arg in get_args(tp):
        if get_origin(tp) is Annotated and arg is not get_args(tp)[0]:
            continue
        yield from models_in(arg)


def section_paths(model: type[BaseModel] = Config, path: Path_ = ()) -> Iterator[tuple[Path_, type[BaseModel]]]:
    yield path, model
    for name, field in model.model_fields.items():
        for sub in models_in(field.annotation):
            yield from section_paths(sub, (*path, name))


SECTIONS = [(p, m) for p, m in section_paths() if p[:1] not in {k[:1] for k in DOCUMENTED_ELSEWHERE}]
ORDERED = [(path, a, op, b) for path, model in SECTIONS if issubclass(model, Section) for a, op, b in model.ordered]


@pytest.mark.parametrize(("path", "a", "op", "b"), ORDERED, ids=lambda v: v if isinstance(v, str) else None)
def test_ordered_keys_are_refused_out_of_order_and_named(path: Path_, a: str, op: str, b: str) -> None:
    sa, sb = schema_at((*path, a)), schema_at((*path, b))
    assert sa is not None and sb is not None
    if sa.get("type") == "array":  # a pair: every coordinate
        item_a, item_b = resolve(sa["prefixItems"][0]), resolve(sb["prefixItems"][0])
        high, low = ends(item_a)[1], ends(item_b)[0]
        big, small = [high] * len(sa["prefixItems"]), [low] * len(sb["prefixItems"])
    else:
        big, small = ends(sa)[1], ends(sb)[0]
    same = shipped((*path, a))  # valid for a; for b too, and it keeps a's other order rules
    out_of_order = with_value((*path, b), small, with_value((*path, a), big))
    message = rejection(out_of_order)
    ka, kb = ".".join((*path, a)), ".".join((*path, b))
    assert message is not None and ka in message and kb in message and op in message, message
    equal = rejection(with_value((*path, b), same, with_value((*path, a), same)))
    if op == "<":
        assert equal is not None and ka in equal, f"{ka} = {kb} must be refused"
    else:
        assert equal is None, f"{ka} = {kb} must be accepted: {equal}"


class Case(NamedTuple):
    """Keys set (dotted) on top of the shipped file, and the keys the refusal must name (none: accepted)."""

    values: dict[str, Any]
    names: tuple[str, ...]


#: A lower-body suit (imu_set = "lower"): pelvis, thighs, shanks, feet.
_LOWER = {
    "00B40011": "Hips", "00B40012": "LeftUpperLeg", "00B40013": "LeftLowerLeg", "00B40014": "LeftFoot",
    "00B40015": "RightUpperLeg", "00B40016": "RightLowerLeg", "00B40017": "RightFoot",
}  # fmt: skip

#: (model, validator) -> cases; every model validator of the schema needs at least one refused case here
CROSS_CASES: dict[tuple[str, str], list[Case]] = {
    ("Config", "_ports_apart"): [
        Case({"websocket.port": 8765}, ("daemon.http_port", "websocket.port")),
        Case({"websocket.port": 8765, "daemon.http_port": 0}, ()),
        Case(
            {"imu.bridge.enabled": True, "udp.mvn.enabled": True, "udp.mvn.destinations": ["127.0.0.1:9773"]},
            ("imu.bridge.port", "udp.mvn.destinations"),
        ),
        Case({"imu.bridge.enabled": True, "udp.vmc.enabled": True, "udp.vmc.destinations": ["127.0.0.1:9774"]}, ()),
    ],
    ("ImuConfig", "_one_bone_per_sensor"): [
        Case(
            {
                "imu.assignment": {"AA:BB:CC:DD:EE:FF/0": "Hips"},
                "imu.slimevr.assignment": {"AA:BB:CC:DD:EE:FF/0": "Head"},
            },
            ("imu.assignment", "imu.slimevr.assignment"),
        ),
        Case({"imu.assignment": {"00B40011": "Hips"}, "imu.slimevr.assignment": {"AA:BB:CC:DD:EE:FF/0": "Head"}}, ()),
    ],
    ("VrChatStreamConfig", "_an_identity"): [
        Case({"udp.vrchat.subject": "all"}, ("udp.vrchat.subject",)),
        Case({"udp.vrchat.subject": "suit:suit0"}, ()),
    ],
    ("ImuConfig", "_assignment_forms_the_set"): [
        Case({"imu.imu_set": "6", "imu.assignment": {"00B40011": "Hips"}}, ("imu.assignment", "imu.imu_set")),
        Case({"imu.imu_set": "", "imu.assignment": {"00B40011": "Hips"}}, ()),
        Case({"imu.imu_set": "lower", "imu.assignment": {"00B40011": "Hips"}}, ("imu.assignment", "imu.imu_set")),
        Case({"imu.imu_set": "lower", "imu.assignment": {**_LOWER, "00B40018": "Spine2"}}, ()),
        Case(
            {"imu.imu_set": "lower", "imu.assignment": {**_LOWER, "00B40018": "Spine2", "00B40019": "Spine3"}},
            ("imu.assignment", "imu.imu_set"),
        ),
    ],
    ("AwindaSection", "_complete_when_enabled"): [
        Case({"imu.awinda.experimental": True}, ("imu.awinda.experimental", "imu.awinda.path")),
        Case(
            {"imu.awinda.experimental": True, "imu.awinda.path": "/dev/ttyUSB0", "imu.awinda.delta_q_scale": 1e-6},
            ("imu.awinda.experimental", "imu.awinda.delta_v_scale"),
        ),
        Case(
            {
                "imu.awinda.experimental": True,
                "imu.awinda.path": "/dev/ttyUSB0",
                "imu.awinda.delta_q_scale": 1e-6,
                "imu.awinda.delta_v_scale": 1e-6,
            },
            (),
        ),
    ],
    ("VmcStreamConfig", "_one_subject_per_avatar"): [
        Case({"udp.vmc.subjects": ["suit:a", "suit:b"]}, ("udp.vmc.subjects", "udp.vmc.destinations")),
        Case({"udp.vmc.subjects": ["suit:a", "suit:b"], "udp.vmc.destinations": ["127.0.0.1:1", "127.0.0.1:2"]}, ()),
    ],
    ("UdpConfig", "_loopback_unless_allowed"): [
        Case({"udp.mvn.destinations": ["10.0.0.7:9763"]}, ("udp.mvn.destinations", "udp.allow_remote")),
        Case({"udp.vmc.destinations": ["192.168.1.2:39539"]}, ("udp.vmc.destinations", "udp.allow_remote")),
        Case({"udp.vmc.destinations": ["192.168.1.2:39539"], "udp.allow_remote": True}, ()),
    ],
    ("ZenohConfig", "_secured_off_loopback"): [
        Case({"zenoh.listen": ["tcp/0.0.0.0:7447"]}, ("zenoh.listen", "zenoh.user", "zenoh.users_file")),
        Case(
            {"zenoh.listen": ["tcp/10.0.0.1:7447"], "zenoh.user": "a", "zenoh.password_file": "p"},
            ("zenoh.listen", "zenoh.users_file"),
        ),
        Case(
            {
                "zenoh.listen": ["tcp/10.0.0.1:7447"],
                "zenoh.user": "a",
                "zenoh.password_file": "p",
                "zenoh.users_file": "u",
            },
            (),
        ),
        Case({"zenoh.listen": [], "zenoh.connect": ["tcp/10.0.0.1:7447"]}, ("zenoh.connect", "zenoh.user")),
        Case(
            {"zenoh.listen": [], "zenoh.connect": ["tcp/10.0.0.1:7447"], "zenoh.user": "a", "zenoh.password_file": "p"},
            (),
        ),
        Case({"zenoh.user": "a"}, ("zenoh.user", "zenoh.password_file")),
        Case({"zenoh.listen": ["tls/10.0.0.1:7447"]}, ("zenoh.listen", "zenoh.tls_root_ca")),
        Case(
            {"zenoh.listen": ["tls/10.0.0.1:7447"], "zenoh.tls_root_ca": "ca.pem"},
            ("zenoh.listen", "zenoh.tls_cert", "zenoh.tls_key"),
        ),
        Case(
            {
                "zenoh.listen": ["tls/10.0.0.1:7447"],
                "zenoh.tls_root_ca": "ca.pem",
                "zenoh.tls_cert": "c.pem",
                "zenoh.tls_key": "k.pem",
            },
            (),
        ),
        # issue 34: TLS off loopback is mutual: a connector that only knows the (public) CA certificate is refused
        Case(
            {"zenoh.listen": [], "zenoh.connect": ["tls/10.0.0.1:7447"], "zenoh.tls_root_ca": "ca.pem"},
            ("zenoh.connect", "zenoh.tls_cert"),
        ),
        Case(
            {
                "zenoh.listen": [],
                "zenoh.connect": ["tls/10.0.0.1:7447"],
                "zenoh.tls_root_ca": "ca.pem",
                "zenoh.tls_cert": "c.pem",
                "zenoh.tls_key": "k.pem",
            },
            (),
        ),
        Case({"zenoh.tls_cert": "c.pem"}, ("zenoh.tls_cert", "zenoh.tls_key")),
        Case({"zenoh.listen": ["tcp/[::1]:7447", "tcp/127.0.0.2:7447"]}, ()),
    ],
    ("ZenohConfig", "_identities_checkable"): [
        Case({"zenoh.identities": {"hostA": "user:hostA"}}, ("zenoh.identities", "zenoh.users_file")),
        Case(
            {"zenoh.identities": {"hostA": "user:hostA"}, "zenoh.mode": "client", "zenoh.users_file": "u"},
            ("zenoh.identities", "zenoh.mode"),
        ),
        Case({"zenoh.identities": {"hostA": "user:hostA"}, "zenoh.users_file": "u"}, ()),
        Case({"zenoh.identities": {"hostA": "cert:hostA"}}, ("zenoh.identities", "zenoh.listen", "zenoh.tls_cert")),
        Case(
            {
                "zenoh.identities": {"hostA": "cert:hostA"},
                "zenoh.listen": ["tls/127.0.0.1:7447"],
                "zenoh.tls_root_ca": "ca.pem",
                "zenoh.tls_cert": "c.pem",
                "zenoh.tls_key": "k.pem",
            },
            (),
        ),
    ],
    ("WebSocketConfig", "_token_off_loopback"): [
        Case({"websocket.host": "0.0.0.0"}, ("websocket.host", "websocket.token")),
        Case({"websocket.host": "192.168.1.5", "websocket.token": "x" * 15}, ("websocket.host", "websocket.token")),
        Case({"websocket.host": "192.168.1.5", "websocket.token": "x" * 16}, ()),
        Case({"websocket.host": "::1"}, ()),
    ],
}


def apply(values: dict[str, Any]) -> dict[str, Any]:
    doc = copy.deepcopy(SHIPPED)
    for key, value in values.items():
        doc = with_value(tuple(key.split(".")), value, doc)
    return doc


def model_validators() -> set[tuple[str, str]]:
    """The cross-key rules of the schema: ``mode="after"`` model validators, less the generic ``ordered`` one."""
    out = set()
    for _, model in SECTIONS:
        for name, dec in model.__pydantic_decorators__.model_validators.items():
            if dec.info.mode == "after" and name != "_check_order":
                out.add((model.__name__, name))
    return out


def test_every_rule_across_keys_has_cases() -> None:
    assert model_validators() == set(CROSS_CASES)
    for cases in CROSS_CASES.values():
        assert any(c.names for c in cases)


@pytest.mark.parametrize(
    "case", [c for cases in CROSS_CASES.values() for c in cases], ids=lambda c: ",".join(f"{k}" for k in c.values)
)
def test_rules_across_keys(case: Case) -> None:
    message = rejection(apply(case.values))
    if not case.names:
        assert message is None, message
        return
    assert message is not None, f"accepted: {case.values}"
    for key in case.names:
        assert key in message, message


# ---------------------------------------------------------------------------------------------- format rules

#: validator function -> values it must refuse (dotted key, bad value); generic ones are exercised for every key
FORMAT_CASES: dict[str, list[tuple[str, Any]]] = {
    "_provider": [("detector.providers", ["cdua"]), ("detector.providers", ["Cuda Execution Provider"])],
    "_canvas": [("detector.packing.canvas_width", 1000), ("detector.packing.canvas_height", 33)],
    "_tile_height": [("detector.packing.max_tile_height", 0.05)],
    "_odd": [("detector.tracking.window_px", 12)],
    "_factor": [("detector.tracking.downsample", 3)],
    "_assignment": [
        ("imu.assignment", {"00B40011": "Pelvis"}),
        ("imu.assignment", {"xyz": "Hips"}),
        ("imu.assignment", {"00B40011": "Hips", "00B40012": "Hips"}),
    ],
    "_sensor_id": [("daemon.offsets.imus", {"xyz": 0.1}), ("daemon.offsets.imus", {"00B4001Z": 0.1})],
    "_user_height": [("udp.vrchat.user_height_m", 0.3), ("udp.vrchat.user_height_m", 0.49)],
    "_ip_literal": [("imu.slimevr.host", "my-laptop"), ("imu.slimevr.host", "192.168.1")],
    "_role": [("udp.vrchat.trackers", ["hips"]), ("udp.vrchat.trackers", ["left_hand"])],
    "_slimevr_assignment": [
        ("imu.slimevr.assignment", {"00B421E6": "Hips"}),
        ("imu.slimevr.assignment", {"AA:BB:CC:DD:EE:FF/0": "Pelvis"}),
    ],
    "_name": [("daemon.offsets.cameras", {"cam 1": 0.1}), ("daemon.offsets.cameras", {"c" * 33: 0.1})],
    "_destination": [
        ("udp.mvn.destinations", ["127.0.0.1"]),
        ("udp.mvn.destinations", ["example.com:9763"]),
        ("udp.mvn.destinations", ["127.0.0.1:0"]),
        ("udp.mvn.destinations", ["127.0.0.1:65536"]),
        ("udp.mvn.destinations", ["127.0.0.1:+1"]),
        ("udp.vmc.destinations", ["239.1.1.1:1"]),
        ("udp.vmc.destinations", ["0.0.0.0:1"]),
        ("udp.vmc.destinations", [1]),
    ],
    "_identity": [("udp.mvn.subjects", ["all"]), ("udp.mvn.character_ids", {"all": 1})],
    "_subjects": [("udp.mvn.subjects", "everyone"), ("udp.vmc.subjects", [])],
    "_distinct_ids": [("udp.mvn.character_ids", {"suit:a": 1, "suit:b": 1})],
    "_distinct_names": [("udp.rokoko.actor_names", {"suit:a": "Alice", "suit:b": "Alice"})],
    "_host": [("websocket.host", "example.com"), ("websocket.host", "")],
    "_token": [("websocket.token", "a b"), ("websocket.token", "tab\there")],
    "_web_host": [
        ("web.allowed_hosts", ["evil.example:8766"]),
        ("web.allowed_hosts", ["a b"]),
        ("web.allowed_hosts", ["127.0.0.1"]),
        ("web.allowed_hosts", ["-x.example"]),
    ],
    "_origin": [
        ("web.allowed_origins", ["null"]),
        ("web.allowed_origins", ["http://localhost:3000/"]),
        ("web.allowed_origins", ["file://"]),
        ("web.allowed_origins", ["http://localhost:99999"]),
        ("web.allowed_origins", ["localhost:3000"]),
        ("web.allowed_origins", ["http://a.example/x"]),
    ],
    "_endpoint": [
        ("zenoh.listen", ["127.0.0.1:7447"]),
        ("zenoh.listen", ["udp/127.0.0.1:7447"]),
        ("zenoh.listen", ["tcp/localhost:7447"]),
        ("zenoh.connect", ["tcp/127.0.0.1:65536"]),
        ("zenoh.connect", ["tcp/300.0.0.1:7447"]),
        ("zenoh.connect", ["tcp/::1:7447"]),
    ],
    "_host_name": [("zenoh.host", "a b"), ("zenoh.rig", "r/x"), ("zenoh.host", "h" * 33)],
    "_speaker_identity": [
        ("zenoh.identities", {"hostA": "hostA"}),
        ("zenoh.identities", {"hostA": "group:hostA"}),
        ("zenoh.identities", {"hostA": "user:"}),
        ("zenoh.identities", {"hostA": "user:a b"}),
        ("zenoh.identities", {"hostA": "cert:../x" + "y" * 64}),
    ],
}
#: validators exercised for every key that has them: a TOML array as a tuple (no rule), NUL refused in every
#: string (bad_values), ``unique`` (test_arrays_of_distinct_entries_refuse_repeats)
GENERIC = {"as_tuple", "_no_nul", "unique"}


def validators_in(tp: Any, meta: list[Any]) -> Iterator[str]:
    for m in meta:
        if isinstance(m, AfterValidator | BeforeValidator | PlainValidator | WrapValidator):
            yield m.func.__name__
        elif hasattr(m, "metadata"):
            yield from validators_in(None, list(m.metadata))
    if tp is None or (isinstance(tp, type) and issubclass(tp, BaseModel)):
        return
    if get_origin(tp) is Annotated:
        args = get_args(tp)
        yield from validators_in(args[0], list(args[1:]))
        return
    for arg in get_args(tp):
        yield from validators_in(arg, [])


def field_validators() -> dict[str, set[str]]:
    """Validator function name -> dotted keys of the fields that use it."""
    out: dict[str, set[str]] = {}
    for path, model in SECTIONS:
        for name, field in model.model_fields.items():
            for func in validators_in(field.annotation, list(field.metadata)):
                out.setdefault(func, set()).add(".".join((*path, name)))
    return out


def test_every_format_rule_has_cases() -> None:
    assert set(field_validators()) == set(FORMAT_CASES) | GENERIC


@pytest.mark.parametrize(
    ("key", "bad"), [c for cases in FORMAT_CASES.values() for c in cases], ids=lambda v: str(v)[:40]
)
def test_format_rules_refuse_and_name_the_key(key: str, bad: Any) -> None:
    message = rejection(apply({key: bad}))
    assert message is not None and key in message, f"{key} = {bad!r}: {message}"


@pytest.mark.parametrize("key", sorted(field_validators()["unique"]))
def test_arrays_of_distinct_entries_refuse_repeats(key: str) -> None:
    leaf = next(leaf for leaf in LEAVES if leaf.key == key)
    listed = isinstance(leaf.value, list) and leaf.value
    item = leaf.value[0] if listed else valid_example(resolve(leaf.schema["items"]))
    message = rejection(apply({key: [item, item]}))
    assert message is not None and key in message and "twice" in message, message


def test_choices_of_the_schema_are_those_of_the_code() -> None:
    """Literal choices are spelled out for the schema; they must stay those of the layers below."""
    assert set(get_args(WebSocketConfig.model_fields["encoding"].annotation)) == set(ENCODINGS)
    assert set(get_args(WebSocketConfig.model_fields["convention"].annotation)) == set(STREAM_CONVENTIONS)
    assert set(get_args(ModelSection.model_fields["keypoint_format"].annotation)) == set(FORMATS)


def test_a_config_survives_its_session_manifest_copy() -> None:
    """Sessions record the configuration as a document; reading it back gives the same Config."""
    doc = apply({
        "udp.mvn.subjects": ["suit:a", "track:2"], "udp.mvn.character_ids": {"suit:a": 3},
        "udp.vmc.destinations": ["localhost:39540"], "imu.assignment": {"00b40011": "Hips"},
        "imu.awinda.delta_q_scale": 1e-6, "daemon.offsets.imus": {"00b421e6": -0.004},
        "tracking.enrolment.start_positions": [[0.5, 1.0]], "solver.terms.floor.loss": "huber",
    })  # fmt: skip
    for cfg in (load_config(), parse_config(doc)):
        assert parse_config(config_document(cfg)) == cfg
    cfg = parse_config(doc)
    assert cfg.imu.assignment == {"00B40011": "Hips"} and cfg.daemon.imu_offsets_s == {"00B421E6": -0.004}
    udp = config_document(cfg)["udp"]
    assert udp["mvn"]["subjects"] == ["suit:a", "track:2"] and "subjects" not in udp["vmc"]  # "all": the default
    assert udp["vmc"]["destinations"] == ["127.0.0.1:39540"]


# ---------------------------------------------------------------------------------------------- bytes of the file


def line_of(path: Path_) -> int:
    """0-based line of ``key = ...`` for a key of the shipped file."""
    table: Path_ = ()
    for i, line in enumerate(SHIPPED_TEXT.splitlines()):
        header = re.match(r"^\[([A-Za-z0-9_.]+)\]", line)
        if header:
            table = tuple(header.group(1).split("."))
        elif table == path[:-1] and re.match(rf"^{path[-1]}\s*=", line):
            return i
    raise AssertionError(f"{'.'.join(path)} not found in config.toml")


def holds_strings(leaf: Leaf) -> bool:
    if isinstance(leaf.value, str):
        return True
    if not isinstance(leaf.value, list) or "items" not in leaf.schema:
        return False
    return all(isinstance(v, str) for v in leaf.value) and resolve(leaf.schema["items"]).get("type") in ("string", None)


STRING_LEAVES = [leaf for leaf in LEAVES if holds_strings(leaf)]


@pytest.mark.parametrize("leaf", STRING_LEAVES, ids=lambda leaf: leaf.key)
def test_a_non_utf8_byte_in_a_string_names_the_file_line_and_key(leaf: Leaf, tmp_path: Path) -> None:
    lines = SHIPPED_TEXT.encode("utf-8").split(b"\n")
    n = line_of(leaf.path)
    key, _, rest = lines[n].partition(b"=")
    quote = rest.find(b'"')
    rest = rest[: quote + 1] + b"\xff" + rest[quote + 1 :] if quote >= 0 else b' ["\xff"]'
    lines[n] = key + b"=" + rest
    path = tmp_path / "config.toml"
    path.write_bytes(b"\n".join(lines))
    with pytest.raises(ConfigError) as err:
        load_config(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and "not UTF-8" in message
    assert f"line {n + 1}," in message and leaf.path[-1] in message


# ---------------------------------------------------------------------------------------------- documentation

_INTERVAL = re.compile(r"([\[(])\s*(-?[\d.]+(?:e[+-]?\d+)?)\s*,\s*(-?[\d.]+(?:e[+-]?\d+)?)\s*([\])])")
_DOTS = re.compile(r"(?<![\d.])(-?\d+(?:\.\d+)?(?:e[+-]?\d+)?)\.\.(-?\d+(?:\.\d+)?(?:e[+-]?\d+)?)")


def documentation(path: Path_) -> str:
    """The comments that document a key: those of its group of lines (keys written together share the comment
    above them), its own and continuation comments, and the comments introducing its table and the tables above."""
    lines = SHIPPED_TEXT.splitlines()
    tables = [preamble(path[:k]) for k in range(1, len(path))]
    if preamble(path):  # a table of entries written as [table] (imu.assignment)
        return "\n".join([*tables, preamble(path)])
    n = commented_line(path) if path in commented_keys() else line_of(path)
    group = []
    for line in reversed(lines[:n]):  # up to a blank line or a table header
        if not line.strip() or line.startswith("["):
            break
        group.append(line if line.startswith("#") else "")
    own = [lines[n] if path in commented_keys() else lines[n].partition("#")[2]]
    for line in lines[n + 1 :]:
        if not re.match(r"^\s+#", line):
            break
        own.append(line)
    return "\n".join([*tables, *reversed(group), *own])


def preamble(table: Path_) -> str:
    """The comment block right above ``[table]`` and the header's own comment ("" for a table without header)."""
    lines = SHIPPED_TEXT.splitlines()
    header = f"[{'.'.join(table)}]"
    for i, line in enumerate(lines):
        if line.split("#")[0].strip() == header:
            above = []
            for prev in reversed(lines[:i]):
                if not prev.startswith("#"):
                    break
                above.append(prev)
            return "\n".join([*reversed(above), line.partition("#")[2]])
    return ""


def commented_line(path: Path_) -> int:
    table: Path_ = ()
    for i, line in enumerate(SHIPPED_TEXT.splitlines()):
        header = re.match(r"^\[([A-Za-z0-9_.]+)\]", line)
        if header:
            table = tuple(header.group(1).split("."))
        elif table == path[:-1] and re.match(rf"^#\s*{path[-1]}\s*=", line):
            return i
    raise AssertionError(path)


def documented_ranges(text: str) -> set[tuple[float, bool, float, bool]]:
    found = {(float(a), o == "[", float(b), c == "]") for o, a, b, c in _INTERVAL.findall(text)}
    return found | {(float(a), True, float(b), True) for a, b in _DOTS.findall(text)}


@pytest.mark.parametrize("leaf", LEAVES, ids=lambda leaf: leaf.key)
def test_each_key_is_documented_with_what_the_schema_allows(leaf: Leaf) -> None:
    """The comment of a key in config.toml states the range the schema enforces, and its choices."""
    text = documentation(leaf.path)
    assert text.strip(), f"{leaf.key} has no comment in config.toml"
    s = leaf.schema
    item = resolve(s["prefixItems"][0]) if "prefixItems" in s else None
    numeric = (
        item if item is not None else resolve(s.get("additionalProperties", {})) if "additionalProperties" in s else s
    )
    if numeric.get("type") in ("integer", "number") and "enum" not in numeric:
        lo, lo_in, hi, hi_in = bounds(numeric)
        assert (float(lo), lo_in, float(hi), hi_in) in documented_ranges(text), (
            f"{leaf.key}: the comment does not state the range {'[' if lo_in else '('}{lo}, {hi}{']' if hi_in else ')'}"
            f":\n{text}"
        )
    for choice in s.get("enum", []):
        assert f'"{choice}"' in text, f"{leaf.key}: the comment does not list {choice!r}:\n{text}"


@pytest.mark.parametrize(
    ("raw", "expected"),
    [
        # Found by tests/test_fuzz_files.py: `listen = [[1, 2], [3]]` was two lines for one key.
        ({"zenoh": {"listen": [[1, 2], [3]]}},
         'zenoh.listen[0] = [1, 2], zenoh.listen[1] = [3]; allowed: "tcp/<ip>:<port>" or "tls/<ip>:<port>"'),
        ({"detector": {"providers": ["cdua", "xx"]}},
         "detector.providers[0] = 'cdua', detector.providers[1] = 'xx': not a provider; allowed: "),
        ({"detector": {"providers": ["cdua", 1]}}, "detector.providers[0] = 'cdua': not a provider; allowed: "),
    ],
)  # fmt: skip
def test_bad_items_of_one_array_are_one_line(raw: dict[str, Any], expected: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(raw)
    message = str(info.value)
    assert "\n" not in message and message.startswith(expected), message
    # Another bad key is its own line.
    with pytest.raises(ConfigError) as info:
        parse_config({**raw, "daemon": {"rate_hz": -1}})
    assert len(str(info.value).splitlines()) == 2
