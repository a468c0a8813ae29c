"""VRChat OSC trackers: bundles decoded with python-osc, the Unity frame and Euler angles checked against an
independent computation (scipy's rotations, an explicit mirror), tracker selection, height scaling, and the sink on
a real loopback socket."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage
from scipy.spatial.transform import Rotation

from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.errors import InputError
from mocapd.io.udp_stream import VrChatUdpSink
from mocapd.pipeline.scheduler import PersonPose, PoseFrame
from mocapd.protocols.vrchat import ROLES, TRACKERS, VrChatEncoder, unity_euler_deg

SKELETON = Skeleton.from_height(1.75)
MIRROR = np.diag([-1.0, 1.0, 1.0])  # Unity x is mocapd's -X (the subject's right); y up and z forward are shared


def decode(bundle: bytes) -> dict[str, tuple[float, ...]]:
    assert OscBundle.dgram_is_bundle(bundle)
    out = {}
    for item in OscBundle(bundle):
        assert isinstance(item, OscMessage) and item.address not in out
        out[item.address] = tuple(item.params)
    return out


def random_theta(rng: np.random.Generator) -> np.ndarray:
    return np.concatenate([[0.3, 0.95, -0.4], rng.normal(scale=0.5, size=63)])


def test_bundle_holds_every_documented_address_in_order() -> None:
    enc = VrChatEncoder(SKELETON)
    theta = random_theta(np.random.default_rng(1))
    bundle = enc.encode(theta)
    addresses = [m.address for m in OscBundle(bundle)]
    expected = []
    for n in [*range(1, 9), "head"]:
        expected += [f"/tracking/trackers/{n}/position", f"/tracking/trackers/{n}/rotation"]
    assert addresses == expected
    assert all(len(v) == 3 and all(isinstance(x, float) for x in v) for v in decode(bundle).values())
    assert len(bundle) < 1472


def test_positions_and_euler_angles_match_an_independent_computation() -> None:
    rng = np.random.default_rng(7)
    user = 1.62
    enc = VrChatEncoder(SKELETON, user_height_m=user)
    kin = Kinematics(SKELETON)
    for _ in range(20):
        theta = random_theta(rng)
        got = decode(enc.encode(theta))
        fk = kin.forward(theta)
        for role, (n, pos_bone, rot_bone) in TRACKERS.items():
            p = MIRROR @ fk.positions[BONE_INDEX[pos_bone]] * (user / SKELETON.height)
            np.testing.assert_allclose(got[f"/tracking/trackers/{n}/position"], p, atol=1e-5, err_msg=role)
            # Unity's eulerAngles: R = Ry(y) Rx(x) Rz(z), i.e. intrinsic Y, X, Z; the rotation seen in Unity's
            # mirrored axes is M R M.
            x, y, z = got[f"/tracking/trackers/{n}/rotation"]
            R_unity = Rotation.from_euler("YXZ", [y, x, z], degrees=True).as_matrix()
            np.testing.assert_allclose(R_unity, MIRROR @ fk.rotations[BONE_INDEX[rot_bone]] @ MIRROR, atol=1e-5)
        # The head tracker sits between the eyes: above the neck, in front of the head joint at rest.
        head = np.array(got["/tracking/trackers/head/position"])
        assert np.linalg.norm(head - MIRROR @ fk.positions[BONE_INDEX["Head"]] * user / SKELETON.height) < 0.2


def test_rest_pose_faces_forward_with_zero_angles() -> None:
    theta = np.zeros(66)
    theta[1] = SKELETON.root_height
    got = decode(VrChatEncoder(SKELETON).encode(theta))
    for n in [*range(1, 9), "head"]:
        np.testing.assert_allclose(got[f"/tracking/trackers/{n}/rotation"], (0.0, 0.0, 0.0), atol=1e-6)
    # Turned 90° to the subject's left (about +Y in mocapd's right-handed frame): Unity's y angle is -90.
    theta[3:6] = [0.0, np.pi / 2, 0.0]
    got = decode(VrChatEncoder(SKELETON, roles=["hip"]).encode(theta))
    np.testing.assert_allclose(got["/tracking/trackers/1/rotation"], (0.0, -90.0, 0.0), atol=1e-4)


def test_euler_angles_at_the_gimbal_lock() -> None:
    for x in (90.0, -90.0):
        R = Rotation.from_euler("YXZ", [30.0, x, 0.0], degrees=True).as_matrix()
        np.testing.assert_allclose(unity_euler_deg(R), (x, 30.0, 0.0), atol=1e-6)


def test_tracker_selection_and_validation() -> None:
    theta = random_theta(np.random.default_rng(3))
    got = decode(VrChatEncoder(SKELETON, roles=["right_foot", "hip", "left_foot"]).encode(theta))
    assert sorted(got) == sorted(f"/tracking/trackers/{n}/{k}" for n in (1, 3, 4) for k in ("position", "rotation"))
    for bad in (["hip", "tail"], [], ["hip", "hip"]):
        with pytest.raises(InputError):
            VrChatEncoder(SKELETON, roles=bad)
    with pytest.raises(InputError):
        VrChatEncoder(SKELETON, user_height_m=7.0)
    with pytest.raises(InputError):
        VrChatEncoder(SKELETON).encode(np.full(66, np.nan))
    assert set(ROLES) == {*TRACKERS, "head"}


def person(identity: str, theta: np.ndarray) -> PersonPose:
    return PersonPose(identity, 0, None, theta, Kinematics(SKELETON).forward(theta).positions, 1.0, 2, 0, 3, True)


@pytest.mark.asyncio
async def test_sink_streams_the_chosen_subject_to_a_loopback_socket() -> None:
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2.0)
    rng = np.random.default_rng(5)
    a, b = random_theta(rng), random_theta(rng)
    sink = VrChatUdpSink(SKELETON, rx.getsockname(), subject="suit:suit0", roles=["hip", "head"], rate_divisor=2)
    await sink.start()
    try:
        for n in range(4):
            sink.publish(PoseFrame(n, n * 16_666_667, n * 16_666_667, [person("track:1", a), person("suit:suit0", b)],
                                   0))  # fmt: skip
        got = [decode(rx.recv(65536)) for _ in range(2)]
        rx.setblocking(False)
        with pytest.raises(BlockingIOError):
            rx.recv(65536)
        expected = decode(VrChatEncoder(SKELETON, roles=["hip", "head"]).encode(b))
        assert got == [expected, expected]
        st = sink.status()
        assert (st["frames_seen"], st["frames_sent"], st["datagrams_sent"], st["datagrams_dropped"]) == (4, 2, 2, 0)
    finally:
        await sink.aclose()
        rx.close()
