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

An export is a door (issue 34): the file must be a regular file of at most :data:`MAX_FILE_BYTES`
(:mod:`mocapd.io.input_files`: a FIFO or ``/dev/zero`` is refused, not waited on or read forever), and it is read
line by line in chunks of :data:`CHUNK_ROWS` rows, keeping only the recognised columns as numbers (a 265 MB
export of a 26-column MTw file holds ~14 columns of numbers: ~110 bytes of text a row become ~112 bytes of
float64). Every value is checked before use and refused with one line naming the file, the column and the data
row: an orientation that is not a rotation (quaternion norm outside 1 ± 0.1, a matrix that is not orthonormal
within 0.1, Euler angles beyond ±720°), accelerations, rates of turn and magnetic fields beyond what an IMU
measures (:data:`LIMITS`), a ``PacketCounter`` or ``SampleTimeFine`` that does not increase (a counter running
backwards, or one sample time twice: after unwrapping, each step must be positive), an update rate outside
[:data:`MIN_RATE_HZ`, :data:`MAX_RATE_HZ`] or one the ``// Update Rate`` line and ``SampleTimeFine`` disagree
on by more than 10 %; lines longer than :data:`MAX_LINE_CHARS`, more than :data:`MAX_HEADER_LINES` header lines
or :data:`MAX_COLUMNS` columns, more than :data:`MAX_ROWS` rows.
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np
from numpy.typing import NDArray

from mocapd.core.imu import STANDARD_GRAVITY
from mocapd.core.imu_calibration import quat_to_enu
from mocapd.core.rotations import matrix_from_quat, quat_from_matrix, quat_normalize
from mocapd.errors import InputError
from mocapd.io.input_files import GiB, open_input_text

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

TICK_HZ = 10_000
"""SampleTimeFine ticks per second."""
_SEPARATORS = ("\t", ",", ";")
MAX_FILE_BYTES = 4 * GiB
"""Largest export read (MT Manager writes ~300 bytes a row at most: 14 million rows, 39 hours at 100 Hz)."""
MAX_ROWS = 20_000_000
"""Most data rows of one export."""
MAX_LINE_CHARS = 65_536
"""Longest line (a row of 512 columns of 100 characters each still fits)."""
MAX_HEADER_LINES = 1_000
MAX_COLUMNS = 512
CHUNK_ROWS = 65_536
"""Rows parsed at a time (numpy parses a chunk in one call; the text of one chunk is all that is held)."""
MIN_RATE_HZ = 1.0
MAX_RATE_HZ = 2_000.0
"""Update rates accepted (the ``// Update Rate`` line, ``--rate`` or SampleTimeFine's): Xsens devices output up to
2 kHz (MTi 600), MTw up to 120 Hz."""
LIMITS = {"Acc": 2_000.0, "FreeAcc": 2_000.0, "Gyr": 1_000.0, "Mag": 1e4}
"""Largest magnitude of a component accepted per vector column: m/s² (about 200 g; MTw measure ±160 m/s²), rad/s,
magnetometer units (normalised to ~1 by MT Manager)."""
_RATE = re.compile(r"^\s*([0-9]+(?:\.[0-9]*)?(?:[eE][-+]?[0-9]+)?)\s*(?:Hz)?\s*$", re.IGNORECASE)
_QUAT = [f"Quat_q{i}" for i in range(4)]
_MAT = [f"Mat[{i}][{j}]" for i in (1, 2, 3) for j in (1, 2, 3)]
_EULER = ["Roll", "Pitch", "Yaw"]
_VECTORS = {f"{p}_{a}": p for p in ("Acc", "FreeAcc", "Gyr", "Mag") for a in "XYZ"} | {
    f"FreeAcc_{a}": "FreeAcc" for a in "ENU"
}
_USED = frozenset(["PacketCounter", "SampleTimeFine", *_QUAT, *_MAT, *_EULER, *_VECTORS])
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
    """Read one MT Manager export file (see :func:`parse_mt_export`), line by line with bounded memory.

    Raises
    ------
    InputError
        Not a regular file of at most :data:`MAX_FILE_BYTES`, unreadable, or not a valid export (one line naming
        the file and what is wrong).
    """
    p = Path(path)
    with open_input_text(p, "MT Manager export", max_bytes=MAX_FILE_BYTES, encoding="utf-8-sig") as fh:
        try:
            return _parse(_lines(fh, p.name), name=p.name, rate_hz=rate_hz, sensor=sensor)
        except OSError as exc:
            raise InputError(f"cannot read MT Manager export {p}: {exc.strerror or exc}") from None


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
        No column row, no orientation columns, no rows, no usable rate, no sensor id, a malformed number, a value
        out of its range (see the module docstring).
    """
    return _parse(iter(text.splitlines()), name=name, rate_hz=rate_hz, sensor=sensor)


def _parse(lines: Iterator[str], *, name: str, rate_hz: float | None, sensor: str | None) -> MtExport:
    header, names, sep = _head(lines, name)
    col, used = _layout(names, name)
    orientation = _orientation_kind(col, name)
    values, q, col = _rows(lines, used, sep, name, col, orientation)  # NaN where empty
    keep = np.all(np.isfinite(q), axis=1)
    rows = np.flatnonzero(keep)  # data row of each kept sample (for messages)
    dropped = int((~keep).sum())
    if dropped:
        values, q = values[keep], q[keep]
    if len(q) == 0:
        raise InputError(f"{name}: no sample has an orientation")
    _check_vectors(values, col, rows, name)
    frame = header.get("Coordinate system", "ENU").strip().upper() or "ENU"
    q = quat_to_enu(quat_normalize(q), frame)
    ticks = _unwrapped(values, col.get("SampleTimeFine"), 1 << 32, name, "SampleTimeFine", rows)
    counter = _unwrapped(values, col.get("PacketCounter"), 1 << 16, name, "PacketCounter", rows)
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
def _lines(fh: TextIO, name: str) -> Iterator[str]:
    """The lines of a file without their ends, none longer than :data:`MAX_LINE_CHARS` (a file without newlines
    is not read whole into one string)."""
    while line := fh.readline(MAX_LINE_CHARS + 2):
        body = line.rstrip("\r\n")
        if len(body) > MAX_LINE_CHARS:
            raise InputError(f"{name}: a line longer than {MAX_LINE_CHARS} characters (not an MT Manager export)")
        yield body


def _head(lines: Iterator[str], name: str) -> tuple[dict[str, str], list[str], str]:
    """The ``//`` header (``key: value``, each cut to 64/256 characters), the column names and the separator."""
    header: dict[str, str] = {}
    for i, line in enumerate(lines):
        if line.startswith("//") or not line.strip():
            if i >= MAX_HEADER_LINES:
                raise InputError(f"{name}: more than {MAX_HEADER_LINES} header lines before the column row")
            body = line[2:].strip()
            if ":" in body:
                key, _, value = body.partition(":")
                header.setdefault(key.strip()[:64], value.strip()[:256])
            continue
        sep = max(_SEPARATORS, key=line.count)
        if line.count(sep) == 0:
            raise InputError(f"{name}: the column row has no tab, comma or semicolon separator: {line[:60]!r}")
        names = [c.strip() for c in line.split(sep)]
        if len(names) > MAX_COLUMNS:
            raise InputError(f"{name}: {len(names)} columns; an MT Manager export has at most {MAX_COLUMNS}")
        return header, names, sep
    raise InputError(f"{name}: no column row after the // header (not an MT Manager export?)")


def _layout(names: list[str], name: str) -> tuple[dict[str, int], list[int]]:
    """The recognised columns: name -> index among the kept ones, and their indices in a row."""
    col: dict[str, int] = {}
    used: list[int] = []
    for i, c in enumerate(names):
        if c not in _USED:
            continue
        if c in col:
            raise InputError(f"{name}: column {c!r} appears twice in the column row")
        col[c] = len(used)
        used.append(i)
    return col, used


def _rows(
    lines: Iterator[str], used: list[int], sep: str, name: str, col: dict[str, int], orientation: str
) -> tuple[FloatArray, FloatArray, dict[str, int]]:
    """Every non-empty data row, ``CHUNK_ROWS`` rows at a time: the recognised columns other than the orientation
    as numbers (n, k), each row's orientation as a quaternion (n, 4; NaN where the row has none), and the column
    map of the first array. A chunk's orientation columns (9 of a matrix) are turned into its quaternion at once:
    what is held is what the export keeps, not the text or the matrices."""
    other = [c for c in col if c not in _ORIENTATION[orientation]]
    take = [col[c] for c in other]
    parts: list[tuple[FloatArray, FloatArray]] = []
    n = 0
    while block := list(itertools.islice(lines, CHUNK_ROWS)):
        rows = [ln for ln in block if ln.strip()]
        if not rows:
            continue
        if n + len(rows) > MAX_ROWS:
            raise InputError(f"{name}: more than {MAX_ROWS} data rows")
        numbers = _chunk(rows, used, sep, name, n)
        parts.append((numbers[:, take], _orientation(numbers, col, orientation, name, n)))
        n += len(rows)
    values, q = np.empty((n, len(take))), np.empty((n, 4))
    at = 0
    parts.reverse()
    while parts:  # into one array each, each part let go once copied: the parts and the whole are not all held
        v, qq = parts.pop()
        values[at : at + len(v)], q[at : at + len(v)] = v, qq
        at += len(v)
    return values, q, {c: i for i, c in enumerate(other)}


def _chunk(rows: list[str], used: list[int], sep: str, name: str, first: int) -> FloatArray:
    if not used:
        return np.empty((len(rows), 0))
    # numpy's parser: one call for the whole chunk when every used cell is a number or empty (MT Manager leaves
    # the cells of a column empty where a sample lacks it: they are written "nan" first, with C-level replaces)
    text = "\n" + "\n".join(rows) + "\n"
    empty = sep + sep
    while empty in text:  # twice for a run of empty cells (each replace fills every other one)
        text = text.replace(empty, sep + "nan" + sep)
    text = text.replace("\n" + sep, "\nnan" + sep).replace(sep + "\n", sep + "nan\n")
    try:
        values = np.loadtxt(text[1:-1].split("\n"), delimiter=sep, usecols=used, ndmin=2, comments=None)
        return np.asarray(values, dtype=np.float64)
    except ValueError:
        pass  # empty cells, short rows or a bad number: cell by cell, to say which
    out = np.full((len(rows), len(used)), np.nan)
    for r, line in enumerate(rows):
        cells = line.split(sep)
        for k, c in enumerate(used):
            cell = cells[c].strip() if c < len(cells) else ""
            if not cell or cell.lower() == "nan":
                continue
            try:
                out[r, k] = float(cell)
            except ValueError:
                raise InputError(f"{name}: row {first + r + 1}, column {c + 1}: not a number: {cell[:40]!r}") from None
    return out


def _columns(values: FloatArray, col: dict[str, int], names: list[str]) -> FloatArray | None:
    if not all(n in col for n in names):
        return None
    return np.asarray(values[:, [col[n] for n in names]])


_ORIENTATION = {"quaternion": _QUAT, "matrix": _MAT, "euler": _EULER}


def _orientation_kind(col: dict[str, int], name: str) -> str:
    """Where the orientation comes from: the quaternion, else the matrix, else the Euler angles."""
    for kind, names in _ORIENTATION.items():
        if all(n in col for n in names):
            return kind
    raise InputError(f"{name}: no orientation columns (Quat_q0..q3, Mat[i][j] or Roll/Pitch/Yaw)")


def _orientation(values: FloatArray, col: dict[str, int], kind: str, name: str, first: int) -> FloatArray:
    """Each row's orientation quaternion (NaN where the row has none); a value that is no rotation is refused
    (``first``: the data row of ``values[0]``, for the message)."""
    rows = np.arange(first, first + len(values))
    if kind == "quaternion":
        q = np.asarray(values[:, [col[n] for n in _QUAT]])
        with np.errstate(over="ignore", invalid="ignore"):  # 1e308 or inf: refused just below
            norm = np.linalg.norm(q, axis=1)
        present = ~np.isnan(q).any(axis=1)  # an empty or NaN cell: the row has no orientation (dropped)
        _refuse(present & ~(np.isfinite(norm) & (norm > 0.9) & (norm < 1.1)), name, "Quat_q0..q3", q,
                "not a rotation (a unit quaternion: norm within 1 ± 0.1)", rows)  # fmt: skip
        return q
    if kind == "matrix":
        m = np.asarray(values[:, [col[n] for n in _MAT]])
        mats = m.reshape(-1, 3, 3)
        ok = np.all(np.isfinite(m), axis=1)
        out = np.full((len(m), 4), np.nan)
        err = np.full(len(m), np.inf)
        det = np.zeros(len(m))
        with np.errstate(over="ignore", invalid="ignore"):  # 1e308: refused just below
            err[ok] = np.abs(mats[ok] @ np.swapaxes(mats[ok], 1, 2) - np.eye(3)).max(axis=(1, 2))
            det[ok] = np.linalg.det(mats[ok])
        present = ~np.isnan(m).any(axis=1)
        _refuse(present & ((err > 0.1) | (det <= 0)), name, "Mat[1][1]..Mat[3][3]", m,
                "not a rotation matrix (orthonormal within 0.1, determinant +1)", rows)  # fmt: skip
        out[ok] = quat_from_matrix(_orthonormal(mats[ok]))  # the export rounds to 6 decimals: re-orthonormalise
        return out
    e = np.asarray(values[:, [col[n] for n in _EULER]])
    present = ~np.isnan(e).any(axis=1)
    _refuse(present & ~(np.abs(e) <= 720.0).all(axis=1), name, "Roll/Pitch/Yaw", e, "an angle beyond ±720°", rows)
    return _quat_from_xsens_euler(np.radians(e))


def _orthonormal(m: FloatArray) -> FloatArray:
    """The nearest rotations (polar factors) of matrices (n, 3, 3) within 0.1 of orthonormal: Newton–Schulz
    iterations ``R <- R (3 I - Rᵀ R) / 2`` (matrix products only: faster than a batched SVD; each iteration about
    squares the error: 1e-6 after the export's rounding is below 1e-15 after two, the 0.3 allowed after six)."""
    r = m
    for _ in range(6):
        r = r @ (3.0 * np.eye(3) - np.swapaxes(r, 1, 2) @ r) / 2.0
    return r


def _refuse(bad: NDArray[np.bool_] | np.bool_, name: str, what: str, values: FloatArray, why: str,
            rows: NDArray[np.int64] | None = None) -> None:  # fmt: skip
    """InputError naming the first row where ``bad`` holds (``rows``: data row of each, default the index)."""
    if not bad.any():
        return
    k = int(np.argmax(bad))
    row = int(rows[k]) if rows is not None else k
    shown = ", ".join(f"{v:.6g}" for v in np.atleast_1d(values[k])[:9])
    raise InputError(f"{name}: {what} = ({shown}) in data row {row + 1}: {why}")


def _check_vectors(values: FloatArray, col: dict[str, int], rows: NDArray[np.int64], name: str) -> None:
    """Accelerations, rates of turn and magnetic fields within what an IMU measures (:data:`LIMITS`)."""
    for column, prefix in _VECTORS.items():
        c = col.get(column)
        if c is not None:
            v = values[:, c]
            limit = LIMITS[prefix]
            _refuse(np.isinf(v) | (np.abs(np.nan_to_num(v)) > limit), name, column, v,
                    f"beyond ±{limit:g} (not a reading of an IMU)", rows)  # fmt: skip


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


MAX_TICK_STEP = 3600 * TICK_HZ
"""Largest SampleTimeFine step between two rows (an hour): a bigger jump is a damaged value, not a pause."""


def _unwrapped(
    values: FloatArray, c: int | None, modulus: int, name: str, column: str, rows: NDArray[np.int64]
) -> IntArray | None:
    """A wrapping device counter unwrapped (None without the column, or where a sample lacks it); a value that is
    not an integer in [0, modulus) is an InputError (cast to int64 it became garbage time, silently), and so is a
    counter that does not increase from row to row (running backwards gave negative times, a constant one many
    samples at one instant)."""
    if c is None or not np.all(np.isfinite(values[:, c])):
        return None
    v = values[:, c]
    bad = (v < 0) | (v >= modulus) | (v != np.floor(v))
    if np.any(bad):
        k = int(np.argmax(bad))
        raise InputError(
            f"{name}: {column} = {float(v[k])!r} in data row {int(rows[k]) + 1}; allowed: an integer in [0, {modulus})"
        )
    raw = v.astype(np.int64)
    steps = np.diff(raw)
    wraps = np.cumsum(np.r_[0, (steps < -modulus // 2).astype(np.int64)])
    out = np.asarray(raw + wraps * modulus, dtype=np.int64)
    steps = np.diff(out)
    stuck = steps <= 0
    if column == "SampleTimeFine":
        stuck |= steps > MAX_TICK_STEP
    if np.any(stuck):
        k = int(np.argmax(stuck))
        raise InputError(
            f"{name}: {column} goes from {int(raw[k])} to {int(raw[k + 1])} at data row {int(rows[k + 1]) + 1}; "
            f"allowed: increasing from row to row (wrapping at {modulus}"
            + (", steps of at most an hour)" if column == "SampleTimeFine" else ")")
        )
    return out


def _rate(rate_hz: float | None, header: dict[str, str], ticks: IntArray | None, name: str) -> float:
    """The update rate: ``rate_hz`` (``--rate``), else the ``// Update Rate`` line, else SampleTimeFine's median
    step; within [MIN_RATE_HZ, MAX_RATE_HZ], and within 10 % of SampleTimeFine's when the file has it."""
    tick_rate = TICK_HZ / float(np.median(np.diff(ticks))) if ticks is not None and len(ticks) > 1 else None
    if rate_hz is not None:
        rate, said = float(rate_hz), f"--rate {rate_hz:g}"
    elif "Update Rate" in header:
        m = _RATE.match(header["Update Rate"])
        if m is None:
            raise InputError(f"{name}: '// Update Rate: {header['Update Rate'][:40]}' is not a rate in Hz")
        rate, said = float(m.group(1)), f"'// Update Rate: {header['Update Rate'][:40]}'"
    elif tick_rate is not None:
        rate, said = tick_rate, "SampleTimeFine's steps"
    else:
        raise InputError(f"{name}: no update rate (no '// Update Rate' line or SampleTimeFine); give it")
    if not (math.isfinite(rate) and MIN_RATE_HZ <= rate <= MAX_RATE_HZ):
        raise InputError(f"{name}: {said} gives an update rate of {rate:.6g} Hz; allowed: {MIN_RATE_HZ:g} to "
                         f"{MAX_RATE_HZ:g} Hz")  # fmt: skip
    if tick_rate is not None and abs(rate / tick_rate - 1.0) > 0.1:
        raise InputError(f"{name}: {said} disagrees with SampleTimeFine, whose steps give {tick_rate:.6g} Hz")
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
