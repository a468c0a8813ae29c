"""Rigs of camera hosts without hardware, for tests and ``tools/bench_zenoh.py``: config files of camera hosts
(``mocapd detect-host``) and of the solver host that receives their cameras (``source = "zenoh"``).

A synthetic camera host runs ``source = "synthetic"`` cameras (the simulated rig of ``[synthetic]``, detector
output computed from recorded motion); the solver host then needs the simulated ring rig's calibration under the
same camera names, which :func:`write_ring_calibration` writes.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from mocapd.core.synthetic import named_ring_rig
from mocapd.io.calibration_files import CalibrationSet, CameraCalibration, write_mocapd_toml


def write_ring_calibration(names: Sequence[str], path: Path) -> None:
    """The simulated ring rig of ``len(names)`` cameras, named ``names``, as a mocapd calibration file."""
    cams = named_ring_rig(names)
    calib = CalibrationSet(tuple(CameraCalibration(c.name, (c.width, c.height), c.K, c.dist, c.R, c.t) for c in cams))
    write_mocapd_toml(calib, path)


def toml_value(value: Any) -> str:
    """A TOML literal of a str, bool, number or list of them (JSON's syntax is TOML's for these), or of a table of
    them (an inline table: ``{ key = value, ... }``)."""
    if isinstance(value, Mapping):
        return "{ " + ", ".join(f"{json.dumps(str(k))} = {toml_value(v)}" for k, v in value.items()) + " }"
    return json.dumps(value)


def toml_tables(tables: Mapping[str, Mapping[str, Any]], cameras: Sequence[Mapping[str, Any]] = ()) -> str:
    """A config document: ``[section]`` tables (dotted names for sub-tables) and ``[[cameras]]``."""
    out: list[str] = []
    for cam in cameras:
        out.append("[[cameras]]")
        out += [f"{k} = {toml_value(v)}" for k, v in cam.items()]
        out.append("")
    for name, table in tables.items():
        out.append(f"[{name}]")
        out += [f"{k} = {toml_value(v)}" for k, v in table.items()]
        out.append("")
    return "\n".join(out)


def host_config(
    host: str,
    cameras: Sequence[Mapping[str, Any]],
    connect: Sequence[str],
    *,
    rig: str = "rig",
    extra: Mapping[str, Mapping[str, Any]] | None = None,
    zenoh: Mapping[str, Any] | None = None,
) -> str:
    """A camera host's config: its cameras, connecting to the solver host at ``connect``."""
    tables: dict[str, dict[str, Any]] = {
        "zenoh": {
            "rig": rig,
            "host": host,
            "listen": [],
            "connect": list(connect),
            "status_period_s": 0.25,
            "clock_period_s": 0.25,
            **(zenoh or {}),
        },
    }
    for k, v in (extra or {}).items():
        tables.setdefault(k, {}).update(v)
    return toml_tables(tables, cameras)


def solver_config(cameras: Mapping[str, str], calibration: Path, listen: Sequence[str], *, rig: str = "rig",
                  extra: Mapping[str, Mapping[str, Any]] | None = None,
                  zenoh: Mapping[str, Any] | None = None) -> str:  # fmt: skip
    """The solver host's config: ``cameras`` (name -> camera host) as ``zenoh`` cameras, listening on ``listen``."""
    tables: dict[str, dict[str, Any]] = {
        "calibration": {"file": str(calibration)},
        "zenoh": {
            "rig": rig,
            "listen": list(listen),
            "connect": [],
            "lost_after_s": 1.0,
            "status_period_s": 0.25,
            "clock_period_s": 0.25,
            **(zenoh or {}),
        },
        "daemon": {"http_port": 0},
        "websocket": {"port": 0},
    }
    for k, v in (extra or {}).items():
        tables.setdefault(k, {}).update(v)
    cams = [{"name": n, "source": "zenoh", "host": h} for n, h in cameras.items()]
    return toml_tables(tables, cams)
