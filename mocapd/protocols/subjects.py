"""Stable small-integer slots for the subjects of an outgoing stream (MVN character ids, VMC destinations).

Solved people carry string identities (``suit:<id>`` for suited people, ``track:<k>`` otherwise, see
:mod:`mocapd.core.people`). Engine protocols address characters by a small integer: MVN's one-byte character id,
or, for VMC (one avatar per receiver), the index of the destination. :class:`SubjectSlots` gives each identity a
slot that stays the same for as long as the identity keeps appearing:

- identities pinned in the configuration always get their pinned slot;
- any other identity (when the stream is not restricted to a list) gets the lowest slot that is neither pinned nor
  held, in order of appearance within the frame;
- a slot is released once its identity has been absent for ``release_after`` consecutive frames, so the short-lived
  ``track:<k>`` identities of people walking in and out do not exhaust the slots;
- identities beyond the capacity, or not in the allowed list, get ``None`` (not streamed) and are counted.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence

from mocapd.errors import InputError


class SubjectSlots:
    """Identity → slot allocator (pure; call :meth:`assign` once per output frame).

    Parameters
    ----------
    capacity : int
        Number of slots (0 .. capacity-1).
    pinned : mapping identity -> slot
        Fixed slots from the configuration (distinct, within the capacity).
    allowed : collection of identities or None
        Only these identities are streamed; None streams every identity.
    release_after : int
        Frames of absence after which an automatically assigned slot is freed (>= 1).
    """

    def __init__(
        self,
        capacity: int,
        pinned: Mapping[str, int] | None = None,
        allowed: Collection[str] | None = None,
        release_after: int = 120,
    ) -> None:
        pinned = dict(pinned or {})
        if capacity < 1:
            raise InputError(f"slot capacity must be >= 1, got {capacity}")
        if release_after < 1:
            raise InputError(f"release_after must be >= 1 frame, got {release_after}")
        bad = {k: v for k, v in pinned.items() if not 0 <= v < capacity}
        if bad:
            raise InputError(f"pinned slots {bad} outside 0..{capacity - 1}")
        if len(set(pinned.values())) != len(pinned):
            raise InputError(f"pinned slots must be distinct, got {pinned}")
        self.capacity = capacity
        self.pinned = pinned
        self.allowed = None if allowed is None else frozenset(allowed)
        self.release_after = release_after
        self._held: dict[str, int] = {}  # identity -> slot (automatic assignments only)
        self._absent: dict[str, int] = {}  # identity -> consecutive frames absent
        self.unassigned = 0
        """Subjects not streamed because no slot was free (counted per frame and subject)."""

    def assign(self, identities: Sequence[str]) -> list[int | None]:
        """Slots for this frame's subjects, in the given order (None: not streamed)."""
        present = set(identities)
        for ident in list(self._held):
            if ident in present:
                self._absent[ident] = 0
                continue
            self._absent[ident] = self._absent.get(ident, 0) + 1
            if self._absent[ident] >= self.release_after:
                del self._held[ident]
                del self._absent[ident]
        taken = set(self.pinned.values()) | set(self._held.values())
        out: list[int | None] = []
        for ident in identities:
            if self.allowed is not None and ident not in self.allowed:
                out.append(None)
                continue
            slot = self.pinned.get(ident, self._held.get(ident))
            if slot is None:
                slot = next((s for s in range(self.capacity) if s not in taken), None)
                if slot is None:
                    self.unassigned += 1
                else:
                    self._held[ident] = slot
                    self._absent[ident] = 0
                    taken.add(slot)
            out.append(slot)
        return out

    def held(self) -> dict[str, int]:
        """Current identity → slot table (pinned and automatic)."""
        return {**self._held, **self.pinned}
