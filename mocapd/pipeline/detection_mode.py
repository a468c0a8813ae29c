"""Which detection mode serves each pass best, from measured cost: a packed canvas or a whole frame.

Packed detection (:mod:`mocapd.pipeline.packing`) puts the regions around the people every camera saw last time
on shared canvases, so one inference serves several cameras; whole-frame detection runs one inference per camera
frame (at the camera's aspect, :func:`~mocapd.core.pose2d.fitted_input_size`). Which costs less depends on the
pass: three cameras whose people share a canvas cost a canvas; one camera left over costs a canvas too, or a
smaller whole frame.

:class:`ModeChooser` decides *per pass*, before it runs, from what each mode would cost for the camera frames it
would detect: the pixels of the network inputs it would run (the planned canvases, cropped where an export fits,
or the fitted whole frame) times that mode's measured detector time per pixel (the median of its last ``window``
passes, which holds the per-pass work beside the inference: canvas rendering, letterboxing, decoding; a median,
because on a shared machine single passes are slowed by other work, and a mode's first pass by its warm-up). The
cheaper per camera frame runs; the mode run last keeps the pass unless the other is cheaper by ``margin`` (no
flapping on noise). A mode measured on fewer than ``settle_passes`` passes gets another after ``explore_unsettled_s``
of detector time; a settled one unmeasured for ``explore_after_s`` is measured again from scratch (its window
emptied, ``settle_passes`` passes) when it is predicted within ``explore_margin`` of the other, and after
``explore_always_s`` whatever its prediction (an estimate measured while the machine was busy would otherwise never
be corrected), so that its estimate follows the machine.

Issue 15's epoch bandit ran each mode for 3 s epochs and re-checked the other every 15-120 s: when the two were
close (they are on the demo rig: a canvas of 2-3 cameras against 0.6 canvas per fitted whole frame), its whole
epochs cost throughput, and the `auto` run was the worst live (0.58 of the detector alone against 0.94 packed
only in the same session). Deciding per pass from cost has no epochs: the extra passes of the other mode are one
pass every ``explore_after_s``.

Pure: the caller passes each pass's detector time; nothing here reads a clock.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from mocapd.errors import InputError

MODES = ("packed", "whole")


@dataclass(frozen=True)
class PassCost:
    """What a candidate pass would detect and run: ``frames`` camera frames, ``pixels`` network input pixels."""

    frames: int
    pixels: int


@dataclass(frozen=True)
class ModeChooserOptions:
    """How a mode's cost is learned and compared."""

    window: int = 16
    """Passes of a mode whose median detector ns per input pixel is its cost."""
    settle_passes: int = 3
    """A mode measured on fewer passes than this is measured again soon (``explore_unsettled_s``)."""
    explore_unsettled_s: float = 3.0
    margin: float = 0.1
    """The mode that ran last keeps the pass unless the other is predicted cheaper per frame by this fraction."""
    explore_after_s: float = 30.0
    """Detector time after which a mode not run since gets one pass (when predicted within ``explore_margin``)."""
    explore_margin: float = 0.3
    explore_always_s: float = 120.0
    """Detector time after which a mode not run since gets one pass whatever its prediction."""

    def __post_init__(self) -> None:
        if self.window < 1 or self.settle_passes < 1 or not 0 <= self.margin < 1 or self.explore_margin < 0:
            raise InputError("mode chooser needs window >= 1, settle_passes >= 1, 0 <= margin < 1, explore_margin >= 0")
        if not 0 < self.explore_unsettled_s <= self.explore_after_s <= self.explore_always_s:
            raise InputError("mode chooser needs 0 < explore_unsettled_s <= explore_after_s <= explore_always_s")


@dataclass
class _Totals:
    passes: int = 0
    frames: int = 0
    usable: int = 0
    busy_ns: int = 0

    def per_s(self, what: int) -> float:
        return what / (self.busy_ns / 1e9) if self.busy_ns > 0 else 0.0


class ModeChooser:
    """Per pass: packed or whole, whichever is predicted to cost less detector time per camera frame.

    Parameters
    ----------
    options : ModeChooserOptions
    first : str
        The mode run when neither has been measured and both cost the same.
    """

    def __init__(self, options: ModeChooserOptions | None = None, first: str = "packed") -> None:
        if first not in MODES:
            raise InputError(f"detection mode {first!r} is not one of {list(MODES)}")
        self.options = options if options is not None else ModeChooserOptions()
        self.mode = first  # the mode of the last pass chosen
        self.switches = 0
        self.explorations = 0
        self.ns_per_pixel: dict[str, float | None] = dict.fromkeys(MODES)  # the median of ``_samples``
        self._samples: dict[str, deque[float]] = {m: deque(maxlen=self.options.window) for m in MODES}
        self.totals = {m: _Totals() for m in MODES}
        self.predicted: dict[str, float | None] = dict.fromkeys(MODES)  # ms per camera frame, last choice
        self._since_ns = dict.fromkeys(MODES, 0)  # detector time since each mode last ran

    def _rate(self, mode: str) -> float:
        """Detector ns per input pixel of ``mode``: measured, else the other's (then only pixels compare)."""
        own = self.ns_per_pixel[mode]
        other = self.ns_per_pixel[next(m for m in MODES if m != mode)]
        return own if own is not None else other if other is not None else 1.0

    def choose(self, packed: PassCost | None, whole: PassCost | None) -> str:
        """The mode of the next pass, given what each candidate would detect and run (None: not possible now)."""
        if packed is None and whole is None:
            raise InputError("mode chooser: no candidate pass")
        options = {m: c for m, c in (("packed", packed), ("whole", whole)) if c is not None and c.frames > 0}
        if not options:
            raise InputError("mode chooser: candidate passes detect no frame")
        cost = {m: self._rate(m) * c.pixels / c.frames for m, c in options.items()}
        self.predicted = {m: round(cost[m] / 1e6, 3) if m in cost else None for m in MODES}
        if len(cost) == 1:
            chosen = next(iter(cost))
        else:
            keep, other = self.mode, next(m for m in MODES if m != self.mode)
            chosen = other if cost[other] < (1 - self.options.margin) * cost[keep] else keep
            rest = next(m for m in MODES if m != chosen)
            o, since = self.options, self._since_ns[rest] / 1e9
            close = cost[rest] <= (1 + o.explore_margin) * cost[chosen]
            unsettled = len(self._samples[rest]) < o.settle_passes and since >= o.explore_unsettled_s
            if unsettled or (since >= o.explore_after_s and close) or since >= o.explore_always_s:
                if not unsettled:  # its estimate may be stale: measured again from scratch (settle_passes passes)
                    self._samples[rest].clear()
                chosen = rest
                self.explorations += 1
        if chosen != self.mode:
            self.switches += 1
        self.mode = chosen
        return chosen

    def record(self, mode: str, frames: int, usable: int, pixels: int, busy_ns: int) -> None:
        """One pass of ``mode`` ran: ``frames`` camera frames (``usable`` of them with someone in them) on
        ``pixels`` input pixels in ``busy_ns`` of detector time."""
        if mode not in MODES:
            raise InputError(f"detection mode {mode!r} is not one of {list(MODES)}")
        t = self.totals[mode]
        t.passes += 1
        t.frames += frames
        t.usable += usable
        t.busy_ns += max(0, busy_ns)
        if pixels > 0 and busy_ns > 0:
            self._samples[mode].append(busy_ns / pixels)
            self.ns_per_pixel[mode] = float(np.median(self._samples[mode]))
        for m in MODES:
            self._since_ns[m] = 0 if m == mode else self._since_ns[m] + max(0, busy_ns)

    def status(self) -> dict[str, Any]:
        """JSON-able: the last mode, the passes and rates of each mode (per detector second), the cost model."""
        chosen = max(MODES, key=lambda m: self.totals[m].passes)
        return {
            "mode": self.mode, "chosen": chosen, "switches": self.switches, "explorations": self.explorations,
            "passes": {m: t.passes for m, t in self.totals.items()},
            "rates": {m: {"usable_frames_per_s": round(t.per_s(t.usable), 2),
                          "camera_frames_per_s": round(t.per_s(t.frames), 2), "busy_s": round(t.busy_ns / 1e9, 2)}
                      for m, t in self.totals.items() if t.passes},
            "ns_per_pixel": {m: None if v is None else round(v, 4) for m, v in self.ns_per_pixel.items()},
            "predicted_ms_per_frame": dict(self.predicted),
        }  # fmt: skip
