"""Xsens MT Manager text exports (``.txt``/``.csv``, one file per sensor) → orientation, acceleration and time.

MT Manager writes, per sensor, optional header lines starting with ``//`` (``// Update Rate: 100.0Hz``,
``// Coordinate system: ENU``, ``//  DeviceId: 00B42D4F``, ``// Filter Profile: human (46.1)``, ...), then one
row of column names, then one row per sample. Columns are separated by tabs, commas or semicolons (whichever the
name row uses); empty cells and ``NaN`` mean "not in this sample". Recognised columns:

=====================================  =================================================================
``PacketCounter``                      16-bit sample counter (wraps at 65536; unwrapped here)
``SampleTimeFine``                     device time, 10 kHz ticks (32-bit; unwrapped here)
``Quat_q0`` .. ``Quat_q3``             orientation quaternion (w, x, y, z), sensor → global frame
``Mat[i][j]`` (i, j in 1..3)           orientation matrix element (row i, column j), sensor → global
``Roll``, ``Pitch``, ``Yaw``           Euler angles in degrees, ``R = Rz(yaw) Ry(pitch) Rx(roll)``
``Acc_X`` .. ``Acc_Z``                 specific force in the sensor frame, m/s² (gravity included)
``FreeAcc_X`` .. (or ``_E/_N/_U``)     acceleration in the global frame with gravity removed, m/s²
``Gyr_X`` .. ``Gyr_Z``                 rate of turn, sensor frame, rad/s
``Mag_X`` .. ``Mag_Z``                 magnetic field, sensor frame, arbitrary units
=====================================  =================================================================

The orientation comes from the quaternion when present, else the matrix, else the Euler angles; a file with none
of them is refused. The global frame is ENU unless a ``// Coordinate system:`` line says NED or NWU; orientations
are returned in ENU. A file with ``Acc_*`` gives the specific force as is; with only ``FreeAcc_*`` it is rebuilt
as ``R_iᵀ (a_free + g·up)``; with neither, as gravity alone (the sensor treated as unaccelerated), and
:attr:`MtExport.acceleration` says which. Rows without an orientation are dropped and counted.

Sample times: ``SampleTimeFine`` when every kept row has it, else ``PacketCounter`` at the update rate, else the
row index at the update rate. The update rate comes from the ``// Update Rate`` line, else from the median
``SampleTimeFine`` step; an export with neither needs it given (``rate_hz``).

The sensor id is the ``DeviceId`` header when there is one, else the last 8-hex-digit token of the file name
(``MT_012005D6_009-001_00B421E6.txt`` → ``00B421E6``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mocapd.core.imu import STANDARD_GRAVITY
from mocapd.core.imu_calibration import quat_to_enu
from mocapd.core.rotations import matrix_from_quat, quat_from_matrix, quat_normalize
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

TICK_HZ = 10_000
"""SampleTimeFine ticks per second."""
_SEPARATORS = ("\t", ",", ";")
_HEX_ID = re.compile(r"(?<![0-9A-Fa-f])([0-9A-Fa-f]{8})(?![0-9A-Fa-f])")


@dataclass(frozen=True)
class MtExport:
    """One sensor's export (see the module docstring).

    Attributes
    ----------
    sensor : str
        8 upper-case hex digits.
    rate_hz : float
    time_s : array, shape (n,)
        Sample times from the first kept sample (s).
    ticks : int array, shape (n,) or None
        Unwrapped SampleTimeFine (10 kHz), when every kept row had it.
    counter : int array, shape (n,) or None
        Unwrapped PacketCounter, when every kept row had it.
    quat : array, shape (n, 4)
        Sensor orientation in ENU (w, x, y, z).
    acc : array, shape (n, 3)
        Specific force in the sensor frame (m/s², gravity included).
    acceleration : {"measured", "from free acceleration", "gravity only"}
    orientation : {"quaternion", "matrix", "euler"}
    gyr, mag : array, shape (n, 3) or None
    header : dict of str
        The ``//`` lines as ``key: value`` (keys stripped).
    dropped_rows : int
        Rows without a usable orientation.
    """

    sensor: str
    rate_hz: float
    time_s: FloatArray
    ticks: IntArray | None
    counter: IntArray | None
    quat: FloatArray
    acc: FloatArray
    acceleration: str
    orientation: str
    gyr: FloatArray | None = None
    mag: FloatArray | None = None
    header: dict[str, str] = field(default_factory=dict)
    dropped_rows: int = 0

    @property
    def n(self) -> int:
        return int(self.quat.shape[0])


def read_mt_export(path: str | Path, *, rate_hz: float | None = None, sensor: str | None = None) -> MtExport:
    """Read one MT Manager export file (see :func:`parse_mt_export`)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig", errors="replace")
    except OSError as exc:
        raise InputError(f"cannot read MT Manager export {p}: {exc}") from exc
    return parse_mt_export(text, name=p.name, rate_hz=rate_hz, sensor=sensor)


def sensor_id_from_name(name: str) -> str | None:
    """The last 8-hex-digit token of a file name (``MT_012005D6_009-001_00B421E6.txt`` → ``00B421E6``)."""
    found = _HEX_ID.findall(Path(name).stem)
    return found[-1].upper() if found else None


def parse_mt_export(
    text: str, *, name: str = "<text>", rate_hz: float | None = None, sensor: str | None = None
) -> MtExport:
    """Parse the text of an MT Manager export.

    Parameters
    ----------
    text : str
    name : str
        File name, for messages and the sensor id.
    rate_hz : float, optional
        The update rate, when the file does not say it (overrides the header).
    sensor : str, optional
        The sensor id (overrides the header and the file name).

    Raises
    ------
    InputError
        No column row, no orientation columns, no rows, no usable rate, no sensor id, a malformed number.
    """
    header, names, rows, sep = _split(text, name)
    col = {c.strip(): i for i, c in enumerate(names)}
    values = _numbers(rows, len(names), sep, name)  # (n, n_cols), NaN where empty
    q, orientation = _orientation(values, col, name)
    keep = np.all(np.isfinite(q), axis=1)
    dropped = int((~keep).sum())
    values, q = values[keep], q[keep]
    if len(q) == 0:
        raise InputError(f"{name}: no sample has an orientation")
    frame = header.get("Coordinate system", "ENU").strip().upper() or "ENU"
    q = quat_to_enu(quat_normalize(q), frame)
    ticks = _unwrapped(values, col.get("SampleTimeFine"), 1 << 32, name, "SampleTimeFine")
    counter = _unwrapped(values, col.get("PacketCounter"), 1 << 16, name, "PacketCounter")
    rate = _rate(rate_hz, header, ticks, name)
    if ticks is not None:
        time_s = (ticks - ticks[0]) / TICK_HZ
    elif counter is not None:
        time_s = (counter - counter[0]) / rate
    else:
        time_s = np.arange(len(q)) / rate
    acc, acceleration = _specific_force(values, col, q, frame)
    sid = (sensor or _header_device_id(header) or sensor_id_from_name(name) or "").upper()
    if not re.fullmatch(r"[0-9A-F]{8}", sid):
        raise InputError(f"{name}: no sensor id (8 hex digits) in a DeviceId header or the file name; give one")
    return MtExport(
        sensor=sid,
        rate_hz=rate,
        time_s=np.asarray(time_s, dtype=np.float64),
        ticks=ticks,
        counter=counter,
        quat=q,
        acc=acc,
        acceleration=acceleration,
        orientation=orientation,
        gyr=_triple(values, col, "Gyr"),
        mag=_triple(values, col, "Mag"),
        header=header,
        dropped_rows=dropped,
    )


# ---------------------------------------------------------------------------------------------- helpers
def _split(text: str, name: str) -> tuple[dict[str, str], list[str], list[str], str]:
    header: dict[str, str] = {}
    lines = text.splitlines()
    i = 0
    while i < len(lines) and (lines[i].startswith("//") or not lines[i].strip()):
        body = lines[i][2:].strip()
        if ":" in body:
            key, _, value = body.partition(":")
            header.setdefault(key.strip(), value.strip())
        i += 1
    if i >= len(lines):
        raise InputError(f"{name}: no column row after the // header (not an MT Manager export?)")
    row = lines[i]
    sep = max(_SEPARATORS, key=row.count)
    if row.count(sep) == 0:
        raise InputError(f"{name}: the column row has no tab, comma or semicolon separator: {row[:60]!r}")
    names = [c.strip() for c in row.split(sep)]
    return header, names, [ln for ln in lines[i + 1 :] if ln.strip()], sep


def _numbers(rows: list[str], n_cols: int, sep: str, name: str) -> FloatArray:
    out = np.full((len(rows), n_cols), np.nan)
    for r, line in enumerate(rows):
        cells = line.split(sep)
        for c, raw in enumerate(cells[:n_cols]):
            cell = raw.strip()
            if not cell or cell.lower() == "nan":
                continue
            try:
                out[r, c] = float(cell)
            except ValueError as exc:
                raise InputError(f"{name}: row {r + 1}, column {c + 1}: not a number: {cell!r}") from exc
    return out


def _columns(values: FloatArray, col: dict[str, int], names: list[str]) -> FloatArray | None:
    if not all(n in col for n in names):
        return None
    return np.asarray(values[:, [col[n] for n in names]])


def _orientation(values: FloatArray, col: dict[str, int], name: str) -> tuple[FloatArray, str]:
    q = _columns(values, col, [f"Quat_q{i}" for i in range(4)])
    if q is not None:
        return q, "quaternion"
    m = _columns(values, col, [f"Mat[{i}][{j}]" for i in (1, 2, 3) for j in (1, 2, 3)])
    if m is not None:
        mats = m.reshape(-1, 3, 3)
        ok = np.all(np.isfinite(m), axis=1)
        out = np.full((len(m), 4), np.nan)
        if ok.any():
            u, _, vt = np.linalg.svd(mats[ok])  # the export rounds to 6 decimals: re-orthonormalise
            out[ok] = quat_from_matrix(u @ vt)
        return out, "matrix"
    e = _columns(values, col, ["Roll", "Pitch", "Yaw"])
    if e is not None:
        return _quat_from_xsens_euler(np.radians(e)), "euler"
    raise InputError(f"{name}: no orientation columns (Quat_q0..q3, Mat[i][j] or Roll/Pitch/Yaw)")


def _quat_from_xsens_euler(rpy: FloatArray) -> FloatArray:
    """Xsens Euler angles (roll x, pitch y, yaw z; ``R = Rz Ry Rx``) → quaternions (n, 4)."""
    hr, hp, hy = rpy[:, 0] / 2, rpy[:, 1] / 2, rpy[:, 2] / 2
    cr, sr, cp, sp, cy, sy = np.cos(hr), np.sin(hr), np.cos(hp), np.sin(hp), np.cos(hy), np.sin(hy)
    return np.stack(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ],
        axis=1,
    )


def _unwrapped(values: FloatArray, c: int | None, modulus: int, name: str, column: str) -> IntArray | None:
    """A wrapping device counter unwrapped (None without the column, or where a sample lacks it); a value that is
    not an integer in [0, modulus) is an InputError (cast to int64 it became garbage time, silently)."""
    if c is None or not np.all(np.isfinite(values[:, c])):
        return None
    v = values[:, c]
    bad = (v < 0) | (v >= modulus) | (v != np.floor(v))
    if np.any(bad):
        row = int(np.argmax(bad))
        raise InputError(
            f"{name}: {column} = {float(v[row])!r} in data row {row + 1}; allowed: an integer in [0, {modulus})"
        )
    raw = v.astype(np.int64)
    steps = np.diff(raw)
    wraps = np.cumsum(np.r_[0, (steps < -modulus // 2).astype(np.int64)])
    return np.asarray(raw + wraps * modulus, dtype=np.int64)


def _rate(rate_hz: float | None, header: dict[str, str], ticks: IntArray | None, name: str) -> float:
    if rate_hz is not None:
        rate = float(rate_hz)
    elif "Update Rate" in header:
        m = re.match(r"\s*([0-9.]+)", header["Update Rate"])
        rate = float(m.group(1)) if m else math.nan
    elif ticks is not None and len(ticks) > 1:
        rate = TICK_HZ / float(np.median(np.diff(ticks)))
    else:
        rate = math.nan
    if not (math.isfinite(rate) and rate > 0):
        raise InputError(f"{name}: no update rate (no '// Update Rate' line or SampleTimeFine); give it")
    return rate


def _header_device_id(header: dict[str, str]) -> str | None:
    for key in ("DeviceId", "Device ID", "Device Id"):
        if key in header and re.fullmatch(r"[0-9A-Fa-f]{8}", header[key].strip()):
            return header[key].strip().upper()
    return None


def _triple(values: FloatArray, col: dict[str, int], prefix: str) -> FloatArray | None:
    return _columns(values, col, [f"{prefix}_{a}" for a in "XYZ"])


def _specific_force(values: FloatArray, col: dict[str, int], q_enu: FloatArray, frame: str) -> tuple[FloatArray, str]:
    acc = _triple(values, col, "Acc")
    if acc is not None and np.all(np.isfinite(acc)):
        return acc, "measured"
    free = _triple(values, col, "FreeAcc")
    if free is None:
        free = _columns(values, col, ["FreeAcc_E", "FreeAcc_N", "FreeAcc_U"])
    up = np.array([0.0, 0.0, STANDARD_GRAVITY])
    R = matrix_from_quat(q_enu)  # sensor -> ENU
    if free is not None and np.all(np.isfinite(free)):
        free_enu = quat_to_enu_vectors(free, frame)
        return np.einsum("nji,nj->ni", R, free_enu + up), "from free acceleration"
    return np.einsum("nji,j->ni", R, up), "gravity only"


def quat_to_enu_vectors(v: FloatArray, frame: str) -> FloatArray:
    """Vectors (n, 3) given in the device global ``frame`` (ENU, NED, NWU) in ENU."""
    if frame == "ENU":
        return np.asarray(v, dtype=np.float64)
    R = matrix_from_quat(quat_to_enu(np.array([1.0, 0.0, 0.0, 0.0]), frame))
    return np.asarray(v @ R.T)
