"""The ``[tracking]`` section: detection sorting, enrolment and suit-binding options.

Each sub-table maps one-to-one onto a frozen options dataclass of ``mocapd.core``; keys are the field names, and
values are checked against the field's type (number, integer, boolean, a pair of numbers, a list of pairs).
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Any, TypeVar

from mocapd.core.sorting import SortingOptions
from mocapd.core.suit_binding import BindingOptions
from mocapd.core.tracking import TrackingOptions
from mocapd.errors import ConfigError

T = TypeVar("T")


@dataclass(frozen=True)
class TrackingConfig:
    sorting: SortingOptions = field(default_factory=SortingOptions)
    enrolment: TrackingOptions = field(default_factory=TrackingOptions)
    binding: BindingOptions = field(default_factory=BindingOptions)


def parse_tracking_config(t: dict[str, Any]) -> TrackingConfig:
    allowed = {"sorting", "enrolment", "binding"}
    unknown = set(t) - allowed
    if unknown:
        raise ConfigError(f"unknown key(s) {sorted(unknown)} in [tracking]; allowed: {sorted(allowed)}")
    return TrackingConfig(
        sorting=parse_options(SortingOptions, t.get("sorting", {}), "tracking.sorting"),
        enrolment=parse_options(TrackingOptions, t.get("enrolment", {}), "tracking.enrolment"),
        binding=parse_options(BindingOptions, t.get("binding", {}), "tracking.binding"),
    )


def parse_options(cls: type[T], table: object, where: str) -> T:
    """A frozen options dataclass from a TOML table; unknown keys and ill-typed or negative values rejected."""
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table, got {table!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = set(table) - names
    if unknown:
        raise ConfigError(f"unknown key(s) {sorted(unknown)} in [{where}]; allowed: {sorted(names)}")
    values = {k: _convert(v, hints[k], f"{where}.{k}") for k, v in table.items()}
    return cls(**values)


def _number(v: object, key: str, integer: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or (integer and not isinstance(v, int)):
        raise ConfigError(f"{key} = {v!r}; allowed: {'an integer' if integer else 'a number'} >= 0")
    if v < 0:
        raise ConfigError(f"{key} = {v!r}; allowed: {'an integer' if integer else 'a number'} >= 0")
    return v


def _pair(v: object, key: str) -> tuple[float, float]:
    if not (
        isinstance(v, list) and len(v) == 2 and all(isinstance(x, int | float) and not isinstance(x, bool) for x in v)
    ):
        raise ConfigError(f"{key} = {v!r}; allowed: a pair of numbers [x, z] (metres)")
    return float(v[0]), float(v[1])


def _convert(v: object, hint: object, key: str) -> object:
    if hint is float:
        return float(_number(v, key))
    if hint is int:
        return int(_number(v, key, integer=True))
    if hint is bool:
        if not isinstance(v, bool):
            raise ConfigError(f"{key} = {v!r}; allowed: true or false")
        return v
    if hint == tuple[float, float]:
        return _pair(v, key)
    if hint == tuple[tuple[float, float], ...]:
        if not isinstance(v, list):
            raise ConfigError(f"{key} = {v!r}; allowed: a list of [x, z] pairs (metres)")
        return tuple(_pair(x, key) for x in v)
    raise ConfigError(f"{key}: unsupported option type {hint!r}")  # a programming error, named clearly
