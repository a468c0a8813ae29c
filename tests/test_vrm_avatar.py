"""mocapd's generated VRM 1.0 mannequin (issue 44) read back with pygltflib, the viewer libraries' pinned check, and
the server's avatar paths (real sockets on loopback)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pygltflib as gl
import pytest

from mocapd.core.hand_skeleton import HAND_BONE_NAMES, VRM1_NAMES, HandSkeleton
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import BONE_NAMES, Skeleton
from mocapd.io.viewer_libs import FILES, lib_dir, viewer_lib_files, viewer_libs_current
from mocapd.io.ws_server import ServerSettings, WebSocketStreamServer
from mocapd.protocols.vrm_avatar import HUMAN_BONES, MERGED, avatar_vrm, default_avatar
from mocapd.protocols.ws_stream import StreamDescription
from tests.test_ws_server import http_get

#: VRM 1.0's required humanoid bones (the specification's table)
LIMBS = ("UpperArm", "LowerArm", "Hand", "UpperLeg", "LowerLeg", "Foot")
REQUIRED = {"hips", "spine", "head", *(s + b for s in ("left", "right") for b in LIMBS)}


def _doc(data: bytes) -> gl.GLTF2:
    return gl.GLTF2.load_from_bytes(data)


def _world(doc: gl.GLTF2) -> dict[str, np.ndarray]:
    """Rest world position of every named node (translations only: every rest rotation is checked identity)."""
    out: dict[str, np.ndarray] = {}

    def walk(i: int, at: np.ndarray) -> None:
        n = doc.nodes[i]
        here = at + np.array(n.translation or [0.0, 0.0, 0.0])
        out[str(n.name)] = here
        for c in n.children or []:
            walk(c, here)

    for root in doc.scenes[0].nodes:
        walk(root, np.zeros(3))
    return out


def test_the_mannequin_is_a_vrm1_humanoid_with_mocapds_bones_at_mocapds_joints() -> None:
    skel = Skeleton.from_height(1.62)
    doc = _doc(avatar_vrm(skel))
    ext = doc.extensions["VRMC_vrm"]
    assert doc.extensionsUsed == ["VRMC_vrm"] and ext["specVersion"] == "1.0"
    assert ext["meta"]["authors"] == ["mocapd"] and "publicdomain/zero" in ext["meta"]["otherLicenseUrl"]
    human = {name: b["node"] for name, b in ext["humanoid"]["humanBones"].items()}
    assert set(human) >= REQUIRED
    assert {VRM1_NAMES[n] for n in HAND_BONE_NAMES} <= set(human)  # the 30 finger bones, VRM 1.0 names
    assert len(human) == len(HUMAN_BONES) == len(BONE_NAMES) - 1 + 30
    for node in doc.nodes:
        assert node.rotation is None or np.allclose(node.rotation, [0, 0, 0, 1])  # rest = T-pose, identity
    # Each humanoid node sits where mocapd's rest pose puts its bone's joint (body and fingers).
    rest = Kinematics(skel).forward(skel.rest_pose())
    hands = HandSkeleton.from_body(skel)
    want = {n: rest.positions[i] for i, n in enumerate(BONE_NAMES)}
    for h, side in enumerate(("Left", "Right")):  # at rest every frame is the world's: joints add up the offsets
        for b in range(15):
            parent = want[f"{side}Hand"] if b % 3 == 0 else want[HAND_BONE_NAMES[15 * h + b - 1]]
            want[HAND_BONE_NAMES[15 * h + b]] = parent + hands.offsets[h, b]
    world = _world(doc)
    for node_name, vrm, mocapd in HUMAN_BONES:
        assert doc.nodes[human[vrm]].name == node_name
        np.testing.assert_allclose(world[node_name], want[mocapd], atol=1e-6, err_msg=node_name)
    assert MERGED not in {m for _, _, m in HUMAN_BONES}
    # A skinned mesh whose every vertex follows one bone.
    (mesh_node,) = [n for n in doc.nodes if n.mesh is not None]
    assert mesh_node.skin == 0 and len(doc.skins[0].joints) == len(HUMAN_BONES)


def test_the_default_mannequin_is_built_once() -> None:
    assert default_avatar() is default_avatar()
    assert default_avatar()[:4] == b"glTF"


def test_the_viewer_libraries_are_served_only_when_every_file_is_the_pinned_one(tmp_path: Path) -> None:
    src = lib_dir()
    assert viewer_libs_current(src), "set-up fetched the viewer libraries (setup/steps/33-viewer-libs.sh)"
    copy = tmp_path / "lib"
    shutil.copytree(src, copy)
    files = viewer_lib_files(copy)
    assert set(files) == {"/lib/" + rel for rel in FILES}
    assert files["/lib/three/three.module.min.js"][0] == "text/javascript"
    meta = json.loads((src / "viewer_libs.json").read_text())
    assert {p["name"]: p["licence"].split()[0] for p in meta["packages"]} == {"three": "MIT", "@pixiv/three-vrm": "MIT"}
    with (copy / "three-vrm" / "three-vrm.module.min.js").open("ab") as f:
        f.write(b"// changed")
    assert viewer_lib_files(copy) == {} and not viewer_libs_current(copy)
    assert viewer_lib_files(tmp_path / "nothing") == {}


@pytest.mark.asyncio
async def test_the_server_serves_the_avatar_and_its_libraries() -> None:
    stream = StreamDescription(60.0, {"default": Skeleton.from_height()})
    srv = WebSocketStreamServer(ServerSettings(port=0, status_hz=0), stream)
    await srv.start()
    try:
        code, headers, body = await http_get(srv.port, "/avatar.vrm")
        assert code == 200 and headers["Content-Type"] == "model/gltf-binary" and body == default_avatar()
        code, headers, body = await http_get(srv.port, "/avatar.js")
        assert code == 200 and headers["Content-Type"] == "text/javascript" and b"createAvatarView" in body
        code, _, body = await http_get(srv.port, "/lib/three-vrm/three-vrm.module.min.js")
        assert code == 200 and body == (lib_dir() / "three-vrm" / "three-vrm.module.min.js").read_bytes()
        assert (await http_get(srv.port, "/lib/three/../../../etc/passwd"))[0] == 404
    finally:
        await srv.aclose()
    off = WebSocketStreamServer(ServerSettings(port=0, status_hz=0, viewer=False), stream)
    await off.start()
    try:
        assert (await http_get(off.port, "/avatar.vrm"))[0] == 404  # no viewer, no avatar
    finally:
        await off.aclose()
