"""Stable subject slots (MVN character ids, VMC avatars): pinned, lowest free, released after absence."""

from __future__ import annotations

import pytest

from mocapd.errors import InputError
from mocapd.protocols.subjects import SubjectSlots


def test_subject_slots() -> None:
    slots = SubjectSlots(3, pinned={"suit:p": 2}, release_after=2)
    assert slots.assign(["track:1", "suit:p", "track:2"]) == [0, 2, 1]
    assert slots.assign(["track:3", "track:2"]) == [None, 1]  # 0 still held by track:1 (absent 1 frame)
    assert slots.unassigned == 1
    assert slots.assign(["track:3", "track:2"]) == [0, 1]  # track:1 absent 2 frames: released
    assert slots.held() == {"track:3": 0, "track:2": 1, "suit:p": 2}
    only = SubjectSlots(4, allowed={"suit:a"})
    assert only.assign(["track:1", "suit:a"]) == [None, 0]
    with pytest.raises(InputError, match="distinct"):
        SubjectSlots(4, pinned={"a": 1, "b": 1})
    with pytest.raises(InputError, match="outside"):
        SubjectSlots(2, pinned={"a": 2})
