"""How far a walk's stance leg leans at the instants a stance-phase model could take for mid-stance (issue 42).

Gravity from stance phases (:mod:`mocapd.core.stance_calibration`) could turn the thigh and shank mountings about the
knee axis only if the true leg lean (the half sum of the thigh's and shank's sagittal tilts, degrees: 0 with the
ankle under the hip, negative with the hip ahead of it) were known at some instant of every stance. This measures it
at each candidate instant, with the truth: the simulated development walks (``--clip WALKS --sway 5`` of
:mod:`mocapd.eval.calibration_posture`, seed 42, the truth's bones) and, given its folder, the real MTw walk's Vicon
joint centres (hip, knee and ankle joint centres of Plug-in-Gait, the stances from its foot sensors through the
calibration ``calibrate imu --from`` makes). A usable instant has a mean near 0 and a small spread on both. Prints
JSON::

    python tools/stance_leg_lean.py [--optical DIR_WITH_SESSION VICON_MAT]

``DIR_WITH_SESSION``: a session imported by ``tools/optical_walk_cli.py`` (its ``WORK/take``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mocapd.core.imu_calibration import common_grid, heading_alignment
from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import matrix_from_quat, quat_conjugate, quat_from_matrix, quat_multiply
from mocapd.core.skeleton import BONE_INDEX
from mocapd.core.stance_calibration import LEGS, detect_stances, sagittal_tilt, turn_rate

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

RULES = ("foot_flat_mean", "foot_flat_middle", "shank_slowest", "at_35_percent", "pelvis_vault_top",
         "leg_fastest", "knee_straightest")  # fmt: skip
"""The candidate instants (see :func:`instants`)."""


def tilts(q: FloatArray) -> FloatArray:
    """Sagittal tilt (radians, (n,)) of bone orientations (n, 4)."""
    return np.array([sagittal_tilt(x) for x in q])


def instants(
    t: FloatArray, span: tuple[float, float], leg_sum: FloatArray, shank_rate: FloatArray, pelvis_up: FloatArray,
    knee: FloatArray,
) -> dict[str, IntArray]:  # fmt: skip
    """Each rule's sample indices in one stance ``span`` (s): the foot-flat's mean and middle, the shank's slowest
    turn, 35 % into it, the pelvis's smallest vertical specific force (the top of the body's vault over the foot),
    the leg's fastest rotation (the measured tilts' sum ``leg_sum``, whose rate no mounting changes), the knee's
    straightest (``knee``: thigh tilt minus shank tilt)."""
    sel = np.flatnonzero((t >= span[0]) & (t <= span[1]))
    rate = np.gradient(leg_sum, t)
    return {
        "foot_flat_mean": sel,
        "foot_flat_middle": sel[[len(sel) // 2]],
        "shank_slowest": sel[[int(np.argmin(shank_rate[sel]))]],
        "at_35_percent": sel[[int(0.35 * (len(sel) - 1))]],
        "pelvis_vault_top": sel[[int(np.argmin(pelvis_up[sel]))]],
        "leg_fastest": sel[[int(np.argmin(rate[sel]))]],
        "knee_straightest": sel[[int(np.argmin(knee[sel]))]],
    }


def _summary(rows: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    return {r: {"mean_deg": round(float(np.mean([x[r] for x in rows])), 1),
                "sd_deg": round(float(np.std([x[r] for x in rows])), 1)} for r in RULES}  # fmt: skip


def _up_force(q_world: FloatArray, f: FloatArray) -> FloatArray:
    """World-vertical specific force (n,) of a sensor's world orientations (n, 4) and specific force (n, 3)."""
    return np.asarray(np.einsum("nij,nj->ni", matrix_from_quat(q_world), f)[:, 1], dtype=np.float64)


def simulated(seed: int = 42, sway_deg: float = 5.0) -> dict[str, object]:
    """The development walks, as ``python -m mocapd.eval.calibration_posture --clip WALKS --sway 5`` simulates them."""
    from mocapd.eval.calibration_posture import FPS, STILL_S, WALKS, simulate_take
    from mocapd.eval.data import default_data_root, load_clip

    rng = np.random.default_rng(seed)
    per_clip, rows_all = {}, []
    for path in WALKS:
        clip = load_clip(default_data_root() / path, FPS)
        samples, bones, truth, _, _ = simulate_take(clip.skeleton, clip.theta[: round(8 * FPS)], rng, sway_deg)
        fk = Kinematics(clip.skeleton).forward(truth)
        by_bone = {b: s for s, b in bones.items()}
        t = np.arange(len(truth)) / FPS
        _, q_p, f_p = samples[by_bone["Hips"]]
        pelvis_up = _up_force(np.asarray(quat_multiply(heading_alignment(0.0), q_p)), f_p)
        rows = []
        for thigh, shank, foot in LEGS.values():
            q_t = quat_from_matrix(fk.rotations[:, BONE_INDEX[thigh]])
            q_s = quat_from_matrix(fk.rotations[:, BONE_INDEX[shank]])
            leg_sum = (tilts(q_t) + tilts(q_s)) / 2
            shank_rate = turn_rate(t, samples[by_bone[shank]][1])
            knee = tilts(q_t) - tilts(q_s)
            t_f, q_f, a_f = samples[by_bone[foot]]
            for span in detect_stances(t_f, q_f, a_f, exclude=(0.0, STILL_S)):
                at = instants(t, span, leg_sum, shank_rate, pelvis_up, knee)
                rows.append({r: float(np.degrees(leg_sum[i].mean())) for r, i in at.items()})
        if rows:
            per_clip[Path(path).stem] = {"stances": len(rows)} | _summary(rows)
        rows_all += rows
    return {"stances": len(rows_all), "all": _summary(rows_all), "per_clip": per_clip}


def optical(session_dir: Path, vicon_mat: Path) -> dict[str, object]:
    """The real MTw walk: its Vicon joint centres' leg lean at the instants its IMUs give."""
    from scipy.io import loadmat

    from mocapd.core.stance_calibration import foot_stances
    from mocapd.io.session import open_session
    from mocapd.service.session.calibrate import calibrate_session, session_samples

    session = open_session(session_dir)
    samples = session_samples(session)
    result = calibrate_session(session, person="walk")
    calib = result.calibration
    by_bone = {b: s for s, b in calib.bones.items()}
    t, q = common_grid(samples, sorted(calib.bones))
    own = calib.device_heading_quats()

    def world(sid: str, qs: FloatArray) -> FloatArray:
        return np.asarray(quat_multiply(calib.q_ig, quat_multiply(own[sid], qs) if sid in own else qs))

    def bone(name: str) -> FloatArray:
        sid = by_bone[name]
        return np.asarray(quat_multiply(world(sid, q[sid]), quat_conjugate(calib.q_ib[sid])))

    hips = by_bone["Hips"]
    t_p, q_p, f_p = samples[hips]
    pelvis_up = np.interp(t, t_p, _up_force(world(hips, q_p), f_p))
    m = {k: np.asarray(v, dtype=np.float64) for k, v in loadmat(vicon_mat, squeeze_me=True).items() if k[0] != "_"}
    left = m["LASI"] + m["LPSI"] - m["RASI"] - m["RPSI"]
    left[:, 2] = 0.0
    forward = np.cross(left / np.linalg.norm(left, axis=1)[:, None], np.array([0.0, 0.0, 1.0]))
    frame = np.clip(np.round(t * 100.0).astype(np.int64), 0, len(forward) - 1)  # Vicon at 100 Hz, one time base

    def vicon_tilt(top: str, bottom: str) -> FloatArray:
        d = m[top] - m[bottom]
        tilt = -np.arctan2(np.sum(d * forward, axis=1), d[:, 2])  # the sign of sagittal_tilt
        return np.asarray(tilt[frame], dtype=np.float64)

    def measured(name: str) -> FloatArray:
        return tilts(bone(name))

    rows = []
    stances = foot_stances(calib, samples, result.window_s)
    for side, spans in stances.items():
        thigh, shank, _ = LEGS[side]
        s = side[0]
        truth = (vicon_tilt(f"{s}HJC", f"{s}KJC") + vicon_tilt(f"{s}KJC", f"{s}AJC")) / 2
        leg_sum = (measured(thigh) + measured(shank)) / 2
        knee = measured(thigh) - measured(shank)
        shank_rate = turn_rate(t, bone(shank))
        for span in spans:
            at = instants(t, span, leg_sum, shank_rate, pelvis_up, knee)
            rows.append({r: float(np.degrees(truth[i].mean())) for r, i in at.items()})
    return {"stances": len(rows), "all": _summary(rows)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--optical", nargs=2, type=Path, metavar=("SESSION", "VICON_MAT"), default=None)
    args = p.parse_args(argv)
    out: dict[str, object] = {"simulated_walks": simulated()}
    if args.optical is not None:
        out["real_mtw_walk"] = optical(*args.optical)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
