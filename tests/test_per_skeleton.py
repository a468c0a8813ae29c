"""The per-skeleton cache: one part per distinct skeleton, by value."""

from __future__ import annotations

from mocapd.core.per_skeleton import PerSkeleton
from mocapd.core.skeleton import Skeleton


def test_equal_skeletons_share_a_part_and_none_is_the_default() -> None:
    built: list[float] = []

    def build(sk: Skeleton) -> float:
        built.append(sk.height)
        return sk.height

    cache = PerSkeleton(0.0, build, limit=2)
    assert cache.get(None) == 0.0 and built == []
    a, a_copy, b = Skeleton.from_height(1.6), Skeleton.from_height(1.6), Skeleton.from_height(1.9)
    assert cache.get(a) == 1.6 and cache.get(a_copy) == 1.6  # a decoded copy is the same skeleton
    assert cache.get(b) == 1.9 and built == [1.6, 1.9]
    assert cache.get(Skeleton.from_height(1.7)) == 1.7 and cache.get(a) == 1.6  # over the limit: rebuilt, not wrong
    assert built == [1.6, 1.9, 1.7, 1.6]
