"""Body size estimated from triangulated joints recovers known bone lengths."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.body_size import estimate_skeleton
from mocapd.core.keypoints import coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.core.synthetic import moving_sequence
from mocapd.errors import InputError


def test_recovers_limb_lengths_and_height_from_noisy_joints() -> None:
    rng = np.random.default_rng(0)
    base = Skeleton.from_height(1.62)
    truth = Skeleton.from_bone_lengths(
        {"LeftLowerLeg": 0.41, "RightLowerLeg": 0.41, "LeftFoot": 0.39, "RightFoot": 0.39,
         "LeftLowerArm": 0.27, "RightLowerArm": 0.27, "LeftHand": 0.23, "RightHand": 0.23},
        height=base.height,
    )  # fmt: skip
    kin = Kinematics(truth)
    targets = coco17_targets(truth)
    kp = kin.targets(kin.forward(moving_sequence(truth, 120, seed=4)), targets.bones, targets.offsets)
    kp = kp + rng.normal(scale=0.02, size=kp.shape)
    kp[rng.uniform(size=kp.shape[:2]) < 0.1] = np.nan  # missed keypoints
    kp[5, 9] += 0.5  # a gross outlier
    est = estimate_skeleton(kp)
    for bone in ("LeftLowerLeg", "LeftFoot", "LeftLowerArm", "LeftHand"):
        assert est.bone_length(bone) == pytest.approx(truth.bone_length(bone), abs=0.01), bone
    assert est.height == pytest.approx(1.75 * 0.80 / 0.86, abs=0.02)
    assert abs(est.offsets[BONE_INDEX["LeftUpperArm"], 0]) == pytest.approx(
        abs(truth.offsets[BONE_INDEX["LeftUpperArm"], 0]), abs=0.02
    )


def test_too_few_frames_is_an_error() -> None:
    with pytest.raises(InputError, match="at least 10 frames"):
        estimate_skeleton(np.full((30, 17, 3), np.nan))
    with pytest.raises(InputError, match="shape"):
        estimate_skeleton(np.zeros((30, 12, 3)))


def test_torso_length_is_measured_not_assumed() -> None:
    """A person whose spine is 25 % shorter than the default for their legs: the sized skeleton puts the
    shoulders at the measured distance above the hips, which height scaling alone would miss by centimetres."""
    base = Skeleton.from_height(1.8)
    off = base.offsets.copy()
    for b in ("Spine", "Spine1", "Spine2", "Spine3"):
        off[BONE_INDEX[b]] *= 0.75
    person = Skeleton(offsets=off, root_height=base.root_height, height=1.8)

    def rest_sites(sk: Skeleton) -> np.ndarray:
        kin, targets = Kinematics(sk), coco17_targets(sk)
        return np.asarray(kin.targets(kin.forward(np.zeros(66)), targets.bones, targets.offsets))

    def torso(x: np.ndarray) -> float:  # hip midpoint to shoulder midpoint (COCO 5, 6, 11, 12)
        return float(np.linalg.norm(0.5 * (x[5] + x[6]) - 0.5 * (x[11] + x[12])))

    truth = torso(rest_sites(person))
    sized = estimate_skeleton(np.repeat(rest_sites(person)[None], 20, axis=0))
    assert abs(torso(rest_sites(sized)) - truth) < 1e-3
    assert abs(torso(rest_sites(Skeleton.from_height(sized.height))) - truth) > 0.05


@pytest.mark.parametrize("fmt", ["body25", "halpe26"])
def test_any_keypoint_set_is_sized_by_names(fmt: str) -> None:
    """BODY_25 and Halpe-26 (and any set naming the limbs' joints) give the skeleton COCO-17 gives from the same
    people: the joints are looked up by name, not by COCO-17's positions. (Their neck, mid-hip and nose also place
    the trunk's other joints, :func:`test_the_trunk_is_measured_neck_hips_and_head`: there only the limbs, widths
    and height are COCO-17's.)"""
    from mocapd.core.body_size import COCO17_NAMES, can_size
    from mocapd.core.keypoint_sets import BLAZEPOSE33, convert
    from mocapd.core.keypoints import keypoint_format

    truth = Skeleton.from_bone_lengths({"LeftLowerLeg": 0.43, "RightLowerLeg": 0.43, "LeftFoot": 0.41,
                                        "RightFoot": 0.41}, height=1.8)  # fmt: skip
    kin = Kinematics(truth)
    fk = kin.forward(moving_sequence(truth, 60, seed=2))
    coco = coco17_targets(truth)
    other = keypoint_format(fmt).track_targets(truth)
    ref = estimate_skeleton(kin.targets(fk, coco.bones, coco.offsets))
    est = estimate_skeleton(kin.targets(fk, other.bones, other.offsets), names=other.names)
    limbs = [BONE_INDEX[f"{side}{b}"] for side in ("Left", "Right") for b in ("LowerArm", "Hand", "LowerLeg", "Foot")]
    np.testing.assert_allclose(est.offsets[limbs], ref.offsets[limbs], atol=1e-9)
    np.testing.assert_allclose(est.offsets[:, 0], ref.offsets[:, 0], atol=1e-9)  # shoulder and hip widths
    assert est.height == pytest.approx(ref.height)
    assert can_size(other.names) and can_size(BLAZEPOSE33) and not can_size(COCO17_NAMES[:11])
    # BlazePose's 33 landmarks, put onto halpe26 by name, size the same person too
    uv = np.zeros((1, 33, 2))
    assert convert("blazepose33", uv, np.ones((1, 33)), other.names)[1].shape == (1, len(other.names))
    with pytest.raises(InputError, match="left_ankle"):
        estimate_skeleton(np.zeros((12, 11, 3)), names=COCO17_NAMES[:11])


def test_initial_pose_by_names() -> None:
    """A new person's warm start finds the hips by name in any set (BODY_25's hips are at 12 and 9)."""
    from mocapd.core.keypoints import BODY25_FORMAT
    from mocapd.core.warm_start import initial_pose

    sk = Skeleton.from_height(1.75)
    kin = Kinematics(sk)
    theta = sk.rest_pose()
    theta[0:3] = [0.4, 0.95, -1.2]
    theta[3:6] = [0.0, 0.7, 0.0]
    fk = kin.forward(theta)
    body25 = BODY25_FORMAT.track_targets(sk)
    start = initial_pose(sk, kin.targets(fk, body25.bones, body25.offsets), body25.names)
    coco = coco17_targets(sk)
    same = initial_pose(sk, kin.targets(fk, coco.bones, coco.offsets))
    np.testing.assert_allclose(start, same, atol=1e-12)
    assert start[4] == pytest.approx(0.7) and start[0] == pytest.approx(0.4)
    assert np.array_equal(initial_pose(sk, np.full((25, 3), np.nan), body25.names), sk.rest_pose())


@pytest.mark.parametrize(("fmt", "mid_hip"), [("body25", "mid_hip"), ("halpe26", "hip")])
def test_the_trunk_is_measured_neck_hips_and_head(fmt: str, mid_hip: str) -> None:
    """A person whose Neck joint sits 4 cm higher above the shoulders, whose Hips joint sits 5 cm higher above the
    hip joints and whose head is 3 cm longer than the default proportions: sized from BODY_25 or Halpe-26 detections
    (neck, mid-hip and nose among them; Halpe-26 calls its mid-hip ``hip``), the sized skeleton's Neck, Hips and nose
    sites are within a few mm of the truth (the old sizing, which left these at the height-scaled default, missed
    them by 3 to 5 cm; it did so for Halpe-26 until its ``hip`` was taken as the mid-hip)."""
    from mocapd.core.keypoints import keypoint_format

    kp_set = keypoint_format(fmt)
    base = Skeleton.from_height(1.8)
    off = base.offsets.copy()
    off[BONE_INDEX["Neck"], 1] += 0.04
    off[BONE_INDEX["Head"], 1] += 0.03
    for leg in ("LeftUpperLeg", "RightUpperLeg"):
        off[BONE_INDEX[leg], 1] -= 0.05  # the hip joints 5 cm further below the Hips joint
    person = Skeleton(offsets=off, root_height=base.root_height + 0.05, height=1.8)
    kin = Kinematics(person)
    targets = kp_set.track_targets(person)
    kp = kin.targets(kin.forward(moving_sequence(person, 80, seed=3)), targets.bones, targets.offsets)
    kp = kp + np.random.default_rng(1).normal(scale=0.005, size=kp.shape)
    sized = estimate_skeleton(kp, names=targets.names)

    def sites(sk: Skeleton) -> np.ndarray:  # rest pose, hip joints' midpoint at the origin
        kin, tg = Kinematics(sk), kp_set.track_targets(sk)
        x = np.asarray(kin.targets(kin.forward(sk.rest_pose()), tg.bones, tg.offsets), dtype=np.float64)
        return np.asarray(x - 0.5 * (x[targets.names.index("left_hip")] + x[targets.names.index("right_hip")]))

    truth, est = sites(person), sites(sized)
    for name in ("neck", mid_hip, "nose", "left_shoulder", "right_shoulder"):
        i = targets.names.index(name)
        assert np.linalg.norm(est[i] - truth[i]) < 0.005, name
    assert sized.root_height == pytest.approx(person.root_height, abs=0.01)  # the rest pose still stands on the floor
    # what the default proportions (the old sizing) give: centimetres off
    old = sites(Skeleton.from_height(sized.height))
    for name in ("neck", mid_hip, "nose"):
        i = targets.names.index(name)
        assert np.linalg.norm(old[i] - truth[i]) > 0.02, name


def test_coco17_sizing_is_unchanged_by_the_trunk_fit() -> None:
    """COCO-17 (no neck, no mid-hip) is sized bit for bit as before the trunk fit (values from commit 71b7a47's
    sizing of the same input; the input is built without trigonometry, so it is the same on any CPU)."""
    base = Skeleton.from_bone_lengths({"LeftLowerLeg": 0.44, "RightLowerLeg": 0.44, "LeftFoot": 0.40,
                                       "RightFoot": 0.40, "LeftLowerArm": 0.27, "RightLowerArm": 0.27},
                                      height=1.7)  # fmt: skip
    kin, tg = Kinematics(base), coco17_targets(base)
    rest = np.asarray(kin.targets(kin.forward(np.zeros(66)), tg.bones, tg.offsets))
    rng = np.random.default_rng(7)
    kp = rest[None] + rng.normal(scale=0.02, size=(40, 17, 3))
    kp[rng.uniform(size=kp.shape[:2]) < 0.1] = np.nan
    sized = estimate_skeleton(kp)
    before = np.array([
        [0.0, 0.0, 0.0], [0.0, 0.08626439651199401, -0.009584932945777114], [0.0, 0.10543426240354825, 0.0],
        [0.0, 0.10543426240354825, 0.0], [0.0, 0.10543426240354825, 0.0], [0.0, 0.0985025215786319, 0.0],
        [0.0, 0.0985025215786319, 0.00985025215786319], [0.1774587730897294, 0.05755962431029835, 0.0],
        [0.27156937808412474, 0.0, 0.0], [0.2403301953706179, 0.0, 0.0],
        [-0.1774587730897294, 0.05755962431029835, 0.0], [-0.27156937808412474, 0.0, 0.0],
        [-0.2403301953706179, 0.0, 0.0], [0.09053388431014925, -0.050296602394527365, 0.0],
        [0.0, -0.4489694598278173, 0.0], [0.0, -0.39815222574841713, 0.0],
        [0.0, -0.01970050431572638, 0.13790353021008467], [-0.09053388431014925, -0.050296602394527365, 0.0],
        [0.0, -0.4489694598278173, 0.0], [0.0, -0.39815222574841713, 0.0],
        [0.0, -0.01970050431572638, 0.13790353021008467],
    ])  # fmt: skip
    np.testing.assert_array_equal(sized.offsets, before)
    assert sized.root_height == 0.966370053075804 and sized.height == 1.7237941276260582
