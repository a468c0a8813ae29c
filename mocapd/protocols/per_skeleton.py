"""A small cache of per-skeleton encoder parts (body sizing gives each person their own skeleton).

Keyed by object identity (a skeleton is frozen and one person keeps theirs), bounded so that people coming and
going over hours do not keep every skeleton ever seen.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Generic, TypeVar

from mocapd.core.skeleton import Skeleton

T = TypeVar("T")


class PerSkeleton(Generic[T]):
    """``get(skeleton)`` → ``build(skeleton)``, built once per skeleton; ``None`` → the default part."""

    def __init__(self, default: T, build: Callable[[Skeleton], T], limit: int = 64) -> None:
        self.default = default
        self._build = build
        self._limit = limit
        self._parts: dict[int, tuple[Skeleton, T]] = {}

    def get(self, skeleton: Skeleton | None) -> T:
        if skeleton is None:
            return self.default
        hit = self._parts.get(id(skeleton))
        if hit is None or hit[0] is not skeleton:
            if len(self._parts) >= self._limit:
                self._parts.clear()
            hit = self._parts[id(skeleton)] = (skeleton, self._build(skeleton))
        return hit[1]
