"""Retargeting recorded motion onto the 21-bone skeleton of DESIGN.md.

Input: a :class:`~mocapd.core.motion.SourceMotion` (any joint names, rest pose, units already metres). Output:
a per-clip sized :class:`Skeleton`, θ per frame, and the skeleton's global joint positions and bone rotations.

Method (name mapping + rest-pose alignment):

1. **Name mapping.** Each of our joints is matched to a source joint through the file's naming convention
   (:mod:`mocapd.core.naming`: CMU ASF and BVH, Mixamo, HumanIK, Bandai, Xsens MVN, DAZ/Poser, SMPL); a foot
   without a toe joint uses its end site. Our four spine joints have no single counterpart: they are placed along
   the source's spine polyline (hips → neck base) at our default arc-length fractions.
2. **Rest-pose alignment.** Each of our bones is driven by one source joint's global rotation ``G_s(t)`` through
   a constant alignment ``C_b``: ``Q_b(t) = G_s(t) · C_b``. ``C_b`` maps our T-pose bone axes to the source
   joint's local frame; it is found from the data, not from the source's rest pose (which may be a T-pose,
   arms-down or, for Bandai, every bone along X): the bone direction (joint → child joint) and a second,
   anatomical direction — the hip or shoulder line for the trunk, the elbow/knee hinge axis for limbs — are
   averaged over the clip in the source joint's frame and aligned with their T-pose counterparts. The twist of
   every bone therefore follows the source, and its rest twist is the anatomical one whatever the source's
   conventions.
3. **Sizing.** Our bone offsets are the clip averages of ``Q_p(t)ᵀ (x_b(t) − x_p(t))`` over the mapped source
   joints, so forward kinematics reproduces the source joints (a test checks it on every shared file).
4. **Placement.** The clip is moved so its mean root position is above the origin and its feet stand on the
   floor (the 1st percentile of the lowest foot/toe joint at the floor term's radius).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.kinematics import Kinematics
from mocapd.core.motion import SourceMotion
from mocapd.core.naming import CONVENTIONS, match_roles
from mocapd.core.rotations import rotvec_from_matrix
from mocapd.core.skeleton import _DEFAULT_OFFSETS, BONE_INDEX, BONE_NAMES, N_BONES, POSE_DIM, Skeleton
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

MIN_HINGE_DEG = 20.0
"""Elbow/knee bend (degrees) above which the hinge axis of a frame is used for the limb's twist."""


@dataclass(frozen=True)
class Retargeted:
    """A clip on the 21-bone skeleton.

    Attributes
    ----------
    name : str
    skeleton : Skeleton
        Sized to the source subject.
    theta : array, shape (n_frames, 66)
    positions : array, shape (n_frames, 21, 3)
        Global joint positions of ``theta`` on ``skeleton`` (metres).
    rotations : array, shape (n_frames, 21, 3, 3)
        Global bone rotations.
    source_positions : array, shape (n_frames, 21, 3)
        The mapped source joints (same placement), the reference of the retargeting error.
    fps : float
    """

    name: str
    skeleton: Skeleton
    theta: FloatArray
    positions: FloatArray
    rotations: FloatArray
    source_positions: FloatArray
    fps: float

    @property
    def n_frames(self) -> int:
        return int(self.theta.shape[0])

    def joint_error(self) -> FloatArray:
        """Distance (m) of each retargeted joint from its mapped source joint, shape (n_frames, 21)."""
        return np.asarray(np.linalg.norm(self.positions - self.source_positions, axis=-1))


def _unit(v: FloatArray) -> FloatArray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.asarray(v / np.where(n > 1e-12, n, 1.0))


def _basis(a: FloatArray, b: FloatArray) -> FloatArray:
    """Orthonormal frame (columns) with first axis along ``a`` and second towards ``b``; shapes (..., 3)."""
    e1 = _unit(a)
    e2 = _unit(b - np.sum(b * e1, axis=-1, keepdims=True) * e1)
    e3 = np.cross(e1, e2)
    return np.stack((e1, e2, e3), axis=-1)


def _chain(motion: SourceMotion, top: int, bottom: int) -> list[int]:
    """Joints from ``bottom`` up to ``top`` (inclusive), ordered bottom → top."""
    path = [top]
    j = top
    while j != bottom:
        j = motion.parents[j]
        if j < 0:
            raise InputError(f"retarget {motion.name!r}: neck joint is not below the hips joint")
        path.append(j)
    return path[::-1]


def _spine_points(x: FloatArray, chain: list[int], fractions: FloatArray) -> tuple[FloatArray, list[int]]:
    """Points at arc-length fractions of the rest-length polyline through ``chain``; and the driving joint."""
    seg = np.linalg.norm(x[0, chain[1:]] - x[0, chain[:-1]], axis=-1)
    cum = np.concatenate(([0.0], np.cumsum(seg)))
    total = cum[-1]
    if total <= 1e-6:
        raise InputError("retarget: the source spine has no length")
    pts, drivers = [], []
    for fr in fractions:
        s = fr * total
        k = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
        while seg[k] <= 1e-9 and k < len(seg) - 1:
            k += 1
        a = (s - cum[k]) / max(seg[k], 1e-9)
        if a > 1.0 - 1e-6 and k < len(seg) - 1:  # on a joint: the segment below it drives the point
            k, a = k + 1, 0.0
        pts.append((1 - a) * x[:, chain[k]] + a * x[:, chain[k + 1]])
        drivers.append(chain[k])
    return np.stack(pts, axis=1), drivers


def retarget(motion: SourceMotion, floor_clearance: float = 0.05) -> Retargeted:
    """Retarget a clip (see the module doc). The clip should already be at the wanted frame rate."""
    G, x = motion.forward()
    f = motion.n_frames
    J = match_roles(motion.joint_names, motion.name).joints
    toe_x = {side: _toe_positions(motion, J, G, x, side) for side in "lr"}
    # Our spine joints at our default arc-length fractions between the hips and the neck base.
    d = _DEFAULT_OFFSETS
    lens = np.array([np.linalg.norm(d[n]) for n in ("Spine", "Spine1", "Spine2", "Spine3", "Neck")])
    fractions = np.cumsum(lens)[:4] / np.sum(lens)
    chain = _chain(motion, J["neck_base"], J["hips"])
    spine_x, spine_drv = _spine_points(x, chain, fractions)

    src = np.zeros((f, N_BONES, 3))
    driver = np.zeros(N_BONES, dtype=np.intp)

    def put(bone: str, pos: FloatArray, drv: int) -> None:
        src[:, BONE_INDEX[bone]] = pos
        driver[BONE_INDEX[bone]] = drv

    put("Hips", x[:, J["hips"]], J["hips"])
    for k, name in enumerate(("Spine", "Spine1", "Spine2", "Spine3")):
        put(name, spine_x[:, k], spine_drv[k])
    put("Neck", x[:, J["neck_base"]], motion.parents[J["head"]])
    put("Head", x[:, J["head"]], J["head"])
    for side, S in (("l", "Left"), ("r", "Right")):
        put(f"{S}UpperArm", x[:, J[side + "shoulder"]], J[side + "shoulder"])
        put(f"{S}LowerArm", x[:, J[side + "elbow"]], J[side + "elbow"])
        put(f"{S}Hand", x[:, J[side + "wrist"]], J[side + "wrist"])
        put(f"{S}UpperLeg", x[:, J[side + "hip"]], J[side + "hip"])
        put(f"{S}LowerLeg", x[:, J[side + "knee"]], J[side + "knee"])
        put(f"{S}Foot", x[:, J[side + "ankle"]], J[side + "ankle"])
        put(f"{S}Toes", toe_x[side], J.get(side + "toe", J[side + "ankle"]))

    def P(name: str) -> FloatArray:  # noqa: N802 (reads as the position symbol)
        return src[:, BONE_INDEX[name]]

    hip_line = P("LeftUpperLeg") - P("RightUpperLeg")
    shoulder_line = P("LeftUpperArm") - P("RightUpperArm")
    trunk_up = P("Neck") - P("Hips")
    forward = np.cross(_unit(shoulder_line), _unit(trunk_up))
    all_frames = np.ones(f, dtype=bool)
    X, Y, Z = np.eye(3)

    # (bone, primary world vector, its T-pose direction, secondary world vector, T-pose direction, valid frames)
    specs: list[tuple[str, FloatArray, FloatArray, FloatArray, FloatArray, BoolArray]] = []
    specs.append(("Hips", hip_line, X, P("Spine1") - P("Hips"), Y, all_frames))
    spine_names = ("Spine", "Spine1", "Spine2", "Spine3", "Neck")
    for k, name in enumerate(spine_names[:-1]):
        a = fractions[k]
        left = (1 - a) * _unit(hip_line) + a * _unit(shoulder_line)
        specs.append((name, P(spine_names[k + 1]) - P(name), Y, left, X, all_frames))
    specs.append(("Neck", P("Head") - P("Neck"), Y, shoulder_line, X, all_frames))
    head_end = motion.end_sites[J["head"]]
    if np.linalg.norm(head_end) > 1e-4:
        head_dir = np.einsum("fij,j->fi", G[:, J["head"]], head_end)
    else:
        head_dir = P("Head") - P("Neck")
    specs.append(("Head", head_dir, Y, shoulder_line, X, all_frames))
    copy_parent: list[str] = []
    for side, S, sx in (("l", "Left", 1.0), ("r", "Right", -1.0)):
        up, lo, hand = P(f"{S}UpperArm"), P(f"{S}LowerArm"), P(f"{S}Hand")
        hinge, bent = _hinge(lo - up, hand - lo)
        if np.count_nonzero(bent) >= 5:
            arm2, arm2_rest, arm_ok = hinge, -sx * Y, bent
        else:  # arms never bend in this clip: the trunk's forward direction fixes the twist instead
            arm2, arm2_rest, arm_ok = forward, Z, all_frames
        specs.append((f"{S}UpperArm", lo - up, sx * X, arm2, arm2_rest, arm_ok))
        specs.append((f"{S}LowerArm", hand - lo, sx * X, arm2, arm2_rest, arm_ok))
        if side + "hand_tip" in J:
            specs.append((f"{S}Hand", x[:, J[side + "hand_tip"]] - hand, sx * X, arm2, arm2_rest, arm_ok))
        else:
            copy_parent.append(f"{S}Hand")
        th, kn, an, toe = P(f"{S}UpperLeg"), P(f"{S}LowerLeg"), P(f"{S}Foot"), P(f"{S}Toes")
        khinge, kbent = _hinge(kn - th, an - kn)
        if np.count_nonzero(kbent) >= 5:
            leg2, leg_ok = khinge, kbent
        else:
            leg2, leg_ok = hip_line, all_frames
        specs.append((f"{S}UpperLeg", kn - th, -Y, leg2, X, leg_ok))
        specs.append((f"{S}LowerLeg", an - kn, -Y, leg2, X, leg_ok))
        foot_rest = _unit(np.asarray(d[f"{S}Toes"]))
        specs.append((f"{S}Foot", toe - an, foot_rest, leg2, X, leg_ok))
        toe_end = motion.end_sites[J[side + "toe"]] if side + "toe" in J else np.zeros(3)
        if np.linalg.norm(toe_end) > 1e-4:
            toe_dir = np.einsum("fij,j->fi", G[:, J[side + "toe"]], toe_end)
            specs.append((f"{S}Toes", toe_dir, Z, leg2, X, leg_ok))
        else:
            copy_parent.append(f"{S}Toes")

    Q = np.zeros((f, N_BONES, 3, 3))
    for bone, p_w, p_r, s_w, s_r, ok in specs:
        Gs = G[:, driver[BONE_INDEX[bone]]]
        p_l = np.einsum("fji,fj->fi", Gs, _unit(p_w)).mean(axis=0)
        s_l = np.einsum("fji,fj->fi", Gs[ok], _unit(s_w[ok])).mean(axis=0)
        C = _basis(p_l, s_l) @ _basis(p_r, s_r).T
        Q[:, BONE_INDEX[bone]] = Gs @ C
    parents = Skeleton.from_height().parents
    for bone in copy_parent:
        Q[:, BONE_INDEX[bone]] = Q[:, parents[BONE_INDEX[bone]]]

    # Offsets: clip averages of the mapped joints in their parents' frames.
    offsets = np.zeros((N_BONES, 3))
    for b in range(1, N_BONES):
        p = parents[b]
        offsets[b] = np.einsum("fji,fj->fi", Q[:, p], src[:, b] - src[:, p]).mean(axis=0)
    theta = np.zeros((f, POSE_DIM))
    local = np.empty_like(Q)
    local[:, 0] = Q[:, 0]
    for b in range(1, N_BONES):
        local[:, b] = np.swapaxes(Q[:, parents[b]], -1, -2) @ Q[:, b]
    theta[:, 3:] = rotvec_from_matrix(local).reshape(f, -1)

    # Placement: centre the clip horizontally, feet on the floor.
    shift = np.zeros(3)
    shift[[0, 2]] = -src[:, 0, [0, 2]].mean(axis=0)
    feet = [BONE_INDEX[n] for n in ("LeftFoot", "LeftToes", "RightFoot", "RightToes")]
    shift[1] = floor_clearance - float(np.percentile(src[:, feet, 1].min(axis=1), 1.0))
    src = src + shift
    theta[:, 0:3] = src[:, 0]
    skeleton = _sized_skeleton(offsets, floor_clearance)
    fk = Kinematics(skeleton).forward(theta)
    return Retargeted(motion.name, skeleton, theta, fk.positions, fk.rotations, src, motion.fps)


def _toe_positions(motion: SourceMotion, J: dict[str, int], G: FloatArray, x: FloatArray, side: str) -> FloatArray:
    """World positions of a side's toe joint, shape (n_frames, 3): the toe joint, or the ankle's end site."""
    if side + "toe" in J:
        return np.asarray(x[:, J[side + "toe"]])
    ankle = J[side + "ankle"]
    end = motion.end_sites[ankle]
    if np.linalg.norm(end) <= 1e-4:
        raise InputError(
            f"retarget {motion.name!r}: no {side} toe joint and the {motion.joint_names[ankle]} joint has no end site"
        )
    return np.asarray(x[:, ankle] + np.einsum("fij,j->fi", G[:, ankle], end))


def _hinge(a: FloatArray, b: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Hinge axis ``a × b`` of a two-segment limb per frame and where the bend exceeds MIN_HINGE_DEG."""
    ua, ub = _unit(a), _unit(b)
    c = np.cross(ua, ub)
    bend = np.degrees(np.arccos(np.clip(np.sum(ua * ub, axis=-1), -1.0, 1.0)))
    return c, bend > MIN_HINGE_DEG


def _sized_skeleton(offsets: FloatArray, clearance: float) -> Skeleton:
    """A Skeleton with these offsets: rest root height puts the lowest foot joint at ``clearance``."""
    rest = Skeleton(offsets=offsets, root_height=0.0, height=1.75)
    fk = Kinematics(rest).forward(rest.rest_pose())
    feet = [BONE_INDEX[n] for n in ("LeftFoot", "LeftToes", "RightFoot", "RightToes")]
    root_height = clearance - float(fk.positions[feet, 1].min())
    # Height: the head joint scaled as in the default proportions (head joint at 1.60 m of 1.75 m).
    head = float(fk.positions[BONE_INDEX["Head"], 1]) + root_height
    return Skeleton(offsets=offsets, root_height=root_height, height=float(np.clip(head * 1.75 / 1.60, 0.5, 2.6)))


__all__ = ["BONE_NAMES", "CONVENTIONS", "Retargeted", "retarget"]
