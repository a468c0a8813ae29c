"""Motion-file readers: BVH variants, ASF/AMC, MVNX, unit detection and resampling."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapd.core.motion import SourceMotion
from mocapd.core.rotations import quat_angle, quat_from_rotvec
from mocapd.errors import InputError
from mocapd.eval.data import default_data_root
from mocapd.io.asfamc import parse_amc, parse_asf
from mocapd.io.bvh import parse_bvh
from mocapd.io.mocap_units import detect_unit, quat_from_euler
from mocapd.io.mvnx import read_mvnx

DATA = default_data_root()

BVH = """HIERARCHY
ROOT Hips
{
\tOFFSET 0 0 0
\tCHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
\tJOINT LeftUpLeg
\t{
\t\tOFFSET 10 0 0
\t\tCHANNELS 3 Zrotation Xrotation Yrotation
\t\tJOINT LeftLeg
\t\t{
\t\t\tOFFSET 0 -40 0
\t\t\tCHANNELS 3 Zrotation Yrotation Xrotation
\t\t\tJOINT LeftFoot
\t\t\t{
\t\t\t\tOFFSET 0 -40 0
\t\t\t\tCHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
\t\t\t\tEnd Site
\t\t\t\t{
\t\t\t\t\tOFFSET 0 0 10
\t\t\t\t}
\t\t\t}
\t\t}
\t}
}
MOTION
Frames: 2
Frame Time: .0083333
1 90 3 0 0 90 0 0 0 0 0 0 0 -45 0 0 0 0
2 91 4 0 0 0 0 90 0 0 0 0 0 -40 0 0 0 0
"""


def test_bvh_channels_units_and_position_channels() -> None:
    m = parse_bvh(BVH, "t")
    assert m.fps == 120.0
    assert m.joint_names == ("Hips", "LeftUpLeg", "LeftLeg", "LeftFoot")
    assert m.parents == (-1, 0, 1, 2)
    # Leg of 80 units is recognised as centimetres.
    np.testing.assert_allclose(m.translations[0, 0], [0.01, 0.90, 0.03])
    # Frame 0: root Xrotation 90 (channel order Z Y X).
    q = m.rotations[0, 0]
    assert quat_angle(q, quat_from_rotvec(np.array([np.pi / 2, 0, 0]))) < 1e-9
    # Position channels replace the OFFSET (Bandai / MotionBuilder semantics).
    np.testing.assert_allclose(m.translations[0, 3], [0.0, -0.45, 0.0])
    np.testing.assert_allclose(m.end_sites[3], [0, 0, 0.1])
    # Frame 1: LeftUpLeg "Zrotation Xrotation Yrotation" = (0, 90, 0) is a 90° rotation about X.
    assert quat_angle(m.rotations[1, 1], quat_from_rotvec(np.array([np.pi / 2, 0, 0]))) < 1e-9


def test_bvh_explicit_unit_and_truncated_motion() -> None:
    m = parse_bvh(BVH.rsplit("\n", 2)[0] + "\n2 91 4", "t", unit="m")
    assert m.n_frames == 1  # the incomplete last frame is dropped
    np.testing.assert_allclose(m.translations[0, 1], [10, 0, 0])
    with pytest.raises(InputError):
        parse_bvh("HIERARCHY\nROOT Hips\n{\nOFFSET 0 0 0\n", "bad")


def test_unit_detection() -> None:
    assert detect_unit(80.0)[0] == "cm"
    assert detect_unit(14.5)[0] == "cmu"
    assert detect_unit(0.85)[0] == "m"
    assert detect_unit(850.0)[0] == "mm"


def test_euler_order() -> None:
    q = quat_from_euler(np.array([90.0, 90.0]), "zx")  # R = Rz(90) Rx(90)
    v = np.array([0.0, 1.0, 0.0])  # Rx(90) y = z; Rz(90) z = z
    from mocapd.core.rotations import quat_rotate

    np.testing.assert_allclose(quat_rotate(q, v), [0, 0, 1], atol=1e-12)


ASF = """:version 1.10
:name VICON
:units
  mass 1.0
  length 0.45
  angle deg
:root
   order TX TY TZ RX RY RZ
   axis XYZ
   position 0 0 0
   orientation 0 0 0
:bonedata
  begin
     id 1
     name lfemur
     direction 0 -1 0
     length 10
     axis 0 0 90  XYZ
    dof rx ry rz
    limits (-160.0 20.0)
           (-70.0 70.0)
           (-60.0 70.0)
  end
  begin
     id 2
     name ltibia
     direction 0 -1 0
     length 10
     axis 0 0 0  XYZ
    dof rx
    limits (-10.0 170.0)
  end
:hierarchy
  begin
    root lfemur
    lfemur ltibia
  end
"""
AMC = """:FULLY-SPECIFIED
:DEGREES
1
root 0 20 0 0 0 0
lfemur 90 0 0
ltibia 0
"""


def test_asf_amc_bone_frames() -> None:
    sk = parse_asf(ASF)
    m = parse_amc(AMC, sk, "t")
    _G, x = m.forward()
    s = 0.0254 / 0.45
    np.testing.assert_allclose(x[0, 0], [0, 20 * s, 0])
    # lfemur: rx = 90 about its local X, whose axis is world Y after the 90° Z "axis" rotation: C Rx C⁻¹ is a
    # rotation about world +Y, so the femur (pointing down) is unchanged; the knee is 10 units below the hip.
    np.testing.assert_allclose(x[0, 2], [0, 10 * s, 0], atol=1e-12)
    assert m.fps == 120.0


def test_mvnx_reader() -> None:
    rec = read_mvnx(DATA / "imu/mvnx/mpiea_upperbody_test_mocap.mvnx")
    assert rec.fps == 60.0
    assert len(rec.segments) == 23 and rec.segments[0] == "Pelvis"
    assert rec.segment_orientation.shape == (112, 23, 4)
    assert rec.sensor_orientation.shape == (112, 11, 4)
    assert rec.tpose_orientation is not None
    # Z-up MVN → Y-up: the head is above the pelvis.
    head = rec.segments.index("Head")
    assert np.all(rec.segment_position[:, head, 1] > rec.segment_position[:, 0, 1] + 0.4)
    np.testing.assert_allclose(np.linalg.norm(rec.sensor_orientation, axis=-1), 1.0, atol=1e-6)


def test_resample_catmull_rom() -> None:
    rng = np.random.default_rng(0)
    f, n = 31, 2
    tr = np.cumsum(rng.normal(size=(f, n, 3)), axis=0)
    rot = quat_from_rotvec(np.cumsum(0.05 * rng.normal(size=(f, n, 3)), axis=0))
    m = SourceMotion("t", ("a", "b"), (-1, 0), tr, rot, np.zeros((n, 3)), 30.0)
    up = m.resample(60.0)
    assert up.n_frames == 61 and up.fps == 60.0
    np.testing.assert_allclose(up.translations[::2], tr, atol=1e-12)  # passes through the samples
    assert np.max(quat_angle(up.rotations[::2], rot)) < 1e-6
    down = up.resample(30.0)
    np.testing.assert_allclose(down.translations, tr, atol=1e-12)


def test_data_root_exists() -> None:
    assert (DATA / "mocap").is_dir(), f"shared data not found at {DATA} (set MOCAPD_DATA)"
    assert isinstance(DATA, Path)
