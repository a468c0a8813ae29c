"""Motion naming conventions: small BVH files written here in each naming are read and retargeted exactly.

Each file is our own 21-bone motion re-expressed in another convention's hierarchy (clavicles and hand tips
inserted, a spine joint merged away, toes replaced by an end site), so the joints the convention maps must land
exactly where our forward kinematics put them; a left/right swap, or a clavicle taken for a shoulder, would be off
by decimetres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest
from numpy.typing import NDArray

from mocapd.core.kinematics import Kinematics
from mocapd.core.naming import match_roles, normalized_names
from mocapd.core.retarget import retarget
from mocapd.core.skeleton import BONE_INDEX, BONE_NAMES, PARENTS, Skeleton
from mocapd.core.synthetic import moving_sequence
from mocapd.errors import InputError
from mocapd.io.bvh import parse_bvh
from mocapd.protocols.bvh_writer import euler_zxy_from_matrix

FloatArray = NDArray[np.float64]
N_FRAMES = 90


@dataclass
class Joint:
    name: str
    parent: int
    offset: FloatArray
    rot: FloatArray  # (n_frames, 3, 3) local rotation
    end: FloatArray = field(default_factory=lambda: np.zeros(3))


class Tree:
    """A source hierarchy built from our skeleton by exact edits (inserted joints have identity rotation)."""

    def __init__(self, skeleton: Skeleton, theta: FloatArray) -> None:
        local = Kinematics(skeleton).forward(theta).local
        self.root = theta[:, :3]
        self.joints = [
            Joint(n, p, skeleton.offsets[i].copy(), local[:, i])
            for i, (n, p) in enumerate(zip(BONE_NAMES, PARENTS, strict=True))
        ]
        for i in (BONE_INDEX[n] for n in ("Head", "LeftHand", "RightHand", "LeftToes", "RightToes")):
            self.joints[i].end = 0.5 * skeleton.offsets[i]

    def idx(self, name: str) -> int:
        return next(i for i, j in enumerate(self.joints) if j.name == name)

    def insert_above(self, child: str, name: str) -> None:
        """A joint halfway along ``child``'s offset (identity rotation)."""
        c = self.joints[self.idx(child)]
        half = 0.5 * c.offset
        new = Joint(name, c.parent, half.copy(), np.broadcast_to(np.eye(3), c.rot.shape).copy())
        self.joints.append(new)
        c.parent, c.offset = len(self.joints) - 1, half

    def add_leaf(self, parent: str, name: str) -> None:
        """A leaf at ``parent``'s end site (identity rotation)."""
        p = self.joints[self.idx(parent)]
        self.joints.append(Joint(name, self.idx(parent), p.end.copy(), np.broadcast_to(np.eye(3), p.rot.shape).copy()))

    def merge_up(self, name: str) -> None:
        """Remove a joint whose rotation is the identity: its children hang from its parent."""
        k = self.idx(name)
        gone = self.joints[k]
        assert np.allclose(gone.rot, np.eye(3))
        for j in self.joints:
            if j.parent == k:
                j.parent, j.offset = gone.parent, j.offset + gone.offset
        self._delete(k)

    def leaf_to_end_site(self, name: str) -> None:
        k = self.idx(name)
        self.joints[self.joints[k].parent].end = self.joints[k].offset
        self._delete(k)

    def _delete(self, k: int) -> None:
        self.joints.pop(k)
        for j in self.joints:
            j.parent = j.parent - 1 if j.parent > k else j.parent

    def rename(self, names: dict[str, str], prefix: str = "") -> None:
        for j in self.joints:
            j.name = prefix + names.get(j.name, j.name)

    def bvh(self) -> str:
        """BVH text in centimetres, ZXY rotations on every joint (depth-first order)."""
        children: dict[int, list[int]] = {i: [] for i in range(len(self.joints))}
        for i, j in enumerate(self.joints):
            if j.parent >= 0:
                children[j.parent].append(i)
        lines, order = ["HIERARCHY"], []

        def emit(i: int, d: int) -> None:
            j, pad = self.joints[i], "  " * d
            order.append(i)
            ch = (
                "6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"
                if j.parent < 0
                else "3 Zrotation Xrotation Yrotation"
            )
            lines.extend(
                [
                    f"{pad}{'ROOT' if j.parent < 0 else 'JOINT'} {j.name}",
                    f"{pad}{{",
                    f"{pad} OFFSET {' '.join(f'{100 * v:.6f}' for v in j.offset)}",
                    f"{pad} CHANNELS {ch}",
                ]
            )
            for c in children[i]:
                emit(c, d + 1)
            if not children[i]:
                lines.extend(
                    [
                        f"{pad} End Site",
                        f"{pad} {{",
                        f"{pad}  OFFSET {' '.join(f'{100 * v:.6f}' for v in j.end)}",
                        f"{pad} }}",
                    ]
                )
            lines.append(f"{pad}}}")

        emit(next(i for i, j in enumerate(self.joints) if j.parent < 0), 0)
        angles = np.stack([euler_zxy_from_matrix(self.joints[i].rot) for i in order], axis=1)
        values = np.concatenate([100 * self.root, angles.reshape(N_FRAMES, -1)], axis=1)
        lines += ["MOTION", f"Frames: {N_FRAMES}", "Frame Time: 0.0166667"]
        lines += [" ".join(f"{v:.6f}" for v in row) for row in values]
        return "\n".join(lines) + "\n"


def _side(table: dict[str, str]) -> dict[str, str]:
    """Expand ``{S}``/``{C}`` (Left/L) entries of a rename table to both sides."""
    out = {}
    for ours, theirs in table.items():
        for S, C in (("Left", "l"), ("Right", "r")):
            out[ours.replace("{S}", S)] = (
                theirs.replace("{S}", S).replace("{s}", S.lower()).replace("{C}", C.upper()).replace("{c}", C)
            )
    return out


def _daz(t: Tree) -> None:
    for S, c in (("Left", "l"), ("Right", "r")):
        t.insert_above(f"{S}UpperArm", f"{c}Collar")
        t.insert_above(f"{S}UpperLeg", f"{c}Buttock")
        t.add_leaf(f"{S}Hand", f"{c}Mid1")
        t.leaf_to_end_site(f"{S}Toes")  # CMU's DAZ-friendly takes end at the foot
    t.rename(
        {
            "Hips": "hip",
            "Spine": "abdomen",
            "Spine1": "abdomen2",
            "Spine2": "chest",
            "Spine3": "chestUpper",
            "Neck": "neck",
            "Head": "head",
        }
        | _side(
            {
                "{S}UpperArm": "{c}Shldr",
                "{S}LowerArm": "{c}ForeArm",
                "{S}Hand": "{c}Hand",
                "{S}UpperLeg": "{c}Thigh",
                "{S}LowerLeg": "{c}Shin",
                "{S}Foot": "{c}Foot",
            }
        )
    )


def _autodesk(t: Tree, prefix: str, spine3: bool) -> None:
    if not spine3:
        t.merge_up("Spine3")
    for S in ("Left", "Right"):
        t.insert_above(f"{S}UpperArm", f"{S}Shoulder")  # the clavicle, in this convention
        t.add_leaf(f"{S}Hand", f"{S}HandMiddle1")
        t.add_leaf(f"{S}Toes", f"{S}Toe_End")
    t.rename(
        _side(
            {
                "{S}UpperArm": "{S}Arm",
                "{S}LowerArm": "{S}ForeArm",
                "{S}UpperLeg": "{S}UpLeg",
                "{S}LowerLeg": "{S}Leg",
                "{S}Toes": "{S}ToeBase",
            }
        ),
        prefix,
    )


def _smpl(t: Tree, prefix: str, style: str) -> None:
    t.merge_up("Spine3")
    for S in ("Left", "Right"):
        t.insert_above(f"{S}UpperArm", f"{S}Collar")
        t.add_leaf(f"{S}Hand", f"{S}HandTip")
    table = {
        "{S}Collar": "{x}collar",
        "{S}UpperArm": "{x}shoulder",
        "{S}LowerArm": "{x}elbow",
        "{S}Hand": "{x}wrist",
        "{S}HandTip": "{x}hand",
        "{S}UpperLeg": "{x}hip",
        "{S}LowerLeg": "{x}knee",
        "{S}Foot": "{x}ankle",
        "{S}Toes": "{x}foot",
    }
    x = "{s}_" if style == "lower" else "{C}_"
    names = _side({k: v.replace("{x}", x) for k, v in table.items()})
    if style != "lower":
        names = {k: v[:2] + v[2:].capitalize() for k, v in names.items()}
    centre = {
        "Hips": "pelvis",
        "Spine": "spine1",
        "Spine1": "spine2",
        "Spine2": "spine3",
        "Neck": "neck",
        "Head": "head",
    }
    if style != "lower":
        centre = {k: v.capitalize() for k, v in centre.items()}
    t.rename(centre | names, prefix)
    assert len(t.joints) == 24


def _mvn_segments(t: Tree) -> None:
    for S in ("Left", "Right"):
        t.insert_above(f"{S}UpperArm", f"{S}Shoulder")
    t.rename(
        {"Hips": "Pelvis", "Spine": "L5", "Spine1": "L3", "Spine2": "T12", "Spine3": "T8"}
        | _side({"{S}LowerArm": "{S}ForeArm", "{S}Toes": "{S}Toe"})
    )
    assert len(t.joints) == 23


def _mvn_bvh(t: Tree) -> None:
    for S in ("Left", "Right"):
        t.insert_above(f"{S}UpperArm", f"{S}Collar")
    t.rename(
        {"Spine": "Chest", "Spine1": "Chest2", "Spine2": "Chest3", "Spine3": "Chest4"}
        | _side(
            {
                "{S}UpperArm": "{S}Shoulder",
                "{S}LowerArm": "{S}Elbow",
                "{S}Hand": "{S}Wrist",
                "{S}UpperLeg": "{S}Hip",
                "{S}LowerLeg": "{S}Knee",
                "{S}Foot": "{S}Ankle",
                "{S}Toes": "{S}Toe",
            }
        )
    )


CASES = {
    "daz_poser": ("daz_poser", _daz),
    "mixamo": ("autodesk", lambda t: _autodesk(t, "mixamorig:", spine3=False)),
    "humanik": ("autodesk", lambda t: _autodesk(t, "Character1_", spine3=True)),
    "smpl": ("smpl", lambda t: _smpl(t, "", "lower")),
    "smpl_unity": ("smpl", lambda t: _smpl(t, "m_avg_", "upper")),
    "mvn_segments": ("mvn", _mvn_segments),
    "mvn_bvh": ("mvn", _mvn_bvh),
}


@pytest.fixture(scope="module")
def motion() -> tuple[Skeleton, FloatArray]:
    sk = Skeleton.from_height(1.7)
    theta = moving_sequence(sk, N_FRAMES, seed=5)
    theta[:, 3 + 3 * BONE_INDEX["Spine3"] : 6 + 3 * BONE_INDEX["Spine3"]] = 0.0  # so conventions may merge it away
    return sk, theta


@pytest.mark.parametrize("case", sorted(CASES))
def test_file_in_each_naming_retargets_exactly(case: str, motion: tuple[Skeleton, FloatArray]) -> None:
    sk, theta = motion
    convention, build = CASES[case]
    tree = Tree(sk, theta)
    build(tree)
    source = parse_bvh(tree.bvh(), case)  # the unit (cm) is detected from the leg length
    assert match_roles(source.joint_names).convention == convention
    r = retarget(source)
    truth = Kinematics(sk).forward(theta).positions
    shift = (r.positions - truth).mean(axis=(0, 1))  # retargeting re-centres the clip and stands it on the floor
    err = np.linalg.norm(r.positions - truth - shift, axis=-1)
    assert float(err.max()) < 1e-4, f"{BONE_NAMES[int(err.max(axis=0).argmax())]} off by {1e3 * err.max():.2f} mm"
    lengths = np.linalg.norm(r.skeleton.offsets, axis=1)
    np.testing.assert_allclose(lengths, np.linalg.norm(sk.offsets, axis=1), atol=1e-4)


def test_prefixes_and_namespaces_are_stripped() -> None:
    assert normalized_names(["mixamorig:Hips", "mixamorig:LeftArm"]) == ["hips", "leftarm"]
    assert normalized_names(["Character1_Hips", "Character1_LeftUpLeg"]) == ["hips", "leftupleg"]
    assert normalized_names(["rig|root|Hips", "Spine"]) == ["hips", "spine"]
    # "LeftArm"/"LeftLeg" share "Left" but no underscore: nothing is stripped.
    assert normalized_names(["LeftArm", "LeftLeg"]) == ["leftarm", "leftleg"]


def test_unknown_naming_lists_the_joints_expected() -> None:
    names = ["Root", "Torso", "Skull", "ArmL", "ArmR"]
    with pytest.raises(InputError) as exc:
        match_roles(names, "odd")
    msg = str(exc.value)
    assert "match no known naming convention" in msg and "'odd'" in msg
    for expected in ("daz_poser lacks", "lshldr", "smpl lacks", "left_shoulder", "autodesk lacks", "leftarm", "ArmL"):
        assert expected in msg
    assert "\n" not in msg
