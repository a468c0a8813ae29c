"""The config schema's common ground: pydantic models that say what each key of config.toml may hold.

Every section is a frozen :class:`Section` (unknown keys rejected, no type coercion, no NaN or infinity), so a
typo, a string where a number belongs, ``nan`` or an out-of-range value is refused where the file is read, never
half-way through a run. :func:`validate` turns pydantic's errors into mocapd's messages, one line per problem,
each naming the dotted key, the value and what is allowed::

    cameras[1].exposure_us = -5.0; allowed: a number in (0, 1e+07]
    unknown key daemon.latency; allowed: body_size_s, http_host, ...
    tracking.enrolment.volume_min = [3.0, -2.5] must be < tracking.enrolment.volume_max = [2.5, 2.5] (each coordinate)

Rules live beside the fields: types, ``Field(ge=..., le=...)`` ranges (every number has both bounds, so no
count or size can ask for more than the daemon can allocate), ``max_length`` of arrays, tables and strings,
``Literal`` choices; an order between two keys of a table is declared in its ``ordered``; any other rule across
keys is a model validator raising :class:`RuleError`, which names each key it involves.

Why pydantic: the rules of ~150 keys are declared once, beside their types and defaults, instead of a
hand-written check per key; the schema can be walked by tests (every key of the shipped file must have a rule,
and every rule is exercised with bad values).
"""

from __future__ import annotations

import dataclasses
import json
import re
import reprlib
import types
import typing
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal, NamedTuple, Self, TypeVar, get_args, get_origin

import annotated_types as at
from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, model_validator
from pydantic.fields import FieldInfo

from mocapd.errors import ConfigError

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

M = TypeVar("M", bound=BaseModel)
_D = TypeVar("_D", bound="DataclassInstance")
T = TypeVar("T")

MAX_PATH = 4096
"""Longest path a config key may hold (Linux PATH_MAX)."""
MAX_TEXT = 256
"""Longest name, address or other short string a config key may hold."""


class RuleError(ValueError):
    """A rule across keys of one table is broken: ``template`` names them as ``{0}``, ``{1}``, ...

    In messages each ``{i}`` becomes ``<dotted key> = <value>``, e.g.
    ``daemon.restart_max_s = 1.0 must be >= daemon.restart_min_s = 5.0``.
    """

    def __init__(self, template: str, *keys: str, values: tuple[object, ...]) -> None:
        super().__init__(template.format(*(f"{k} = {show(v)}" for k, v in zip(keys, values, strict=True))))
        self.template = template
        self.keys = keys
        self.values = values


class Allowed(NamedTuple):
    """What a key allows, in words, where the type alone does not say it (``Annotated[str, Allowed(...)]``)."""

    text: str


class Section(BaseModel):
    """Base of every config table: frozen, strict types, unknown keys and non-finite numbers refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    ordered: ClassVar[tuple[tuple[str, Literal["<", "<="], str], ...]] = ()
    """Order rules between keys of this table: ``(a, "<=", b)`` = a is at most b (arrays: element-wise)."""

    @model_validator(mode="after")
    def _check_order(self) -> Self:
        for a, op, b in self.ordered:
            va, vb = getattr(self, a), getattr(self, b)
            if va is None or vb is None:
                continue
            xs, ys = (va, vb) if isinstance(va, tuple) else ((va,), (vb,))
            if not all(x < y if op == "<" else x <= y for x, y in zip(xs, ys, strict=True)):
                each = " (each coordinate)" if isinstance(va, tuple) else ""
                raise RuleError(f"{{0}} must be {op} {{1}}{each}", a, b, values=(va, vb))
        return self

    def build(self, cls: type[_D]) -> _D:
        """The dataclass ``cls`` (a library's options) from this table's keys of the same names."""
        return cls(**{f.name: getattr(self, f.name) for f in dataclasses.fields(cls)})


def as_tuple(value: object) -> object:
    """TOML arrays arrive as lists; the schema keeps immutable tuples (strict mode takes no list for a tuple)."""
    return tuple(value) if isinstance(value, list) else value


def _no_nul(value: str) -> str:
    if "\x00" in value:
        raise ValueError("must not contain a NUL character (\\u0000)")
    return value


def unique(values: tuple[T, ...]) -> tuple[T, ...]:
    """An array whose entries all differ (``AfterValidator(unique)``)."""
    seen: set[T] = set()
    for v in values:
        if v in seen:
            shown = show(v) if isinstance(v, str | int | float | tuple) else show(str(v))
            raise ValueError(f"lists {shown} twice; allowed: distinct entries")
        seen.add(v)
    return values


#: a TOML array stored as a tuple: ``Seq[int]`` accepts ``[1, 2, 3]``; bound its length with ``Field(max_length=)``
Seq = Annotated[tuple[T, ...], BeforeValidator(as_tuple)]
#: a file system path (no NUL, at most MAX_PATH characters)
PathStr = Annotated[str, Field(max_length=MAX_PATH), AfterValidator(_no_nul)]
#: a short string: a name, an address, a token (no NUL, at most MAX_TEXT characters)
Text = Annotated[str, Field(max_length=MAX_TEXT), AfterValidator(_no_nul)]
#: a coordinate on the floor or in the volume, metres
Coord = Annotated[float, Field(ge=-1000.0, le=1000.0)]
#: two coordinates, e.g. ``[x, z]`` (metres)
Pair = Annotated[tuple[Coord, Coord], BeforeValidator(as_tuple)]


def validate(model: type[M], data: object, where: str = "") -> M:
    """``data`` (a parsed TOML table) as ``model``, or :class:`~mocapd.errors.ConfigError` naming every bad key.

    Parameters
    ----------
    model : type of Section
    data : object
        The table (or anything a user wrote there).
    where : str
        Dotted path of the table in the file (``"daemon"``), prefixed to every key in messages.
    """
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError("\n".join(error_lines(exc, model, where))) from None


def error_lines(exc: ValidationError, model: type[BaseModel], where: str = "") -> list[str]:
    """One message per bad key: ``key = value; allowed: what``, ``unknown key k; allowed: ...``, or a rule."""
    # A line, or the bad items of one array, which share one line (one key, one line): complaint -> its items, in
    # order, rendered ``k[0] = a, k[2] = b; allowed: ...``, items with another complaint after `` | ``.
    lines: list[str | dict[str, list[str]]] = []
    items: dict[tuple[str | int, ...], dict[str, list[str]]] = {}  # array path -> its entry in ``lines``

    def group_item(path: tuple[str | int, ...], item: str, tail: str) -> None:
        by_tail = items.get(path[:-1])
        if by_tail is None:
            by_tail = items[path[:-1]] = {}
            lines.append(by_tail)
        by_tail.setdefault(tail, []).append(item)

    errors = exc.errors(include_url=False)
    with_bad_items = {tuple(e["loc"][:-1]) for e in errors if e["loc"] and isinstance(e["loc"][-1], int)}
    for err in errors:
        if err["type"] == "too_short" and tuple(err["loc"]) in with_bad_items:
            continue  # pydantic counts the valid items only: the bad item's own error says it all
        at_ = locate(model, tuple(err["loc"]))
        key = dotted(where, at_.path)
        kind = err["type"]
        cause = (err.get("ctx") or {}).get("error")
        if isinstance(cause, RuleError):
            keys = [dotted(where, (*at_.path, *k.split("."))) for k in cause.keys]
            lines.append(cause.template.format(*(f"{k} = {show(v)}" for k, v in zip(keys, cause.values, strict=True))))
        elif kind == "extra_forbidden":
            allowed = fields_at(model, at_.path[:-1])
            hint = f"; allowed: {', '.join(allowed)}" if allowed else ""
            what = "section" if not where and len(at_.path) == 1 else "key"
            lines.append(f"unknown {what} {key}{hint}")
        elif kind == "missing" and at_.path and isinstance(at_.path[-1], int):  # an array too short
            whole = locate(model, tuple(err["loc"])[:-1])
            lines.append(f"{dotted(where, whole.path)} = {show(err.get('input'))}; allowed: {whole.allowed}")
        elif kind == "missing":
            lines.append(f"{key} is required")
        elif kind in ("value_error", "assertion_error") and isinstance(err.get("input"), dict) and at_.is_table:
            lines.append(f"{key}: {_message(err)}")  # a rule of a whole table (a model validator)
        elif kind in ("value_error", "assertion_error") and at_.path and isinstance(at_.path[-1], int):
            group_item(at_.path, f"{key} = {show(err.get('input'))}", f": {_message(err)}")
        elif kind in ("value_error", "assertion_error"):
            lines.append(f"{key} = {show(err.get('input'))}: {_message(err)}")
        elif at_.is_key:
            lines.append(f"{key} (a key) is not allowed; allowed keys: {at_.allowed or _message(err)}")
        elif at_.path and isinstance(at_.path[-1], int):
            group_item(at_.path, f"{key} = {show(err.get('input'))}", f"; allowed: {at_.allowed or _message(err)}")
        else:
            lines.append(f"{key} = {show(err.get('input'))}; allowed: {at_.allowed or _message(err)}")
    rendered = (
        line if isinstance(line, str) else " | ".join(f"{', '.join(dict.fromkeys(bad))}{t}" for t, bad in line.items())
        for line in lines
    )
    return list(dict.fromkeys(rendered))  # a union reports each member's failure: one line is enough


class Located(NamedTuple):
    """Where a pydantic error location points in the schema."""

    path: tuple[str | int, ...]
    """The keys (and array indices) of the location, without pydantic's union and validator tags."""
    allowed: str
    """What the key allows, in words ("" when the schema says nothing more specific than pydantic)."""
    is_key: bool
    """The error is about a table key itself (``[key]``), not its value."""
    is_table: bool
    """The location is a table of the schema (a model)."""


def locate(model: type[BaseModel], loc: tuple[int | str, ...]) -> Located:
    """Follow ``loc`` (pydantic's error location) through the schema from ``model``."""
    tp: Any = model
    meta: list[Any] = []  # bounds and lengths declared on the current field
    path: list[str | int] = []
    is_key = False
    i = 0
    while i < len(loc):
        part = loc[i]
        tp, more = _unwrap(tp)
        meta = [*meta, *more]
        origin = get_origin(tp)
        sub = _model_of(tp)
        if sub is not None and isinstance(part, str) and part in sub.model_fields:
            field = sub.model_fields[part]
            tp, meta = field.annotation, list(field.metadata)
            path.append(part)
        elif origin is tuple and isinstance(part, int):
            args = get_args(tp)
            tp, meta = (args[0] if len(args) == 2 and args[1] is Ellipsis else args[min(part, len(args) - 1)]), []
            path.append(part)
        elif origin is dict and isinstance(part, str):
            key_t, value_t = get_args(tp)
            path.append(part)
            if i + 1 < len(loc) and loc[i + 1] == "[key]":
                tp, meta, is_key = key_t, [], True
                i += 1
            else:
                tp, meta = value_t, []
        elif isinstance(part, str) and (_is_union(tp) or part.startswith(("function-", "tagged-union"))):
            pass  # a union member's or a validator's tag, not a key: the union is described as a whole
        else:
            path.append(part)
            tp, meta = None, []
        i += 1
    allowed = describe(tp, meta) if tp is not None else ""
    return Located(tuple(path), allowed, is_key, _model_of(tp) is not None)


def dotted(where: str, path: tuple[str | int, ...]) -> str:
    """``("cameras", 1, "gain_db")`` under ``""`` -> ``cameras[1].gain_db``; keys quoted as TOML needs."""
    out = where
    for part in path:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            name = part if re.fullmatch(r"[A-Za-z0-9_-]+", part) else json.dumps(part)
            out = f"{out}.{name}" if out else name
    return out


def fields_at(model: type[BaseModel], path: tuple[str | int, ...]) -> list[str]:
    """The keys allowed in the table at ``path`` below ``model`` (empty when it is not a table of a model)."""
    current: Any = model
    for part in path:
        sub = _model_of(current)
        if sub is not None and isinstance(part, str) and part in sub.model_fields:
            current = sub.model_fields[part].annotation
        elif isinstance(part, int):
            current = _item_type(current)
        else:
            return []
    final = _model_of(current)
    return sorted(final.model_fields) if final is not None else []


def describe(tp: Any, metadata: list[Any] | None = None) -> str:
    """What a value of type ``tp`` with ``metadata`` (bounds, lengths) may be, in words.

    ``a number in [0, 2]``, ``an integer in [1, 1000]``, ``"msgpack" or "json"``, ``an array of at most 64
    items, each a string``, ``a table``.
    """
    tp, more = _unwrap(tp)
    meta = [*(metadata or []), *more]
    words = next((m.text for m in meta if isinstance(m, Allowed)), None)
    if words is not None:
        return words
    if tp is bool or _model_of(tp) is not None:
        return "true or false" if tp is bool else "a table"
    if tp is int or tp is float:
        return ("an integer" if tp is int else "a number") + _range(meta)
    if tp is str:
        n = _max_len(meta)
        empty = "a non-empty string" if any(isinstance(m, at.MinLen) and m.min_length > 0 for m in meta) else "a string"
        return empty + (f" of at most {n} characters" if n is not None else "")
    return _describe_compound(tp, meta)


def _describe_compound(tp: Any, meta: list[Any]) -> str:
    """:func:`describe` for Literal choices, arrays, tables of values and unions."""
    origin, args, n = get_origin(tp), get_args(tp), _max_len(meta)
    text = ""
    if origin is Literal:
        text = _either([json.dumps(a) if isinstance(a, str) else str(a) for a in args])
    elif origin is tuple and len(args) == 2 and args[1] is Ellipsis:
        some = "a non-empty array" if any(isinstance(m, at.MinLen) and m.min_length > 0 for m in meta) else "an array"
        text = f"{some} of {f'at most {n} items' if n is not None else 'items'}, each {describe(args[0])}"
    elif origin is tuple:
        text = f"an array of {len(args)} items, each {describe(args[0])}"
    elif origin is dict:
        text = f"a table{f' of at most {n} entries' if n is not None else ''}, each value {describe(args[1])}"
    elif _is_union(tp):
        text = _either([describe(a) for a in args if a is not type(None)])
    return text


def _either(words: list[str]) -> str:
    """``a``, ``a or b``, ``a, b or c``."""
    return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} or {words[-1]}"


def show(value: object) -> str:
    """A value as a message shows it: arrays in brackets, booleans as TOML writes them, at most ~60 characters."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return _REPR.repr(_as_lists(value))


def _as_lists(value: object) -> object:
    if isinstance(value, tuple):
        return [_as_lists(v) for v in value]
    return value


def _make_repr() -> reprlib.Repr:
    r = reprlib.Repr()
    r.maxlevel, r.maxlist, r.maxdict, r.maxtuple = 3, 6, 4, 6
    r.maxstring, r.maxother, r.maxlong = 60, 60, 40
    return r


_REPR = _make_repr()


def _unwrap(tp: Any) -> tuple[Any, list[Any]]:
    """``Annotated[X, m...]`` -> (X, [m...]) with FieldInfo metadata flattened; ``X | None`` -> X."""
    meta: list[Any] = []
    while True:
        if get_origin(tp) is Annotated:
            args = get_args(tp)
            tp = args[0]
            for m in args[1:]:
                meta.extend(m.metadata if isinstance(m, FieldInfo) else [m])
        elif _is_union(tp) and type(None) in get_args(tp):
            rest = [a for a in get_args(tp) if a is not type(None)]
            tp = rest[0] if len(rest) == 1 else typing.Union[tuple(rest)]  # noqa: UP007 (a runtime Union object)
        else:
            return tp, meta


def _is_union(tp: Any) -> bool:
    return get_origin(tp) in (typing.Union, types.UnionType)


def _max_len(meta: list[Any]) -> int | None:
    return next((int(m.max_length) for m in meta if isinstance(m, at.MaxLen)), None)


def _fmt(x: object) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _range(meta: list[Any]) -> str:
    lo = next(((m.ge, "[") for m in meta if isinstance(m, at.Ge)), None) or next(
        ((m.gt, "(") for m in meta if isinstance(m, at.Gt)), None
    )
    hi = next(((m.le, "]") for m in meta if isinstance(m, at.Le)), None) or next(
        ((m.lt, ")") for m in meta if isinstance(m, at.Lt)), None
    )
    if lo and hi:
        return f" in {lo[1]}{_fmt(lo[0])}, {_fmt(hi[0])}{hi[1]}"
    if lo:
        return f" {'>=' if lo[1] == '[' else '>'} {_fmt(lo[0])}"
    if hi:
        return f" {'<=' if hi[1] == ']' else '<'} {_fmt(hi[0])}"
    return ""


def _model_of(tp: Any) -> type[BaseModel] | None:
    """The model class inside ``tp`` (``Annotated[...]``, ``X | None``), if any."""
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return tp
    origin = get_origin(tp)
    if origin is Annotated:
        return _model_of(get_args(tp)[0])
    if origin in (typing.Union, types.UnionType):
        for arg in get_args(tp):
            found = _model_of(arg)
            if found is not None:
                return found
    return None


def _item_type(tp: Any) -> Any:
    tp, _ = _unwrap(tp)
    args = get_args(tp)
    if get_origin(tp) in (tuple, list) and args:
        return args[0]
    return None


def _message(err: Mapping[str, Any]) -> str:
    """pydantic's message, in the words of a config file."""
    simple = {
        "float_type": "a number",
        "int_type": "an integer",
        "bool_type": "true or false",
        "string_type": "a string",
        "finite_number": "a finite number (not nan or inf)",
        "model_type": "a table",
        "dict_type": "a table",
        "tuple_type": "an array",
        "list_type": "an array",
    }
    if err["type"] in simple:
        return simple[err["type"]]
    message: str = err["msg"]
    for prefix in ("Value error, ", "Assertion failed, "):
        if message.startswith(prefix):
            message = message[len(prefix) :]
    return message[:1].lower() + message[1:]
