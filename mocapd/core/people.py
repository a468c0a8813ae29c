"""People: tracked subjects (detection sorting) and IMU suits (binding) combined into stable identities.

A person's identity is their suit when a suit is paired with their track (``suit:<id>``): suits cannot swap,
so a track that was exchanged between two people in close contact is re-attributed when the binder re-pairs.
A track without a suit keeps the tracker's identity (``track:<id>``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.sorting import Detections2D
from mocapd.core.suit_binding import BindingEvent, SuitBinder
from mocapd.core.tracking import SubjectTracker, TrackingEvent

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Person:
    """One person this frame."""

    identity: str
    track: int
    suit: str | None
    detections: dict[int, int]  # camera -> 2D person index, for the solver
    keypoints: FloatArray  # (17, 3) triangulated by the sorter (association only)
    binding_confidence: float | None = None


@dataclass(frozen=True)
class PeopleFrame:
    people: list[Person]
    bystanders: int
    tracking_events: list[TrackingEvent] = field(default_factory=list)
    binding_events: list[BindingEvent] = field(default_factory=list)


class PeopleTracker:
    """Detection sorting + enrolment, then (optionally) suit binding, one frame at a time."""

    def __init__(self, tracker: SubjectTracker, binder: SuitBinder | None = None) -> None:
        self.tracker = tracker
        self.binder = binder

    def update(
        self, t_ns: int, detections: list[Detections2D], suits: dict[str, dict[str, FloatArray]] | None = None
    ) -> PeopleFrame:
        """One frame: per-camera detections and, per streaming suit, its measured global bone orientations."""
        frame = self.tracker.update(t_ns, detections)
        seen = {s.id: s for s in frame.subjects if s.seen}
        binding_events: list[BindingEvent] = []
        suit_of: dict[int, str] = {}
        confidence: dict[str, float] = {}
        if self.binder is not None:
            binding_events = self.binder.update(t_ns, {k: s.last_points for k, s in seen.items()}, suits or {})
            suit_of = {track: suit for suit, track in self.binder.state.pairs.items()}
            confidence = self.binder.state.confidence
        people = []
        for k, s in seen.items():
            suit = suit_of.get(k)
            people.append(Person(
                identity=f"suit:{suit}" if suit is not None else f"track:{k}",
                track=k, suit=suit, detections=dict(s.detections), keypoints=s.last_points,
                binding_confidence=confidence.get(suit) if suit is not None else None,
            ))  # fmt: skip
        return PeopleFrame(people, frame.bystanders, frame.events, binding_events)
