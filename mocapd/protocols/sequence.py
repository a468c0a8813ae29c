"""Sequence numbers from outside (SlimeVR packet numbers, camera hosts' frame numbers), followed without being
captured by one absurd value (pure).

A receiver that adopts whatever number arrives last can be locked out by a single datagram: after packet number
2⁶⁴−1 every real packet is "older" and dropped, until the sender starts a new connection, which a SlimeVR tracker
never does on its own (issue 34). :class:`SequenceNumbers` takes a number as the next one only when it is
plausible:

- up to ``max_ahead`` past the last one: accepted, the numbers skipped counted as ``lost``;
- the last one or up to ``max_behind`` before it: a duplicate or a late (reordered) message, dropped and counted;
- anything else (a jump ahead beyond ``max_ahead``, or far behind): dropped and counted as a ``jump``, and
  remembered; when ``confirm`` such numbers in a row follow each other (each within ``max_ahead`` of the one
  before), the sender really did move on (it restarted its numbering, or was silent for a long time): the
  sequence *resynchronises* to the newest one (counted in ``resyncs``), without counting the gap as lost.

So one forged number costs nothing but its own datagram, a sender that restarted its numbering is followed after
``confirm`` messages, and a flood of random numbers can make it resynchronise only as often as ``confirm``
consecutive numbers happen to line up.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Verdict = Literal["next", "duplicate", "reordered", "jump", "resync"]


@dataclass(slots=True)
class SequenceNumbers:
    """One sender's sequence numbers (see the module docstring).

    Parameters
    ----------
    max_ahead : int
        Largest step forward taken as the next number (``lost`` counts the numbers skipped).
    max_behind : int
        How far behind the last number a message still counts as late (``reordered``) rather than a jump.
    confirm : int
        Numbers in a row, each following the one before, after which a jump is followed.
    last : int or None
        The last number taken (None: the first number is taken as it comes).
    """

    max_ahead: int
    max_behind: int
    confirm: int = 2
    last: int | None = None
    lost: int = 0
    duplicates: int = 0
    reordered: int = 0
    jumps: int = 0
    resyncs: int = 0
    _candidate: int | None = None
    _agreeing: int = 0

    def __post_init__(self) -> None:
        if self.max_ahead < 1 or self.max_behind < 0 or self.confirm < 1:
            raise ValueError(f"SequenceNumbers: max_ahead >= 1, max_behind >= 0, confirm >= 1 (got {self})")

    def reset(self, last: int | None = None) -> None:
        """A new connection or run: numbering starts again after ``last`` (None: from the first number)."""
        self.last = last
        self._candidate = None
        self._agreeing = 0

    def take(self, number: int) -> Verdict:
        """Judge ``number``: ``"next"`` and ``"resync"`` are taken (``last`` becomes it), the others dropped."""
        last = self.last
        if last is None:
            self.last = number
            return "next"
        step = number - last
        if 0 < step <= self.max_ahead:
            self.lost += step - 1
            self.last = number
            self._candidate = None
            return "next"
        if step == 0:
            self.duplicates += 1
            return "duplicate"
        if -self.max_behind <= step < 0:
            self.reordered += 1
            return "reordered"
        self.jumps += 1
        candidate = self._candidate
        if candidate is not None and 0 < number - candidate <= self.max_ahead:
            self._agreeing += 1
        else:
            self._agreeing = 1
        self._candidate = number
        if self._agreeing >= self.confirm:
            self.jumps -= 1  # this one is taken after all
            self.resyncs += 1
            self.reset(number)
            return "resync"
        return "jump"
