"""Sequence numbers from outside (SlimeVR packet numbers, camera hosts' frame numbers), followed without being
captured by one absurd value (pure).

A receiver that adopts whatever number arrives last can be locked out by a single datagram: after packet number
2⁶⁴−1 every real packet is "older" and dropped, until the sender starts a new connection, which a SlimeVR tracker
never does on its own (issue 34). :class:`SequenceNumbers` takes a number as the next one only when it is
plausible:

- up to ``max_ahead`` past the last one: accepted, the numbers skipped counted as ``lost``;
- the last one or up to ``max_behind`` before it: a duplicate or a late (reordered) message, dropped and counted;
- anything else (a jump ahead beyond ``max_ahead``, or far behind): dropped and counted as a ``jump``.

Numbers that are not taken are remembered: when ``confirm`` of them in a row follow each other (each up to
``max_ahead`` after the one before), the sender really is elsewhere: it restarted its numbering or was silent for
long (a jump), or a forged number inside the window moved the sequence ahead of it (its own numbers now arrive as
"late" ones, one after the other: ``confirm_behind`` of them, more than a burst of reordered datagrams holds). The
sequence then *resynchronises* to the newest (counted in ``resyncs``), without counting the gap as lost.

So a forged number far off costs nothing but its own datagram; one inside the window costs the real sender at most
``confirm_behind - 1`` messages (and inflates ``lost`` by its step); a sender that restarted its numbering is
followed after ``confirm`` messages; a flood of random numbers resynchronises the sequence only when ``confirm``
consecutive ones happen to line up.
"""

from __future__ import annotations

from dataclasses import dataclass, field
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
    confirm_behind : int
        Late numbers in a row, each following the one before, after which the sequence goes back to them.
    last : int or None
        The last number taken (None: the first number is taken as it comes).
    """

    max_ahead: int
    max_behind: int
    confirm: int = 2
    confirm_behind: int = 3
    last: int | None = None
    lost: int = 0
    duplicates: int = 0
    reordered: int = 0
    jumps: int = 0
    resyncs: int = 0
    _chains: dict[bool, tuple[int, int]] = field(default_factory=dict)
    """Numbers not taken, per kind (late or a jump): the newest and how many in a row followed each other."""

    def __post_init__(self) -> None:
        if self.max_ahead < 1 or self.max_behind < 0 or self.confirm < 1 or self.confirm_behind < 1:
            raise ValueError(f"SequenceNumbers: max_ahead >= 1, max_behind >= 0, confirm >= 1 (got {self})")

    def reset(self, last: int | None = None) -> None:
        """A new connection or run: numbering starts again after ``last`` (None: from the first number)."""
        self.last = last
        self._chains.clear()

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
            self._chains.clear()
            return "next"
        # Not taken. Late numbers and jumps are followed apart: a forged number far off does not break the run of
        # the real sender's numbers that a forged number inside the window left behind, nor the other way round.
        late = -self.max_behind <= step <= 0
        newest, run = self._chains.get(late, (None, 0))
        run = run + 1 if newest is not None and 0 < number - newest <= self.max_ahead else 1
        self._chains[late] = (number, run)
        if run >= (self.confirm_behind if late else self.confirm):
            self.resyncs += 1
            self.reset(number)
            return "resync"
        if step == 0:
            self.duplicates += 1
            return "duplicate"
        if late:
            self.reordered += 1
            return "reordered"
        self.jumps += 1
        return "jump"
