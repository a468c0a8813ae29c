"""The WebSocket stream protocol on values and bytes: hello, frames in every convention (forward kinematics on
the received message must give the converted global positions), encode-once caching, subscribe requests and the
error replies to bad ones, and the status subset."""

from __future__ import annotations

import json
from dataclasses import replace
from typing import Any

import msgpack
import numpy as np
import pytest

from mocapd.core.rotations import quat_from_rotvec
from mocapd.core.skeleton import BONE_NAMES, PARENTS, Skeleton
from mocapd.protocols.conventions import convention
from mocapd.protocols.ws_stream import (
    STREAM_CONVENTIONS,
    ClientSession,
    FrameEncoder,
    StreamDescription,
    StreamOptions,
    decimation_for,
    decode,
    health_subset,
)
from tests.ws_support import fk_from_message, person, random_frame

SKEL = Skeleton.from_height(1.75)
TALL = Skeleton.from_height(1.95)


def description(**kw: Any) -> StreamDescription:
    return StreamDescription(rate_hz=60.0, skeletons={"default": SKEL}, **kw)


def test_hello_describes_bones_parents_offsets_and_options() -> None:
    s = ClientSession(description(), StreamOptions())
    s.latest_subjects = ("suit:suit0",)
    h = decode(s.hello())
    assert isinstance(s.hello(), bytes)  # msgpack by default: a binary message
    assert h["type"] == "hello" and h["v"] == 1 and h["convention"] == "native" and h["units"] == "m"
    assert h["bones"] == list(BONE_NAMES) and h["parents"] == list(PARENTS)
    sk = h["skeletons"]["default"]
    np.testing.assert_allclose(np.reshape(sk["offsets"], (21, 3)), SKEL.offsets, atol=1e-6)  # float32
    assert h["subjects"] == [{"id": "suit:suit0", "skeleton": "default"}]
    assert h["rate_hz"] == 60.0 and h["decimation"] == 1 and h["encodings"] == ["msgpack", "json"]


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
@pytest.mark.parametrize("conv", STREAM_CONVENTIONS)
def test_frame_round_trips_through_forward_kinematics_in_every_convention(conv: str, encoding: str) -> None:
    """Per-subject skeletons: FK in the target frame from the message equals conventions.py on the solved joints."""
    desc = StreamDescription(60.0, {"default": SKEL, "tall": TALL}, lambda i: "tall" if i == "person:7" else "default")
    frame = random_frame(np.random.default_rng(1), 42, ["suit:suit0", "person:7"], SKEL)
    frame.people[1] = person("person:7", frame.people[1].theta, TALL)
    session = ClientSession(desc)
    session.receive_message(json.dumps({"type": "subscribe", "convention": conv, "encoding": encoding,
                                        "globals": True}))  # fmt: skip
    hello = decode(session.messages_to_send()[0])
    msg = FrameEncoder(frame, 123, desc).message(session.options)
    assert isinstance(msg, str if encoding == "json" else bytes)
    f = decode(msg)
    assert f["type"] == "frame" and f["frame"] == 42 and f["t_solve_ns"] == frame.t_solve_ns
    assert f["t_publish_ns"] == 123
    c = convention(conv)
    tol = 2e-5 * c.scale * 4  # float32 / 6 decimals on metres-size values
    for sent, solved in zip(f["subjects"], frame.people, strict=True):
        assert sent["id"] == solved.identity
        offsets = hello["skeletons"][sent["skeleton"]]["offsets"]
        expected = c.positions(solved.joints)
        np.testing.assert_allclose(np.reshape(sent["joints"], (21, 3)), expected, atol=tol)
        np.testing.assert_allclose(fk_from_message(sent["root"], sent["rot"], offsets), expected, atol=3 * tol)
        # Quaternions are conventions.py's conversion of the local rotations (sign fixed by w >= 0).
        q = c.quaternions(quat_from_rotvec(solved.theta[3:].reshape(21, 3)))
        np.testing.assert_allclose(np.reshape(sent["rot"], (21, 4)), q, atol=1e-5)
    assert f["subjects"][1]["skeleton"] == "tall" and f["subjects"][0]["suit"] == "suit0"


def test_each_option_set_is_encoded_once_per_frame() -> None:
    desc = description()
    enc = FrameEncoder(random_frame(np.random.default_rng(2), 1, ["a", "b"], SKEL), 0, desc)
    a = StreamOptions(convention="unity")
    same = StreamOptions(convention="unity", decimation=3, status=False)  # frame bytes do not depend on these
    m1, m2 = enc.message(a), enc.message(same)
    assert m1 is m2 and enc.encodings == 1
    enc.message(StreamOptions(convention="unity", encoding="json"))
    enc.message(StreamOptions(convention="unity", subjects=frozenset({"b"})))
    enc.message(StreamOptions(convention="unity", globals=True))
    assert enc.encodings == 4
    assert [s["id"] for s in decode(enc.message(StreamOptions(subjects=frozenset({"b"}))))["subjects"]] == ["b"]
    assert "joints" not in decode(m1)["subjects"][0]


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
def test_a_frame_without_subjects(encoding: str) -> None:
    frame = random_frame(np.random.default_rng(6), 9, [], SKEL)
    f = decode(FrameEncoder(frame, 5, description()).message(StreamOptions(encoding=encoding, globals=True)))
    assert f["frame"] == 9 and f["subjects"] == []


def test_non_finite_subjects_are_left_out_and_counted() -> None:
    frame = random_frame(np.random.default_rng(3), 5, ["a", "b"], SKEL)
    bad = frame.people[0].theta.copy()
    bad[7] = np.nan
    frame.people[0] = person("a", bad, SKEL)
    enc = FrameEncoder(frame, 0, description())
    assert enc.non_finite == 1
    assert [s["id"] for s in json.loads(str(enc.message(StreamOptions(encoding="json"))))["subjects"]] == ["b"]


def test_subscribe_subset_rate_and_encoding_and_msgpack_requests() -> None:
    s = ClientSession(description())
    s.receive_message(msgpack.packb({"type": "subscribe", "subjects": ["b"], "rate_hz": 20, "encoding": "json"}))
    (reply,) = s.messages_to_send()
    assert isinstance(reply, str)  # the hello already comes in the new encoding
    h = json.loads(reply)
    assert h["decimation"] == 3 and h["rate_hz"] == 20.0 and h["subjects_filter"] == ["b"]
    assert [n for n in range(12) if s.wants(n)] == [0, 3, 6, 9]
    s.receive_message('{"type": "subscribe", "rate_hz": null, "subjects": null}')
    assert s.options.decimation == 1 and s.options.subjects is None and s.options.encoding == "json"
    assert decimation_for(60.0, 25.0) == 2 and decimation_for(60.0, 1000.0) == 1 and decimation_for(60, 0.5) == 120


@pytest.mark.parametrize(
    ("data", "code", "says"),
    [
        ("{not json", "bad_encoding", "not valid JSON"),
        (b"\xc1", "bad_encoding", "not valid msgpack"),
        ("[1, 2]", "bad_message", "must be a map"),
        ('{"type": "play"}', "unknown_type", "'play'"),
        ('{"type": "subscribe", "colour": 1}', "bad_field", "['colour']"),
        ('{"type": "subscribe", "convention": "blender"}', "bad_field", "'blender'"),
        ('{"type": "subscribe", "encoding": "xml"}', "bad_field", "'xml'"),
        ('{"type": "subscribe", "globals": 1}', "bad_field", "globals = 1"),
        ('{"type": "subscribe", "rate_hz": -5}', "bad_field", "rate_hz = -5"),
        ('{"type": "subscribe", "rate_hz": true}', "bad_field", "rate_hz = True"),
        ('{"type": "subscribe", "subjects": "a"}', "bad_field", "subjects must be a list"),
        ('{"type": "subscribe", "subjects": [1]}', "bad_field", "subject id 1"),
        ('{"type": "subscribe", "subjects": ["' + "x" * 200 + '"]}', "bad_field", "1..128"),
        ("[" * 5000 + "]" * 5000, "too_large", "at most 4096 bytes"),
        ("[" * 2000 + "]" * 2000, "bad_encoding", "not valid JSON"),
    ],
)
def test_bad_requests_get_an_error_reply_and_change_nothing(data: str | bytes, code: str, says: str) -> None:
    s = ClientSession(description(), StreamOptions(convention="unity"))
    before = s.options
    s.receive_message(data)
    (reply,) = s.messages_to_send()
    err = decode(reply)
    assert err["type"] == "error" and err["code"] == code and says in err["message"], err
    assert s.options == before and s.errors == 1
    s.receive_message('{"type": "subscribe", "convention": "unreal", "globals": 2}')  # atomic: nothing applied
    assert s.options == before


@pytest.mark.parametrize(
    "data",
    [
        '{"type": "subscribe", "rate_hz": 1e-20}',  # issue 18 D1: a decimation of 6e21 frames broke msgpack
        msgpack.packb({"type": "subscribe", "rate_hz": 1e-20}),
        '{"type": "subscribe", "rate_hz": 1e-300, "encoding": "json"}',  # JSON could carry the huge decimation
        '{"type": "subscribe", "rate_hz": ' + "9" * 400 + "}",  # issue 18 D2: no float of 400 digits
        msgpack.packb({"type": "subscribe", "rate_hz": 2**64 - 1}),
        '{"type": "subscribe", "rate_hz": NaN}',
        '{"type": "subscribe", "rate_hz": 1e999}',  # JSON's inf
        '{"type": "subscribe", "rate_hz": 0.009}',
        '{"type": "subscribe", "camera_rate_hz": ' + "9" * 400 + "}",
        '{"type": "subscribe", "camera_rate_hz": 1e-300}',  # the camera loop's next-due time overflowed
    ],
)
def test_extreme_rates_are_bad_fields_not_overflows(data: str | bytes) -> None:
    """Issue 18 D1, D2: a rate is checked for type, finiteness and range (0.01 Hz .. 1 MHz) before it is used,
    and answered with a short ``bad_field`` error (not an echo of 400 digits); the session keeps working."""
    s = ClientSession(description(cameras=(("cam0", 640, 480),)))
    before = s.options
    error = s.receive_message(data)
    (reply,) = s.messages_to_send()
    err = decode(reply)
    assert error is not None and error.code == "bad_field"
    assert err["type"] == "error" and err["code"] == "bad_field" and "rate_hz" in err["message"]
    assert len(err["message"]) < 160, err["message"]
    assert s.options == before and s.errors == 1
    assert s.receive_message('{"type": "subscribe", "rate_hz": 1e9}') is not None  # above 1 MHz
    assert s.receive_message('{"type": "subscribe", "rate_hz": 0.01, "camera_rate_hz": 1' + "0" * 30 + "}")
    s.messages_to_send()
    assert s.receive_message('{"type": "subscribe", "rate_hz": 0.01, "camera_rate_hz": 0.01}') is None
    assert decode(s.messages_to_send()[0])["decimation"] == 6000 and s.options.camera_rate_hz == 0.01
    assert s.receive_message(msgpack.packb({"type": "subscribe", "rate_hz": 10**6})) is None  # every frame
    assert decode(s.messages_to_send()[0])["decimation"] == 1


def test_status_carries_the_health_subset_and_client_counters() -> None:
    health = {
        "uptime_s": 12.5, "ready": True,
        "output": {"configured_hz": 60.0, "achieved_hz": 59, "frames": 700, "missed_ticks": 1, "latency_s": 0.15},
        "latency_ms": {"end_to_end": {"count": 5, "mean_ms": 160.0, "p50": 158.0, "p95": 170.0, "p99": 171.0}},
        "cameras": [{"name": "cam0", "kind": "synthetic", "frames": 300, "skipped": 0}],
        "imu": {"devices": [{"path": "/dev/pts/3", "streaming": True, "samples": 900, "disconnects": 0,
                             "serial": 7}],
                "slimevr": {"listen": "127.0.0.1:6969", "trackers": [
                    {"id": "A1:B2:C3:D4:E5:01", "connected": True, "packets": 4000, "lost": 0, "sensors": []}]}},
        "tasks": {"imu": {"failures": 0, "running": True}},
        "governor": {"step": 1, "shed": "keypoint tracking at half rate", "reason": "tick p95 12.0 ms",
                     "changes": 1, "tick_p95_ms": 12.0, "detector_duty": 1.0, "tracking_rate": 0.5},
    }  # fmt: skip
    s = ClientSession(description())
    st = decode(s.status(health, 99, {"clients": 2, "sent": 10, "dropped": 1}))
    assert st["type"] == "status" and st["t_ns"] == 99
    assert st["latency_ms"]["end_to_end"] == {"p50": 158.0, "p95": 170.0, "p99": 171.0}
    assert st["cameras"] == [{"name": "cam0", "kind": "synthetic", "frames": 300}]
    assert st["imus"][0] == {"path": "/dev/pts/3", "streaming": True, "samples": 900, "disconnects": 0}
    # SlimeVR trackers are listed too (a tracker-only rig's viewer said "IMUs: none").
    assert st["imus"][1] == {"path": "slimevr A1:B2:C3:D4:E5:01", "streaming": True, "samples": 4000,
                             "disconnects": None}  # fmt: skip
    assert decode(s.status({"imu": {"devices": [], "slimevr": None}}, 1, {}))["imus"] == []
    assert st["tasks"] == {"imu": 0} and st["stream"]["dropped"] == 1 and st["output"]["missed_ticks"] == 1
    # What the governor sheds, and why, reaches the viewer (issue 39).
    assert st["governor"] == {"step": 1, "shed": "keypoint tracking at half rate", "reason": "tick p95 12.0 ms"}
    assert health_subset({}) == {}
    # The bumped-camera watch's verdict reaches the viewer's camera rows (issue 43).
    watched = {**health, "camera_watch": {"cam0": {"state": "bumped", "residual_px": 40.0}}}
    assert health_subset(watched)["cameras"] == [{"name": "cam0", "kind": "synthetic", "frames": 300,
                                                   "watch": "bumped"}]  # fmt: skip


def test_description_validates() -> None:
    with pytest.raises(ValueError, match="at least one skeleton"):
        StreamDescription(60.0, {})
    with pytest.raises(ValueError, match="> 0 Hz"):
        StreamDescription(0.0, {"d": SKEL})


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
def test_the_output_mode_and_each_poses_instant_are_carried(encoding: str) -> None:
    """``hello.output`` says whether suit wearers are predicted; every subject says which instant its pose is for
    (a predicted one later than the solve time, the others at it)."""
    frame = random_frame(np.random.default_rng(2), 7, ["suit:suit0", "track:1"], SKEL)
    ahead = frame.t_solve_ns + 137_000_000
    frame.people[0] = replace(frame.people[0], t_pose_ns=ahead)
    session = ClientSession(description(output="predicted"), StreamOptions(encoding=encoding))
    assert decode(session.hello())["output"] == "predicted"
    assert decode(ClientSession(description()).hello())["output"] == "delayed"
    msg = decode(FrameEncoder(replace(frame, output="predicted"), 0, description()).message(session.options))
    assert [s["t_pose_ns"] for s in msg["subjects"]] == [ahead, frame.t_solve_ns]
    with pytest.raises(ValueError, match="output"):
        description(output="early")


def test_calibrate_imu_requests_are_checked_and_handed_to_the_daemon() -> None:
    """Issue 42: the guided IMU calibration asked over the WebSocket; a bad pose, suit or cancel is a bad_field."""
    s = ClientSession(description())
    assert s.receive_message(json.dumps({"type": "calibrate_imu", "suit": "alice", "pose": "a-pose"})) is None
    assert s.receive_message(json.dumps({"type": "calibrate_imu", "cancel": True})) is None
    assert s.commands_received() == [
        ("calibrate_imu", {"suit": "alice", "pose": "a-pose", "cancel": None}),
        ("calibrate_imu", {"suit": None, "pose": None, "cancel": True}),
    ]
    for bad, said in (({"pose": "y-pose"}, "pose = 'y-pose'"), ({"suit": ""}, "suit = ''"),
                      ({"cancel": 1}, "cancel = 1"), ({"when": 3}, "unknown key(s) ['when']")):  # fmt: skip
        error = s.receive_message(json.dumps({"type": "calibrate_imu", **bad}))
        assert error is not None and error.code == "bad_field" and said in str(error), (bad, error)
    assert s.commands_received() == []
    unknown = s.receive_message(json.dumps({"type": "calibrate"}))
    assert unknown is not None and "'calibrate_imu'" in str(unknown)
