"""mocapd's generated VRM 1.0 mannequin (issue 44) read back with pygltflib, the viewer libraries' pinned check, and
the server's avatar paths (real sockets on loopback)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pygltflib as gl
import pytest

from mocapd.core.hand_skeleton import HAND_BONE_NAMES, VRM0_NAMES, VRM1_NAMES, HandSkeleton
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import BONE_NAMES, Skeleton
from mocapd.errors import ConfigError, InputError
from mocapd.io.viewer_libs import FILES, lib_dir, viewer_lib_files, viewer_libs_current
from mocapd.io.ws_server import ServerSettings, WebSocketStreamServer, read_avatar
from mocapd.protocols.vrm_avatar import HUMAN_BONES, MERGED, avatar_vrm, default_avatar
from mocapd.protocols.ws_stream import StreamDescription
from mocapd.service.config import load_config
from tests.test_ws_server import http_get

#: VRM 1.0's required humanoid bones (the specification's table)
STREAM = StreamDescription(60.0, {"default": Skeleton.from_height()})
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


def test_the_vrm0_mannequin_faces_minus_z_with_vrm0_names() -> None:
    doc = _doc(avatar_vrm(version=0))
    ext = doc.extensions["VRM"]
    assert doc.extensionsUsed == ["VRM"] and ext["meta"]["title"] == "mocapd mannequin"
    bones = {b["bone"]: b["node"] for b in ext["humanoid"]["humanBones"]}
    assert {VRM0_NAMES[n] for n in HAND_BONE_NAMES} <= set(bones) and "leftThumbIntermediate" in bones
    world0, world1 = _world(doc), _world(_doc(avatar_vrm(version=1)))
    for name, w in world1.items():  # every joint turned 180° about +Y: the model's left is -X, its front -Z
        np.testing.assert_allclose(world0[name], w * np.array([-1.0, 1.0, -1.0]), atol=1e-6, err_msg=name)
    with pytest.raises(InputError, match="0 or 1"):
        avatar_vrm(version=2)


def test_a_users_avatar_is_read_once_and_a_bad_one_is_refused_by_name(tmp_path: Path) -> None:
    mine = tmp_path / "me.vrm"
    mine.write_bytes(avatar_vrm(version=0))
    assert read_avatar(str(mine)) == mine.read_bytes()
    with pytest.raises(ConfigError, match=r"\[websocket\] avatar: cannot read .*missing\.vrm"):
        read_avatar(str(tmp_path / "missing.vrm"))
    (tmp_path / "photo.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    with pytest.raises(ConfigError, match="is not a VRM"):
        WebSocketStreamServer(ServerSettings(port=0, avatar=str(tmp_path / "photo.png")), STREAM)
    # A relative path in a config file is the file's neighbour, whatever the working directory.
    (tmp_path / "rig.toml").write_text('[websocket]\navatar = "me.vrm"\n', encoding="utf-8")
    assert load_config(tmp_path / "rig.toml").websocket.avatar == str(mine)


@pytest.mark.asyncio
async def test_the_server_serves_a_users_avatar(tmp_path: Path) -> None:
    mine = tmp_path / "me.vrm"
    mine.write_bytes(avatar_vrm(version=0))
    srv = WebSocketStreamServer(ServerSettings(port=0, status_hz=0, avatar=str(mine)), STREAM)
    await srv.start()
    try:
        code, headers, body = await http_get(srv.port, "/avatar.vrm")
        assert code == 200 and headers["Content-Type"] == "model/gltf-binary" and body == mine.read_bytes()
    finally:
        await srv.aclose()
