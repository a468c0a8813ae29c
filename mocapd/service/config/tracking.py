"""The ``[tracking]`` section: detection sorting, enrolment and suit-binding options.

Each sub-table mirrors one frozen options dataclass of ``mocapd.core`` (same key names and defaults), which
``.options()`` builds: :class:`~mocapd.core.sorting.SortingOptions`, :class:`~mocapd.core.tracking.TrackingOptions`
and :class:`~mocapd.core.suit_binding.BindingOptions`.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Annotated

from pydantic import AfterValidator, Field

from mocapd.core.suit_binding import BindingOptions
from mocapd.service.config.schema import Pair, Section, Seq, unique

if TYPE_CHECKING:  # sorting's and tracking's modules load the cameras' model and kernels (NumBa): imported when used
    from mocapd.core.sorting import SortingOptions
    from mocapd.core.tracking import TrackingOptions

_B = BindingOptions()


@functools.cache
def _sorting() -> SortingOptions:
    from mocapd.core.sorting import SortingOptions

    return SortingOptions()


@functools.cache
def _tracking() -> TrackingOptions:
    from mocapd.core.tracking import TrackingOptions

    return TrackingOptions()


class SortingConfig(Section):
    """``[tracking.sorting]``: thresholds of Algorithm 1 (seed 003 §3.3.1)."""

    min_confidence: float = Field(default_factory=lambda: _sorting().min_confidence, ge=0.0, le=1.0)
    min_shared_keypoints: int = Field(default_factory=lambda: _sorting().min_shared_keypoints, ge=1, le=100)
    max_reprojection_error: float = Field(default_factory=lambda: _sorting().max_reprojection_error, gt=0.0, le=1.0)
    """Fraction of the image width."""
    same_person_distance: float = Field(default_factory=lambda: _sorting().same_person_distance, gt=0.0, le=10.0)
    max_interframe_movement: float = Field(default_factory=lambda: _sorting().max_interframe_movement, gt=0.0, le=100.0)
    flip_aware: bool = Field(default_factory=lambda: _sorting().flip_aware)
    """Pair keypoints of views that confused the person's left and right with their labels exchanged."""

    def options(self) -> SortingOptions:
        from mocapd.core.sorting import SortingOptions

        return self.build(SortingOptions)


class EnrolmentConfig(Section):
    """``[tracking.enrolment]``: who becomes a subject."""

    ordered = (("volume_min", "<", "volume_max"),)

    max_subjects: int = Field(default_factory=lambda: _tracking().max_subjects, ge=1, le=64)
    volume_min: Pair = Field(default_factory=lambda: _tracking().volume_min)
    """Floor rectangle [x, z] minimum corner (m)."""
    volume_max: Pair = Field(default_factory=lambda: _tracking().volume_max)
    enrol_after_s: float = Field(default_factory=lambda: _tracking().enrol_after_s, ge=0.0, le=60.0)
    enrol_frames: int = Field(default_factory=lambda: _tracking().enrol_frames, ge=1, le=1000)
    enrol_views: int = Field(default_factory=lambda: _tracking().enrol_views, ge=2, le=64)
    tentative_gap_s: float = Field(default_factory=lambda: _tracking().tentative_gap_s, ge=0.0, le=60.0)
    grace_period_s: float = Field(default_factory=lambda: _tracking().grace_period_s, ge=0.0, le=3600.0)
    start_positions: Annotated[Seq[Pair], Field(max_length=64), AfterValidator(unique)] = ()
    start_radius: float = Field(default_factory=lambda: _tracking().start_radius, gt=0.0, le=100.0)

    def options(self) -> TrackingOptions:
        from mocapd.core.tracking import TrackingOptions

        return self.build(TrackingOptions)


class BindingConfig(Section):
    """``[tracking.binding]``: which IMU suit belongs to which tracked person."""

    window_s: float = Field(_B.window_s, gt=0.0, le=60.0)
    min_samples: int = Field(_B.min_samples, ge=1, le=100_000)
    max_mean_angle_deg: float = Field(_B.max_mean_angle_deg, ge=0.0, le=180.0)
    switch_margin_deg: float = Field(_B.switch_margin_deg, ge=0.0, le=180.0)
    switch_after_s: float = Field(_B.switch_after_s, ge=0.0, le=60.0)

    def options(self) -> BindingOptions:
        return self.build(BindingOptions)


class TrackingConfig(Section):
    """The ``[tracking]`` section."""

    sorting: SortingConfig = Field(default_factory=SortingConfig)
    enrolment: EnrolmentConfig = Field(default_factory=EnrolmentConfig)
    binding: BindingConfig = Field(default_factory=BindingConfig)
