"""Camera views (mocapd.pipeline.camera_views) and their ``camera`` message (mocapd.protocols.ws_stream): a real
frame ring, frames kept pending until their capture time is solved, the pose and detection set nearest that
time, projections through the calibration, the reprojection error and the detection rate; the message in both
encodings and the ``cameras`` subscribe option."""

from __future__ import annotations

import asyncio
import base64
import json

import cv2
import numpy as np
import pytest
from websockets.asyncio.client import connect

from mocapd.core.camera import look_at
from mocapd.core.keypoints import coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import Skeleton
from mocapd.core.sorting import Detections2D
from mocapd.errors import ConfigError
from mocapd.io.ws_server import ServerSettings, WebSocketStreamServer
from mocapd.pipeline.camera_views import CameraViewOptions, CameraViews, LatestSnapshot, RingSnapshots, Snapshot
from mocapd.pipeline.frame_ring import FrameRing
from mocapd.pipeline.scheduler import PersonPose, PoseFrame
from mocapd.protocols.ws_stream import ClientSession, StreamDescription, camera_message, decode

SK = Skeleton.from_height(1.75)
CAM = look_at("cam0", np.array([0.0, 1.5, 4.0]), np.array([0.0, 1.0, 0.0]), 640, 480, 600.0)
TARGETS = coco17_targets(SK)
MS = 1_000_000


def _pose(frame: int, t_ns: int, x: float) -> PoseFrame:
    theta = SK.rest_pose()
    theta[0] = x
    joints = Kinematics(SK).forward(theta).positions
    return PoseFrame(frame, t_ns, t_ns, [PersonPose("track:1", 1, None, theta, joints, 0.9, 1, 0, 3, True)], 0)


def _detections(x: float, shift_px: float = 0.0) -> Detections2D:
    theta = SK.rest_pose()
    theta[0] = x
    fk = Kinematics(SK).forward(theta)
    sites = fk.positions[TARGETS.bones] + np.einsum("kij,kj->ki", fk.rotations[TARGETS.bones], TARGETS.offsets)
    uv = CAM.project(sites) + shift_px
    return Detections2D(uv[None], np.full((1, len(TARGETS)), 0.9))


def test_a_frame_waits_for_its_solve_and_gets_the_nearest_pose_and_detections() -> None:
    ring = FrameRing("cam0", 4, 480, 640, 3)
    ring.next_slot()[:] = 200
    ring.publish(host_ns=1000 * MS, device_ns=0, frame_id=1)
    views = CameraViews([CAM], TARGETS, SK, [RingSnapshots(ring)], CameraViewOptions(max_width=160))
    views.publish(_pose(1, 900 * MS, 0.0))
    assert views.views(1000 * MS) == []  # the frame (t = 1000 ms) is not solved yet: it waits
    for k, t in enumerate((960, 995, 1010, 1050)):
        views.on_detections(0, t * MS, _detections(0.1 * k, shift_px=3.0), t * MS + 30 * MS)
        views.publish(_pose(2 + k, t * MS, 0.1 * k))
    (view,) = views.views(1100 * MS)
    assert view.capture_ns == 1000 * MS and view.frame == 3  # the pose solved at 995 ms, nearest 1000 ms
    assert view.snapshot is not None and view.snapshot.image is not None
    assert view.snapshot.image.shape == (120, 160, 3) and int(view.snapshot.image.mean()) == 200  # downscaled
    joints = Kinematics(SK).forward(_pose(0, 0, 0.1).people[0].theta).positions
    np.testing.assert_allclose(view.subjects[0].joints, CAM.project(joints))
    np.testing.assert_allclose(view.detections[0, :, :2], _detections(0.1, 3.0).keypoints[0])
    assert view.reprojection_px == pytest.approx(3.0 * np.sqrt(2), abs=1e-6)  # every keypoint 3 px off in x and y
    assert view.detection_hz == pytest.approx(4 / 2.0)  # four sets in the last two seconds
    assert views.views(1100 * MS) == []  # no newer frame


def test_without_frames_the_newest_pose_is_drawn_and_far_detections_do_not_match() -> None:
    views = CameraViews([CAM], TARGETS, SK, [None])
    views.on_detections(0, 500 * MS, _detections(2.0), 520 * MS)  # another person, far from the solved one
    views.publish(_pose(7, 500 * MS, 0.0))
    (view,) = views.views(600 * MS)
    assert view.snapshot is None and view.frame == 7 and view.capture_ns == 500 * MS
    assert view.reprojection_px is None  # the detected person is hundreds of pixels from the subject
    with pytest.raises(ConfigError):
        CameraViews([CAM], TARGETS, SK, [])
    with pytest.raises(ConfigError):
        CameraViewOptions(rate_hz=0.0)


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
def test_camera_message_in_both_encodings(encoding: str) -> None:
    jpeg = bytes(cv2.imencode(".jpg", np.full((30, 40, 3), 99, np.uint8))[1].tobytes())
    source = LatestSnapshot()
    source.put(Snapshot(500 * MS, jpeg=jpeg))
    views = CameraViews([CAM], TARGETS, SK, [source])
    views.on_detections(0, 500 * MS, _detections(0.0), 510 * MS)
    views.publish(_pose(3, 500 * MS, 0.0))
    (view,) = views.views(600 * MS)
    msg = decode(camera_message(view, jpeg, (40, 30), encoding))
    assert msg["type"] == "camera" and msg["name"] == "cam0" and (msg["width"], msg["height"]) == (640, 480)
    assert msg["frame"] == 3 and msg["t_capture_ns"] == 500 * MS and msg["image_width"] == 40
    image = base64.b64decode(msg["image"]) if encoding == "json" else msg["image"]
    assert image == jpeg
    assert len(msg["detections"]) == 1 and len(msg["detections"][0]) == 3 * len(TARGETS)
    (subject,) = msg["subjects"]
    assert subject["id"] == "track:1" and len(subject["joints"]) == 42
    np.testing.assert_allclose(np.reshape(subject["joints"], (21, 2)), view.subjects[0].joints, atol=0.01)
    assert msg["reprojection_px"] == 0.0 and msg["detection_hz"] == 0.5


def test_cameras_option_needs_camera_views_and_caps_the_rate() -> None:
    plain = ClientSession(StreamDescription(60.0, {"default": SK}))
    plain.receive_message(json.dumps({"type": "subscribe", "cameras": True}))
    assert decode(plain.messages_to_send()[0])["code"] == "bad_field"
    desc = StreamDescription(60.0, {"default": SK}, cameras=(("cam0", 640, 480),), camera_rate_hz=5.0)
    s = ClientSession(desc)
    s.receive_message(json.dumps({"type": "subscribe", "cameras": True, "camera_rate_hz": 50, "encoding": "json"}))
    hello = decode(s.messages_to_send()[0])
    assert hello["cameras"] == [{"name": "cam0", "width": 640, "height": 480}]
    assert hello["camera_views"] is True and hello["camera_rate_hz"] == 5.0
    s.receive_message(json.dumps({"type": "subscribe", "camera_rate_hz": -1}))
    assert decode(s.messages_to_send()[0])["code"] == "bad_field"


@pytest.mark.asyncio
async def test_a_client_at_the_lowest_camera_rate_does_not_hold_back_the_next_one() -> None:
    """Found reviewing issue 18's rate checks: the camera loop slept ``1 / rate`` of the fastest client asking,
    so a first client at a tiny rate (1e-9 Hz: 30 years; now at least 0.01 Hz: 100 s) kept every later client
    waiting that long for its first camera message. The loop now wakes when a client changes its options."""
    views = CameraViews([CAM], TARGETS, SK, [None], CameraViewOptions(rate_hz=4.0))
    views.publish(_pose(7, 500 * MS, 0.0))
    srv = WebSocketStreamServer(ServerSettings(port=0, status_hz=0), StreamDescription(60.0, {"default": SK}),
                                camera_views=views)  # fmt: skip
    await srv.start()
    try:
        async with connect(srv.url) as slow, connect(srv.url) as other:
            for ws in (slow, other):
                assert decode(await ws.recv())["type"] == "hello"
            await slow.send(json.dumps({"type": "subscribe", "cameras": True, "camera_rate_hz": 0.01}))
            async with asyncio.timeout(5):
                assert decode(await slow.recv())["type"] == "hello"
                assert decode(await slow.recv())["type"] == "camera"  # the first one at once, the next in 100 s
            await other.send(json.dumps({"type": "subscribe", "cameras": True, "camera_rate_hz": 4}))
            async with asyncio.timeout(5):
                assert decode(await other.recv())["type"] == "hello"
                got = [decode(await other.recv())["type"] for _ in range(2)]
            assert got == ["camera", "camera"]  # at 4 Hz, not after the slow client's 100 s
    finally:
        await srv.aclose()
