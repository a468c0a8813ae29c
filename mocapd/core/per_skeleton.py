"""A small cache of parts built from a skeleton (body sizing gives each person their own).

Keyed by the skeleton's values, not its identity: a session reader decodes a fresh but equal skeleton with every
record, and an identity key could be reused by a new object once the old one is collected. Bounded, so that people
coming and going over hours do not keep every skeleton ever seen.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Generic, TypeVar

from mocapd.core.skeleton import Skeleton

T = TypeVar("T")


def skeleton_key(skeleton: Skeleton) -> bytes:
    """A hashable key equal for equal skeletons (bone offsets and root height)."""
    return skeleton.offsets.tobytes() + repr(skeleton.root_height).encode()


class PerSkeleton(Generic[T]):
    """``get(skeleton)`` → ``build(skeleton)``, built once per distinct skeleton; ``None`` → the default part."""

    def __init__(self, default: T, build: Callable[[Skeleton], T], limit: int = 64) -> None:
        self.default = default
        self._build = build
        self._limit = limit
        self._parts: dict[bytes, T] = {}

    def get(self, skeleton: Skeleton | None) -> T:
        if skeleton is None:
            return self.default
        key = skeleton_key(skeleton)
        part = self._parts.get(key)
        if part is None:
            if len(self._parts) >= self._limit:
                self._parts.clear()
            part = self._parts[key] = self._build(skeleton)
        return part
