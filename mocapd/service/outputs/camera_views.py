"""The camera panels' taps on a running daemon: one :class:`~mocapd.pipeline.camera_views.CameraViews` per
daemon, fed by its detection tap and its pose sinks, reading each camera's frames where the rig has them."""

from __future__ import annotations

from typing import TYPE_CHECKING

from mocapd.pipeline.camera_views import CameraViewOptions, CameraViews, RingSnapshots, SnapshotSource
from mocapd.pipeline.frame_ring import FrameRing
from mocapd.pipeline.keypoint_source import DetectorKeypointSource, KeypointSource
from mocapd.sim.camera_frames import SyntheticFrames
from mocapd.sim.world import SyntheticKeypointSource

if TYPE_CHECKING:
    from mocapd.service.daemon import Daemon


def snapshot_source(source: KeypointSource) -> SnapshotSource | None:
    """Where a keypoint source's frames are: its capture ring (a camera, a video), a drawing of the synthetic
    world it simulates, or nowhere."""
    if isinstance(source, SyntheticKeypointSource):
        return SyntheticFrames(source.world, source.camera, source.epoch_ns, source.clock)
    ring = getattr(getattr(source, "frames", None), "ring", None)
    if isinstance(ring, FrameRing):
        stamp = source.capture_ns if isinstance(source, DetectorKeypointSource) else None
        return RingSnapshots(ring, stamp)
    return None


def attach_camera_views(daemon: Daemon, options: CameraViewOptions | None = None) -> CameraViews:
    """Camera views of ``daemon``'s rig, registered as a detection tap and a pose sink (they only keep
    references there: the work happens when a viewer asks, see :mod:`mocapd.pipeline.camera_views`)."""
    rig = daemon.rig
    views = CameraViews(rig.cameras, rig.targets, rig.skeleton, [snapshot_source(s) for s in rig.sources], options)
    daemon.detection_taps.append(views.on_detections)
    daemon.sinks.append(views)
    # a camera recalibrated while running: the subjects projected through its new pose
    daemon.camera_taps.append(lambda change: views.set_camera(change.index, change.camera))
    return views
