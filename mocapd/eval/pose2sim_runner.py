"""Pose2Sim's own person association, triangulation and filtering on mocapd's detections, in a child process.

``python -m mocapd.eval.pose2sim_runner JOB.json`` runs, for each project of the job, Pose2Sim 0.10.49's Python API
(``Pose2Sim.calibration``, ``personAssociation``, ``triangulation``, ``filtering``) with the demo's own
``Config.toml`` and the overrides the job gives, then writes ``result.npz`` into the project: for every person
Pose2Sim output, ``raw_<i>`` (its triangulation) and ``filt_<i>`` (after its filtering), shape (n_frames, K, 3),
the detector's keypoint order (the job's ``pose_model``: ``COCO_17``, K = 17, by default; ``BODY_25``, K = 25),
mocapd's world (metres, +Y up), NaN where Pose2Sim gave nothing (keypoints it does not
triangulate, frames outside the range it kept).

Why a child process: Pose2Sim configures the root logger, sets numpy's print options at import, picks a
matplotlib backend and reads its project layout from the working tree; none of that may leak into mocapd. It is
also an optional dependency (``pip install mocapd[eval]`` plus ``pose2sim --no-deps``, see
``setup/steps/24-pose2sim.sh``): mocapd itself never imports it.

The job file (JSON): ``{"calibration": <Calib.qca.txt or a Pose2Sim Calib.toml>, "config": <the demo's Config.toml>,
"overrides": {...}, "pose_model": "COCO_17", "projects": [{"dir": <project folder with pose/<cam>_json/>, "cameras":
[names kept]}, ...]}``. Each project's calibration is Pose2Sim's own conversion of the Qualisys file (a ``.toml`` is
taken as it is), with the cameras not kept removed.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

# Pose2Sim's Y-up trc coordinates (its zup2yup: X->Y, Y->Z, Z->X of the Z-up world) -> mocapd's Y-up world
# (X_y = (x, z, -y) of the same Z-up world): (a, b, c) = (y_z, z_z, x_z)  ->  (x_z, z_z, -y_z) = (c, b, -a).
TRC_TO_MOCAPD: FloatArray = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


def _update(base: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    for k, v in new.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            _update(base[k], v)
        else:
            base[k] = v
    return base


def _model_columns(model: str = "COCO_17") -> tuple[list[str], list[int], int]:
    """Names and detector indices of the keypoints Pose2Sim's ``model`` (a tree of ``Pose2Sim.skeletons``:
    ``COCO_17``, ``BODY_25``) triangulates, in its trc order, and the detector's keypoint count."""
    from anytree import RenderTree
    from Pose2Sim import skeletons

    counts = {"COCO_17": 17, "BODY_25": 25}
    if model not in counts:
        raise ValueError(f"pose model {model!r}: one of {sorted(counts)}")
    nodes = [node for _, _, node in RenderTree(getattr(skeletons, model)) if node.id is not None]
    return [n.name for n in nodes], [int(n.id) for n in nodes], counts[model]


def _read_trc(path: Path, n_frames: int, columns: list[int], width: int = 17) -> FloatArray:
    """A Pose2Sim trc file as (n_frames, width, 3) in mocapd's world (the detector's keypoint order); NaN outside
    its frame range and for keypoints it does not triangulate."""
    from Pose2Sim.common import read_trc

    q, frames, _, _, _ = read_trc(str(path))
    xyz = q.to_numpy(dtype=np.float64).reshape(len(frames), -1, 3) @ TRC_TO_MOCAPD.T
    out = np.full((n_frames, width, 3), np.nan)
    for row, f in enumerate(frames.to_numpy()):
        if 0 <= int(f) < n_frames:
            out[int(f), columns] = xyz[row]
    return out


def _calibration(project: Path, qca: Path, keep: list[str], cfg: dict[str, Any]) -> None:
    """Pose2Sim's own conversion of the Qualisys file into ``project/calibration`` (a Pose2Sim ``.toml`` is taken as
    it is), then only the kept cameras."""
    import rtoml
    from Pose2Sim import Pose2Sim

    calib = project / "calibration"
    if calib.exists():
        shutil.rmtree(calib)
    calib.mkdir(parents=True)
    shutil.copy(qca, calib / qca.name)
    if qca.suffix.lower() != ".toml":
        Pose2Sim.calibration(cfg)
    tomls = list(calib.glob("*.toml"))
    if len(tomls) != 1:
        raise RuntimeError(f"Pose2Sim's calibration conversion wrote {len(tomls)} .toml files in {calib}")
    data = rtoml.load(tomls[0])
    kept = {k: v for k, v in data.items() if not isinstance(v, dict) or k == "metadata" or v.get("name") in keep}
    names = [v["name"] for k, v in kept.items() if isinstance(v, dict) and k != "metadata"]
    if names != keep:
        raise RuntimeError(f"calibration cameras {names}, expected {keep}")
    tomls[0].write_text(rtoml.dumps(kept))


def run_project(job: dict[str, Any], project: dict[str, Any]) -> dict[str, Any]:
    """One project: calibration, association, triangulation, filtering; ``result.npz`` written. Returns a summary."""
    import rtoml
    from Pose2Sim import Pose2Sim

    root = Path(project["dir"]).resolve()
    cfg = rtoml.load(Path(job["config"]))
    _update(cfg, json.loads(json.dumps(job["overrides"])))
    cfg["project"]["project_dir"] = str(root)
    (root / "Config.toml").write_text(rtoml.dumps(cfg))
    for d in ("pose-associated", "pose-3d"):
        if (root / d).exists():
            shutil.rmtree(root / d)
    cwd = os.getcwd()
    log = logging.FileHandler(root / "pose2sim.log", mode="w")
    log.setLevel(logging.INFO)
    logging.getLogger().addHandler(log)
    os.chdir(root)  # Pose2Sim looks for the session's calibration folder beside the working directory too
    try:
        _calibration(root, Path(job["calibration"]), list(project["cameras"]), cfg)
        Pose2Sim.personAssociation(cfg)
        Pose2Sim.triangulation(cfg)
        Pose2Sim.filtering(cfg)
    finally:
        os.chdir(cwd)
        logging.getLogger().removeHandler(log)
        log.close()
    names, columns, width = _model_columns(str(job.get("pose_model", "COCO_17")))
    n = int(job["n_frames"])
    raw = sorted(p for p in (root / "pose-3d").glob("*.trc") if "filt" not in p.name)
    arrays: dict[str, FloatArray] = {}
    for i, path in enumerate(raw):
        arrays[f"raw_{i}"] = _read_trc(path, n, columns, width)
        stem = path.name.rsplit("_", 1)[0]
        filt = sorted((root / "pose-3d").glob(f"{stem}_*filt*.trc"))
        if len(filt) != 1:
            raise RuntimeError(f"{path.name}: {len(filt)} filtered files")
        arrays[f"filt_{i}"] = _read_trc(filt[0], n, columns, width)
    np.savez(root / "result.npz", **arrays)  # type: ignore[arg-type]
    return {"dir": str(root), "people": len(raw), "trc": [p.name for p in raw], "keypoints": names}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m mocapd.eval.pose2sim_runner JOB.json", file=sys.stderr)
        return 2
    os.environ.setdefault("MPLBACKEND", "Agg")
    job = json.loads(Path(args[0]).read_text())
    # Pose2Sim logs at INFO into each project's pose2sim.log; only its warnings reach stderr.
    stderr = logging.StreamHandler()
    stderr.setLevel(logging.WARNING)
    stderr.setFormatter(logging.Formatter("pose2sim: %(message)s"))
    logging.basicConfig(level=logging.INFO, handlers=[stderr])
    out = [run_project(job, p) for p in job["projects"]]
    print(json.dumps({"projects": out}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
