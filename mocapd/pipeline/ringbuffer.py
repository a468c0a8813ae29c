"""Fixed-capacity, numpy-backed, timestamped ring buffer with interpolated lookup.

One buffer per stream (an IMU, a camera's keypoints, ...). Each sample is a time stamp (int64 ns, host clock)
and a flat float64 row made of named fields; each field says how it is interpolated:

- ``"linear"``: component-wise linear interpolation (accelerations, keypoints, confidences),
- ``"slerp"``: unit quaternions (w, x, y, z), spherical linear interpolation on the shorter arc,
- ``"nearest"``: the value of the closer sample (counters, flags, ids).

Storage is allocated once. Time stamps (and rows) are written twice, at ``i`` and ``i + capacity``, so the
live window is always one contiguous slice: look-ups binary-search it without copying, and writing a sample
costs two row copies and no allocation.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from mocapd.core.rotations import quat_normalize, quat_slerp
from mocapd.errors import InputError

Interp = Literal["linear", "slerp", "nearest"]
FloatArray = NDArray[np.float64]


class LookupStatus(enum.Enum):
    """Why a look-up did or did not produce a value."""

    OK = "ok"  # t inside the data, interpolated between neighbours no further apart than max_gap_ns
    EMPTY = "empty"  # no sample yet
    BEFORE = "before"  # t earlier than the oldest sample kept
    AFTER = "after"  # t later than the newest sample (the caller asked for the future; wait or extrapolate)
    GAP = "gap"  # neighbours further apart than max_gap_ns (a dropout)


@dataclass(frozen=True, slots=True)
class FieldSpec:
    """One named field of a row."""

    name: str
    width: int
    interp: Interp = "linear"


@dataclass(frozen=True, slots=True)
class Lookup:
    """Result of :meth:`RingBuffer.sample`.

    ``row`` has shape ``(row_width,)`` and is valid only when ``status`` is OK (otherwise NaN).
    ``t_before``/``t_after`` are the neighbouring sample times used (or the data's range when outside).
    """

    status: LookupStatus
    row: FloatArray
    t_before: int
    t_after: int


class RingBuffer:
    """Timestamped samples of named vector fields.

    Parameters
    ----------
    capacity : int
        Samples kept; the oldest is overwritten when full.
    fields : sequence of FieldSpec
        Row layout, in order. Slerp fields must have width 4.
    max_gap_ns : int
        Largest spacing of two neighbours across which a look-up still interpolates.
    """

    def __init__(self, capacity: int, fields: Sequence[FieldSpec], *, max_gap_ns: int = 200_000_000) -> None:
        if capacity < 2:
            raise InputError(f"ring buffer capacity must be >= 2, got {capacity}")
        names = [f.name for f in fields]
        if len(set(names)) != len(names) or not names:
            raise InputError(f"ring buffer fields must be non-empty and unique, got {names}")
        self.capacity = capacity
        self.fields = tuple(fields)
        self.max_gap_ns = max_gap_ns
        self.slices: dict[str, slice] = {}
        offset = 0
        for f in fields:
            if f.interp == "slerp" and f.width != 4:
                raise InputError(f"slerp field {f.name!r} must have width 4, got {f.width}")
            self.slices[f.name] = slice(offset, offset + f.width)
            offset += f.width
        self.row_width = offset
        self._t = np.zeros(2 * capacity, dtype=np.int64)
        self._rows = np.full((2 * capacity, offset), np.nan)
        self._start = 0  # physical index of the oldest sample
        self._count = 0
        self._newest_ns = 0  # the newest time as a Python int (valid while _count): no numpy read per push
        self.rejected_out_of_order = 0
        self.overwritten = 0
        self._linear = [self.slices[f.name] for f in fields if f.interp == "linear"]
        self._slerp = [self.slices[f.name] for f in fields if f.interp == "slerp"]
        self._nearest = [self.slices[f.name] for f in fields if f.interp == "nearest"]

    def __len__(self) -> int:
        return self._count

    def push(self, t_ns: int, row: FloatArray | Sequence[float]) -> bool:
        """Append one sample. Returns False (and counts it) if ``t_ns`` is not after the newest sample."""
        if self._count and t_ns <= self._newest_ns:
            self.rejected_out_of_order += 1
            return False
        if self._count == self.capacity:
            self._start = (self._start + 1) % self.capacity
            self._count -= 1
            self.overwritten += 1
        i = (self._start + self._count) % self.capacity
        self._t[i] = t_ns
        self._t[i + self.capacity] = t_ns
        self._rows[i] = row
        self._rows[i + self.capacity] = row
        self._count += 1
        self._newest_ns = int(t_ns)
        return True

    def push_fields(self, t_ns: int, values: Mapping[str, FloatArray | Sequence[float]]) -> bool:
        """Append one sample given per-field values (convenience; :meth:`push` is the fast path)."""
        row = np.empty(self.row_width)
        for name, sl in self.slices.items():
            row[sl] = values[name]
        return self.push(t_ns, row)

    def times(self) -> NDArray[np.int64]:
        """Time stamps of the live window, oldest first (a view, shape ``(len,)``)."""
        return self._t[self._start : self._start + self._count]

    def rows(self) -> FloatArray:
        """Rows of the live window, oldest first (a view, shape ``(len, row_width)``)."""
        return self._rows[self._start : self._start + self._count]

    def transform(self, name: str, fn: Callable[[FloatArray], FloatArray]) -> None:
        """Replace the named field of every stored row with ``fn`` of it (``fn`` maps an array of shape
        ``(n, width)`` to one of the same shape): e.g. every buffered orientation turned by a heading reset."""
        sl = self.slices[name]
        half = self._rows[: self.capacity, sl]
        half[:] = fn(half.copy())
        self._rows[self.capacity :, sl] = half

    def field(self, row: FloatArray, name: str) -> FloatArray:
        """The named field of a row (a view)."""
        return row[..., self.slices[name]]

    def latest(self) -> tuple[int, FloatArray] | None:
        """Newest (time, row copy), or None if empty."""
        if not self._count:
            return None
        i = self._start + self._count - 1
        return int(self._t[i]), self._rows[i].copy()

    def time_range(self) -> tuple[int, int] | None:
        """(oldest, newest) sample times, or None if empty."""
        if not self._count:
            return None
        return int(self._t[self._start]), int(self._t[self._start + self._count - 1])

    def newest_ns(self) -> int | None:
        """The newest sample's time, or None if empty (:meth:`time_range`'s second half, without its tuple)."""
        return self._newest_ns if self._count else None

    def sample(self, t_ns: int) -> Lookup:
        """Interpolate every field at ``t_ns`` (see :class:`LookupStatus` for the outcomes)."""
        nan = np.full(self.row_width, np.nan)
        if not self._count:
            return Lookup(LookupStatus.EMPTY, nan, 0, 0)
        times = self.times()
        first, last = int(times[0]), int(times[-1])
        if t_ns < first:
            return Lookup(LookupStatus.BEFORE, nan, first, last)
        if t_ns > last:
            return Lookup(LookupStatus.AFTER, nan, first, last)
        k = int(np.searchsorted(times, t_ns, side="right")) - 1
        rows = self.rows()
        if times[k] == t_ns:
            return Lookup(LookupStatus.OK, rows[k].copy(), t_ns, t_ns)
        t0, t1 = int(times[k]), int(times[k + 1])
        if t1 - t0 > self.max_gap_ns:
            return Lookup(LookupStatus.GAP, nan, t0, t1)
        alpha = (t_ns - t0) / (t1 - t0)
        return Lookup(LookupStatus.OK, self._blend(rows[k], rows[k + 1], alpha), t0, t1)

    def _blend(self, a: FloatArray, b: FloatArray, alpha: float) -> FloatArray:
        out = np.empty(self.row_width)
        for sl in self._linear:
            out[sl] = a[sl] + alpha * (b[sl] - a[sl])
        for sl in self._slerp:
            out[sl] = quat_slerp(quat_normalize(a[sl]), quat_normalize(b[sl]), alpha)
        for sl in self._nearest:
            out[sl] = a[sl] if alpha < 0.5 else b[sl]
        return out

    def clear(self) -> None:
        """Forget every sample (e.g. after a device reconnects with a new clock)."""
        self._start = 0
        self._count = 0


#: Row layout of an IMU stream: orientation, acceleration and the device's own time stamp.
IMU_FIELDS = (
    FieldSpec("quat", 4, "slerp"),
    FieldSpec("acc", 3, "linear"),
    FieldSpec("device_time_s", 1, "linear"),
    FieldSpec("packet_counter", 1, "nearest"),
)
