"""People: tracked subjects (detection sorting) and IMU suits (binding) combined into stable identities.

A person's identity is their suit when a suit is paired with their track (``suit:<id>``): suits cannot swap,
so a track that was exchanged between two people in close contact is re-attributed when the binder re-pairs.
A track without a suit keeps the tracker's identity (``track:<id>``).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

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

    def __init__(self, tracker: SubjectTracker, binder: SuitBinder | None = None, history: int = 100) -> None:
        self.tracker = tracker
        self.binder = binder
        self.events: deque[TrackingEvent | BindingEvent] = deque(maxlen=history)
        self._bystanders = 0

    def update(
        self,
        t_ns: int,
        detections: list[Detections2D],
        suits: dict[str, dict[str, FloatArray]] | None = None,
        frames: Sequence[int] | None = None,
    ) -> PeopleFrame:
        """One frame: per-camera detections and, per streaming suit, its measured global bone orientations;
        ``frames``, per camera, the detection frame the detections come from (:meth:`SubjectTracker.update`)."""
        frame = self.tracker.update(t_ns, detections, frames)
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
        self.events.extend(frame.events)
        self.events.extend(binding_events)
        self._bystanders = frame.bystanders
        return PeopleFrame(people, frame.bystanders, frame.events, binding_events)

    def status(self) -> dict[str, Any]:
        """JSON-able state for the daemon's status: subjects, the suit pairing with its confidence, and the
        recent enrolments, releases, pairings and re-pairings."""
        binding = self.binder.state if self.binder is not None else None
        return {
            "subjects": [
                {"id": s.id, "seen": s.seen, "last_seen_ns": s.last_seen_ns, "enrolled_ns": s.enrolled_ns,
                 "views": len(s.detections)}
                for s in self.tracker.subjects
            ],
            "bystanders": self._bystanders,
            "suits": None if binding is None else {
                suit: {"track": track, "confidence": round(binding.confidence.get(suit, 0.0), 3),
                       "mean_angle_deg": round(binding.mean_angle_deg.get(suit, float("nan")), 2)}
                for suit, track in binding.pairs.items()
            },
            "events": [_event_dict(e) for e in self.events],
        }  # fmt: skip


def _event_dict(e: TrackingEvent | BindingEvent) -> dict[str, Any]:
    if isinstance(e, TrackingEvent):
        return {"t_ns": e.t_ns, "kind": e.kind, "subject": e.subject}
    return {"t_ns": e.t_ns, "kind": e.kind, "suit": e.suit, "track": e.track, "previous_track": e.previous_track}
