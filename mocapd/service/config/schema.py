"""The config schema's common ground: pydantic models that say what each key of config.toml may hold.

Every section is a frozen :class:`Section` (unknown keys rejected, no type coercion, no NaN or infinity), so a
typo, a string where a number belongs, ``nan`` or an out-of-range value is refused where the file is read, never
half-way through a run. :func:`validate` turns pydantic's errors into mocapd's messages, one line per problem,
each naming the dotted key, the value and what is allowed::

    cameras[1].exposure_us = -5.0: must be >= 1
    unknown key daemon.latency; allowed: body_size_s, http_host, ...

Why pydantic: the rules of ~150 keys are declared once, beside their types and defaults (``Field(ge=..., le=...)``),
instead of a hand-written check per key; the schema can be walked by tests (every key of the shipped file must
have a rule).
"""

from __future__ import annotations

import types
import typing
from collections.abc import Mapping
from typing import Annotated, Any, TypeVar, get_args, get_origin

from pydantic import BaseModel, BeforeValidator, ConfigDict, ValidationError

from mocapd.errors import ConfigError

M = TypeVar("M", bound=BaseModel)
T = TypeVar("T")


class Section(BaseModel):
    """Base of every config table: frozen, strict types, unknown keys and non-finite numbers refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


def _as_tuple(value: object) -> object:
    """TOML arrays arrive as lists; the schema keeps immutable tuples (strict mode takes no list for a tuple)."""
    return tuple(value) if isinstance(value, list) else value


#: a TOML array stored as a tuple: ``Seq[int]`` accepts ``[1, 2, 3]``
Seq = Annotated[tuple[T, ...], BeforeValidator(_as_tuple)]
#: two numbers, e.g. ``[x, z]``
Pair = Annotated[tuple[float, float], BeforeValidator(_as_tuple)]


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
    """One message per validation error: ``key = value: what is allowed``."""
    lines = []
    for err in exc.errors(include_url=False):
        loc = tuple(err["loc"])
        key = dotted(where, loc)
        kind = err["type"]
        if kind == "extra_forbidden":
            allowed = fields_at(model, loc[:-1])
            hint = f"; allowed: {', '.join(allowed)}" if allowed else ""
            lines.append(f"unknown key {key}{hint}")
        elif kind == "missing":
            lines.append(f"{key} is required")
        elif kind == "value_error" and (not loc or err.get("input") is data_of(err)):
            lines.append(f"{key}: {_explain(err)}")  # a rule across keys of one table (model validator)
        else:
            lines.append(f"{key} = {_show(err.get('input'))}: {_explain(err)}")
    return lines


def data_of(err: Mapping[str, Any]) -> object:
    """The input of a model-level error is the whole table: identified as a dict input of a value error."""
    value = err.get("input")
    return value if isinstance(value, dict) else object()


def dotted(where: str, loc: tuple[int | str, ...]) -> str:
    """``("cameras", 1, "gain_db")`` under ``""`` -> ``cameras[1].gain_db``."""
    out = where
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in ("function-before", "function-after") or str(part).startswith(("function-", "tagged-union")):
            continue  # pydantic's validator wrappers, not keys
        else:
            out = f"{out}.{part}" if out else str(part)
    return out


def fields_at(model: type[BaseModel], loc: tuple[int | str, ...]) -> list[str]:
    """The keys allowed in the table at ``loc`` below ``model`` (empty when it is not a table of a model)."""
    current: Any = model
    for part in loc:
        current = _model_of(current)
        if current is None:
            return []
        if isinstance(part, str):
            field = current.model_fields.get(part)
            if field is None:
                return []
            current = field.annotation
        else:  # an index into a sequence: step into its item type
            current = _item_type(current)
    final = _model_of(current)
    return sorted(final.model_fields) if final is not None else []


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
    origin = get_origin(tp)
    if origin is Annotated:
        return _item_type(get_args(tp)[0])
    args = get_args(tp)
    if origin in (tuple, list) and args:
        return args[0]
    return None


def _show(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _explain(err: Mapping[str, Any]) -> str:
    """pydantic's message, in the words of a config file ("must be >= 1", "must be a number")."""
    ctx = err.get("ctx") or {}
    kind = err["type"]
    bounds = {"greater_than_equal": ">=", "greater_than": ">", "less_than_equal": "<=", "less_than": "<"}
    if kind in bounds:
        limit = next(iter(v for k, v in ctx.items() if k in ("ge", "gt", "le", "lt")), None)
        return f"must be {bounds[kind]} {limit}"
    simple = {
        "float_type": "must be a number",
        "int_type": "must be an integer",
        "bool_type": "must be true or false",
        "string_type": "must be a string",
        "finite_number": "must be a finite number (not nan or inf)",
        "model_type": "must be a table",
        "dict_type": "must be a table",
        "tuple_type": "must be an array",
        "list_type": "must be an array",
    }
    if kind in simple:
        return simple[kind]
    if kind == "literal_error":
        return f"allowed: {ctx.get('expected')}"
    message: str = err["msg"]
    if message.startswith("Value error, "):
        message = message[len("Value error, ") :]
    return message[:1].lower() + message[1:]
