"""Which detection mode serves this rig best, measured while it runs: whole frames or packed canvases.

Packed detection (:mod:`mocapd.pipeline.packing`) puts the regions around the people every camera saw last time
on shared canvases, so one inference serves several cameras; whole-frame detection runs one inference per camera
frame. Which delivers more depends on the rig: few small people in many cameras favour packing, people that fill
the frames (or a fast accelerator, on which a canvas costs what a frame costs) do not. :class:`ModeChooser` is a
small epoch bandit over the two: each mode runs for an epoch of detector time, its rate of *usable* camera frames
(frames in which the detector found at least one person) per second of detector time is measured, the better one
runs, and now and then (after 15 s of detector time, doubling up to ``explore_every_s``) the other gets one
epoch to show it has become better. Pure: the caller
passes the detector time each pass took; nothing here reads a clock.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from mocapd.errors import InputError

MODES = ("packed", "whole")


@dataclass(frozen=True)
class ModeChooserOptions:
    """Epoch lengths and the switching margin."""

    epoch_s: float = 3.0
    """Detector time of one epoch (one mode measured)."""
    explore_every_s: float = 120.0
    """Detector time spent in the better mode before the other gets an epoch again, at most: the first re-check
    comes after ``first_explore_s``, and the wait doubles each time the choice holds (a first comparison made
    during start-up, with empty ROIs and a loaded CPU, is corrected soon; a settled one costs one epoch in 41)."""
    first_explore_s: float = 15.0
    margin: float = 0.1
    """The other mode takes over only when its rate beats the current one's by this fraction."""

    def __post_init__(self) -> None:
        if not 0 < self.epoch_s <= self.first_explore_s <= self.explore_every_s or not 0 <= self.margin < 1:
            raise InputError("mode chooser needs 0 < epoch_s <= first_explore_s <= explore_every_s and 0 <= margin < 1")


@dataclass
class _Rate:
    usable: int = 0
    frames: int = 0
    busy_ns: int = 0

    def per_s(self, what: int) -> float:
        return what / (self.busy_ns / 1e9) if self.busy_ns > 0 else 0.0


class ModeChooser:
    """Epoch bandit over ``("packed", "whole")``: measure each, run the better, re-check the other now and then.

    Parameters
    ----------
    options : ModeChooserOptions
    first : str
        The mode measured first.
    """

    def __init__(self, options: ModeChooserOptions | None = None, first: str = "packed") -> None:
        if first not in MODES:
            raise InputError(f"detection mode {first!r} is not one of {list(MODES)}")
        self.options = options if options is not None else ModeChooserOptions()
        self.mode = first
        self.best: str | None = None  # the mode chosen after both were measured
        self.rates: dict[str, _Rate] = {}  # the last finished epoch of each mode
        self.epochs = 0
        self.switches = 0
        self._epoch = _Rate()
        self._since_explore_ns = 0
        self._explore_after_s = self.options.first_explore_s

    def record(self, mode: str, usable: int, frames: int, busy_ns: int) -> str:
        """One pass of ``mode``: ``frames`` camera frames detected, ``usable`` of them with someone in them, in
        ``busy_ns`` of detector time. Returns the mode to run next."""
        if mode != self.mode:  # a pass that started before the mode changed: not this epoch's
            return self.mode
        e = self._epoch
        e.usable += usable
        e.frames += frames
        e.busy_ns += max(0, busy_ns)
        if e.busy_ns >= self.options.epoch_s * 1e9:
            self._end_epoch()
        return self.mode

    def _end_epoch(self) -> None:
        finished, self._epoch = self._epoch, _Rate()
        self.rates[self.mode] = finished
        self.epochs += 1
        previous = self.mode
        other = next(m for m in MODES if m != self.mode)
        if other not in self.rates:
            self.mode = other  # not measured yet
        elif self.best is None or self.mode != self.best:
            # Both measured (first round, or an exploration epoch just ended): keep the incumbent unless the other
            # beats it by the margin.
            incumbent = self.best if self.best is not None else other
            challenger = next(m for m in MODES if m != incumbent)
            rate = {m: self.rates[m].per_s(self.rates[m].usable) for m in MODES}
            chosen = challenger if rate[challenger] > (1 + self.options.margin) * rate[incumbent] else incumbent
            held = chosen == self.best
            self.best = self.mode = chosen
            self._since_explore_ns = 0
            o = self.options
            self._explore_after_s = min(o.explore_every_s, 2 * self._explore_after_s) if held else o.first_explore_s
        else:
            self._since_explore_ns += finished.busy_ns
            # A drop three margins deep (a loaded CPU makes single epochs noisy; a smaller one waits its turn).
            fell = finished.per_s(finished.usable) * (1 + 3 * self.options.margin) < self.rates[other].per_s(
                self.rates[other].usable
            )
            if fell or self._since_explore_ns >= self._explore_after_s * 1e9:
                # One epoch to show it has become better: when its turn comes, or at once when the current mode's
                # last epoch fell below the other's last measured rate.
                self.mode = other
        if self.mode != previous:
            self.switches += 1

    def status(self) -> dict[str, Any]:
        """JSON-able: the mode now, the chosen one, and each mode's last measured rates (per detector second)."""
        return {
            "mode": self.mode, "chosen": self.best, "epochs": self.epochs, "switches": self.switches,
            "rates": {m: {"usable_frames_per_s": round(r.per_s(r.usable), 2),
                          "camera_frames_per_s": round(r.per_s(r.frames), 2), "busy_s": round(r.busy_ns / 1e9, 2)}
                      for m, r in self.rates.items()},
        }  # fmt: skip
