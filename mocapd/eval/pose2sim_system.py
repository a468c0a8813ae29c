"""Pose2Sim as a system of ``mocapd eval video``: mocapd's detections written as OpenPose JSON, Pose2Sim's own
person association, triangulation and filtering run on them (:mod:`mocapd.eval.pose2sim_runner`, in a child
process), its output read back as per-frame 3D keypoints.

Pose2Sim runs with its demo's ``Config.toml`` and these overrides, each needed to run it on this input at all or
to keep it from drawing windows; none changes how it associates, triangulates or filters:

* ``pose.pose_model = "COCO_17"``: the keypoints are mocapd's detector's (COCO-17), not the RTMPose Halpe-26 the
  demo configures (Pose2Sim's COCO_17 model triangulates 13 of them: nose, shoulders, elbows, wrists, hips, knees,
  ankles; it has no neck, so its single-person association tracks the nose, as it says in its log);
* ``project.frame_rate`` = the videos' rate (what ``"auto"`` would read from the videos, which the projects do not
  hold);
* ``filtering.display_figures``, ``filtering.save_filt_plots``, ``triangulation.make_c3d``, ``filtering.make_c3d``
  = false: no windows, plots or C3D files.

What does not run, and why: pose estimation (the point is the same detections for every system), synchronisation
(the demo videos are synchronised), marker augmentation and OpenSim kinematics (they come after the 3D keypoints
this evaluation scores; ``opensim`` and the augmenter's runtime are not installed: Pose2Sim comes without its
dependencies, see ``setup/steps/24-pose2sim.sh``).
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.sorting import Detections2D
from mocapd.errors import MocapdError
from mocapd.eval.video_input import Take
from mocapd.io import lifecycle

FloatArray = NDArray[np.float64]

POSE2SIM_VERSION = "0.10.49"

OVERRIDES: dict[str, Any] = {
    "pose": {"pose_model": "COCO_17"},
    "filtering": {"display_figures": False, "save_filt_plots": False, "make_c3d": False},
    "triangulation": {"make_c3d": False},
    "logging": {"use_custom_logging": True},
}


def pose2sim_missing() -> str | None:
    """Why Pose2Sim cannot run here (None when it can)."""
    if importlib.util.find_spec("Pose2Sim") is None:
        return (f"pose2sim is not installed (pip install 'mocapd[eval]' && pip install --no-deps "
                f"pose2sim=={POSE2SIM_VERSION}; the set-up step setup/steps/24-pose2sim.sh does both)")  # fmt: skip
    version = importlib.metadata.version("pose2sim")
    if version != POSE2SIM_VERSION:
        return f"pose2sim {version} is installed; the evaluation is written for {POSE2SIM_VERSION}"
    for mod in ("pandas", "rtoml", "anytree", "statsmodels", "filterpy", "lxml", "c3d", "tqdm"):
        if importlib.util.find_spec(mod) is None:
            return f"{mod} is missing (pip install 'mocapd[eval]')"
    return None


def demo_config_file(take: Take) -> Path:
    """The Pose2Sim demo's own ``Config.toml`` (beside its ``calibration/`` folder)."""
    path = take.calibration.parent.parent / "Config.toml"
    if not path.is_file():
        raise MocapdError(f"{path} is missing: Pose2Sim runs with its demo's own Config.toml")
    return path


def write_openpose(folder: Path, camera: str, frames: list[Detections2D]) -> None:
    """One camera's detections as OpenPose JSON, one file per frame (``<camera>_json/<camera>_<frame>.json``),
    COCO-17 keypoints as (x, y, confidence) triples: the layout Pose2Sim reads."""
    out = folder / f"{camera}_json"
    out.mkdir(parents=True, exist_ok=True)
    for f, det in enumerate(frames):
        people = [
            {"person_id": [-1],
             "pose_keypoints_2d": np.column_stack((det.keypoints[i], det.confidences[i])).ravel().round(3).tolist(),
             "face_keypoints_2d": [], "hand_left_keypoints_2d": [], "hand_right_keypoints_2d": []}
            for i in range(len(det))
        ]  # fmt: skip
        (out / f"{camera}_{f:06d}.json").write_text(json.dumps({"version": 1.3, "people": people}))


@dataclass
class Pose2SimOutput:
    """Pose2Sim's people of one project: per person (n_frames, K, 3) (K = 17 for COCO-17 detections, 25 for BODY_25),
    NaN where it gave nothing."""

    raw: list[FloatArray]
    filtered: list[FloatArray]
    log: str


def run_pose2sim(
    take: Take,
    frames: list[list[Detections2D]],
    work: Path,
    variants: dict[str, list[int]],
    timeout_s: float = 3600.0,
) -> dict[str, Pose2SimOutput]:
    """Pose2Sim on ``frames`` (per frame, per camera of ``take``) for each variant (name -> camera indices kept),
    in ``work/<variant>/``; one child process for all of them."""
    missing = pose2sim_missing()
    if missing is not None:
        raise MocapdError(missing)
    projects = []
    for name, keep in variants.items():
        root = work / name
        if root.exists():
            shutil.rmtree(root)
        for c in keep:
            write_openpose(root / "pose", take.camera_names[c], [row[c] for row in frames])
        projects.append({"dir": str(root), "cameras": [take.camera_names[c] for c in keep]})
    multi = take.subjects > 1
    overrides = json.loads(json.dumps(OVERRIDES))
    overrides["project"] = {"frame_rate": round(take.fps), "multi_person": multi}
    job = {"calibration": str(take.calibration), "config": str(demo_config_file(take)), "overrides": overrides,
           "projects": projects, "n_frames": len(frames)}  # fmt: skip
    return _run_job(job, work, list(variants), timeout_s)


def _run_job(job: dict[str, Any], work: Path, names: list[str], timeout_s: float) -> dict[str, Pose2SimOutput]:
    """The runner in a child process on ``job`` (written to ``work/job.json``); each project's people read back."""
    work.mkdir(parents=True, exist_ok=True)
    (work / "job.json").write_text(json.dumps(job, indent=2))
    proc = subprocess.run(  # ends with this process, also when it is killed (lifecycle.guarded_command)
        lifecycle.guarded_command([sys.executable, "-m", "mocapd.eval.pose2sim_runner", str(work / "job.json")]),
        capture_output=True, text=True, timeout=timeout_s, check=False,
    )  # fmt: skip
    (work / "runner.log").write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-12:])
        raise MocapdError(f"Pose2Sim failed (exit {proc.returncode}; {work / 'runner.log'}):\n{tail}")
    out = {}
    for name in names:
        with np.load(work / name / "result.npz") as z:
            n = len([k for k in z.files if k.startswith("raw_")])
            raw = [np.asarray(z[f"raw_{i}"]) for i in range(n)]
            filt = [np.asarray(z[f"filt_{i}"]) for i in range(n)]
        log = (work / name / "pose2sim.log").read_text() if (work / name / "pose2sim.log").is_file() else ""
        out[name] = Pose2SimOutput(raw, filt, log)
    return out


def run_pose2sim_openpose(
    folders: list[Path], calibration_toml: Path, fps: float, n_frames: int, work: Path, timeout_s: float = 3600.0
) -> Pose2SimOutput:
    """Pose2Sim (multi-person) on OpenPose BODY_25 folders (``<camera>_json``, one per camera of
    ``calibration_toml``, a Pose2Sim TOML): its demo's ``Config.toml`` (Demo_MultiPerson) with :data:`OVERRIDES`, the
    pose model BODY_25 (what the files hold) and ``fps``; people (n_frames, 25, 3) in BODY_25's order, mocapd's world
    (``mocapd eval keypoints``)."""
    import Pose2Sim

    missing = pose2sim_missing()
    if missing is not None:
        raise MocapdError(missing)
    root = work / "project"
    if root.exists():
        shutil.rmtree(root)
    (root / "pose").mkdir(parents=True)
    for folder in folders:
        shutil.copytree(folder, root / "pose" / folder.name)
    config = Path(Pose2Sim.__file__).parent / "Demo_MultiPerson" / "Config.toml"
    overrides = json.loads(json.dumps(OVERRIDES))
    overrides["pose"]["pose_model"] = "BODY_25"
    overrides["project"] = {"frame_rate": int(fps) if float(fps).is_integer() else fps, "multi_person": True}
    project = {"dir": str(root), "cameras": [f.name.removesuffix("_json") for f in folders]}
    job = {"calibration": str(calibration_toml), "config": str(config), "overrides": overrides,
           "pose_model": "BODY_25", "projects": [project], "n_frames": n_frames}  # fmt: skip
    return _run_job(job, work, ["project"], timeout_s)["project"]
