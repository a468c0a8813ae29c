"""Streams and files of subjects without fingers are byte for byte what they were before fingers existed (issue 44):
every stream's bytes and every file's bytes for two fingerless subjects, hashed, against the digests the code
before fingers wrote (commit e59cca6, computed there with this same file).

The poses are rest poses with the root moved and two sized skeletons, so every number is computed exactly
(identity rotations: products with 0 and 1, sums of offsets) and the digests do not depend on the machine's
vector instructions; the structure (keys, field counts, headers, record layout) is what fingers could have
changed.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import Skeleton
from mocapd.io.session_export import SubjectTrack, write_csv
from mocapd.pipeline.scheduler import PersonPose, PoseFrame
from mocapd.protocols import session_format as sf
from mocapd.protocols.bvh_writer import bvh_text
from mocapd.protocols.gltf_writer import GltfSubject, glb_bytes
from mocapd.protocols.mvn import MvnEncoder
from mocapd.protocols.rokoko import RokokoActor, RokokoEncoder
from mocapd.protocols.vmc import VmcEncoder
from mocapd.protocols.ws_stream import ClientSession, FrameEncoder, StreamDescription, StreamOptions

SKELETON = Skeleton.from_height(1.75)
SHORT = Skeleton.from_height(1.6)
T_NS = 7_000_000_000


def _theta(skeleton: Skeleton, x: float, z: float) -> np.ndarray:
    theta = skeleton.rest_pose()
    theta[0], theta[2] = x, z
    return theta


def _frame() -> PoseFrame:
    people = []
    for k, (who, sk, x) in enumerate((("suit:suit0", SKELETON, 0.5), ("track:3", SHORT, -1.25))):
        theta = _theta(sk, x, -0.25)
        joints = Kinematics(sk).forward(theta).positions
        people.append(PersonPose(who, k, "suit0" if k == 0 else None, theta, joints, 0.875, 3, 13 if k == 0 else 0,
                                 4, True, None if sk is SKELETON else sk))  # fmt: skip
    return PoseFrame(frame=300, t_solve_ns=T_NS, tick_ns=T_NS + 50_000_000, people=people, missing_cameras=1)


def outputs(tmp: Path) -> dict[str, bytes]:
    """The bytes of every stream and file for :func:`_frame` (and a three-frame take of it)."""
    frame = _frame()
    out: dict[str, bytes] = {}
    desc = StreamDescription(60.0, {"default": SKELETON, "short": SHORT},
                             lambda i: "short" if i == "track:3" else "default")  # fmt: skip
    for encoding in ("msgpack", "json"):
        for conv in ("native", "unity"):
            opts = StreamOptions(encoding=encoding, convention=conv, globals=True)
            session = ClientSession(desc, opts)
            session.latest_subjects = ("suit:suit0", "track:3")
            hello, msg = session.hello(), FrameEncoder(frame, T_NS + 1000, desc).message(opts)
            out[f"ws hello {encoding} {conv}"] = hello if isinstance(hello, bytes) else hello.encode()
            out[f"ws frame {encoding} {conv}"] = msg if isinstance(msg, bytes) else msg.encode()
    thetas = np.stack([p.theta for p in frame.people])
    skeletons = [p.skeleton for p in frame.people]
    vmc = VmcEncoder(SKELETON).encode_many(T_NS, thetas, [True, False], skeletons)
    out["vmc"] = b"|".join(b"".join(bundles) for bundles in vmc)
    mvn = MvnEncoder(SKELETON).encode(300, T_NS, [(0, thetas[0]), (1, thetas[1])], skeletons)
    out["mvn"] = b"|".join(mvn)
    actors = [RokokoActor(p.identity, p.theta, (255, 59, 48), p.skeleton, k == 0) for k, p in enumerate(frame.people)]
    out["rokoko"] = RokokoEncoder(SKELETON, fps=60.0, compression="none").encode(300, T_NS, actors).data
    record = sf.PoseRecord(300, T_NS, T_NS + 50_000_000, 1, tuple(
        sf.PersonRecord(p.identity, p.suit, p.track, p.views, p.imus, p.iterations, p.converged, p.confidence,
                        p.theta, p.joints, p.skeleton, T_NS) for p in frame.people))  # fmt: skip
    out["session pose record"] = sf.encode_record(sf.T_POSE, sf.encode_pose(record))
    take = np.stack([thetas[0], _theta(SKELETON, 0.75, 0.0), _theta(SKELETON, 1.0, 0.25)])
    times = np.array([0.0, 1 / 60, 2 / 60])
    out["bvh"] = bvh_text(SKELETON.offsets, take, 60.0).encode()
    out["glb"] = glb_bytes([GltfSubject("suit:suit0", SKELETON.offsets, SKELETON.root_height, times, take),
                            GltfSubject("track:3", SHORT.offsets, SHORT.root_height, times, take)])  # fmt: skip
    track = SubjectTrack("suit:suit0", T_NS + np.arange(3, dtype=np.int64) * 16_666_667, take)
    write_csv(tmp / "take.csv", SKELETON, track)
    out["csv"] = (tmp / "take.csv").read_bytes()
    return out


def digests(tmp: Path) -> dict[str, str]:
    return {k: hashlib.sha256(v).hexdigest() for k, v in outputs(tmp).items()}


# Written by the code before fingers (commit e59cca6):
# `python -m tests.test_fingerless_outputs_unchanged`.
BEFORE_FINGERS: dict[str, str] = {
    "ws hello msgpack native": "bd0075158530ba91e5777c9d6e85aea6f6702ed4b142283e2fba74bc5a448b29",
    "ws frame msgpack native": "0025e7ba36bd3ef0ee33407f3356aecaae38b0cb300e78f0732e1a9702851dad",
    "ws hello msgpack unity": "59f9301ab3559956b42907d05d068a43e331c96d6e8c9d26b5d1218ab29e8e74",
    "ws frame msgpack unity": "cd8208197b92b6d713648cb4975a8163e0fa158cae374fb5262af957cf60091e",
    "ws hello json native": "f7f6d80a4aa2813896406c08d98546cb1f7ca567a68b1d14b7a919108d40d636",
    "ws frame json native": "08c2d26aafa7cea73de226521244c1e33d1bd3f35366e01709ea7e1dc2d1c023",
    "ws hello json unity": "1de26f6965ef0a86766968b1c9cc0fd66a49e6a69b3bf72ee1fbf819b8da4a25",
    "ws frame json unity": "8166cf2f86ccd61fd7b111ceb4ff65a4d910470af472aaf9a4d801b3ca0a3f49",
    "vmc": "ab4f1d350ed08479980ec9534e981e735738717711b863f1527212c0c08cc0e3",
    "mvn": "76e15f0c32c76ce355e0f67ec7c487436fd1cca4c3b4bfc0d2d8504b8ea45c03",
    "rokoko": "36f5ee9d024311fbac7d9c67595ed67651259f82f83687f7e03ed19e43cdea80",
    "session pose record": "78ff9ef899b1f6b127e60908cd34668b1947748e62713a333d7021e22d052afc",
    "bvh": "83267612fda2c4b96e680614fccc8efe8134769cdb9f826fd65d970208d90b2f",
    "glb": "6ce5f40591aef922fe5e897b57ad5b5100af932e1da0bbd958ac9909d6beaa2c",
    "csv": "ecdc80bfe6b373382fc2e3ed1143ed60e52db2b7897e793cfada45b8506a16e7",
}


def test_fingerless_streams_and_files_are_byte_identical_to_before_fingers(tmp_path: Path) -> None:
    assert digests(tmp_path) == BEFORE_FINGERS


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        print(json.dumps(digests(Path(d)), indent=4))
