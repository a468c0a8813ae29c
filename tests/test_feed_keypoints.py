"""``mocapd feed keypoints``: OpenPose BODY_25 folders fed to a running daemon over Zenoh on loopback, as a camera
host; the daemon (``mocapd run``, ``source = "zenoh"`` cameras, ``keypoint_format = "body25"``) solves both people."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from mocapd.io.calibration_files import CalibrationSet, CameraCalibration, write_mocapd_toml
from mocapd.io.lifecycle import guarded_command
from mocapd.sim.camera_hosts import host_config, solver_config
from mocapd.sim.world import SyntheticWorld
from tests.test_camera_hosts import free_port
from tests.test_run_rig import RunProcess

REPO = Path(__file__).resolve().parents[1]
CAMS = ["cam0", "cam1", "cam2", "cam3"]
FPS = 25.0


def _openpose_folders(world: SyntheticWorld, folder: Path, seconds: float) -> list[str]:
    """OpenPose ``--write_json`` folders of the world's cameras (BODY_25, 1 px noise); ``CAMERA=FOLDER`` inputs."""
    rng = np.random.default_rng(0)
    inputs = []
    for c, cam in enumerate(world.cameras):
        d = folder / f"video{c}"  # a name that is no camera's: the inputs name them
        d.mkdir(parents=True)
        for f in range(round(seconds * FPS)):
            det = world.detections(c, f / FPS, rng, 1.0)
            people = [{"pose_keypoints_2d": np.column_stack([det.keypoints[i], det.confidences[i]]).ravel().tolist()}
                      for i in range(len(det))]  # fmt: skip
            (d / f"video{c}_{f:012d}_keypoints.json").write_text(json.dumps({"version": 1.3, "people": people}))
        inputs.append(f"{cam.name}={d}")
    return inputs


def test_openpose_folders_fed_to_a_running_daemon(tmp_path: Path) -> None:
    world = SyntheticWorld(n_cams=4, n_people=2, n_suits=0, keypoints="body25", seed=1, camera_names=CAMS)
    calib = CalibrationSet(tuple(CameraCalibration(c.name, (c.width, c.height), c.K, c.dist, c.R, c.t)
                                 for c in world.cameras))  # fmt: skip
    write_mocapd_toml(calib, tmp_path / "calibration.toml")
    inputs = _openpose_folders(world, tmp_path / "openpose", seconds=8.0)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    extra: dict[str, dict[str, object]] = {
        "daemon": {"latency_s": 0.3, "keypoint_max_age_s": 0.2},
        "detector.model": {"keypoint_format": "body25"},
    }
    solver_toml = solver_config(dict.fromkeys(CAMS, "feedA"), tmp_path / "calibration.toml", [endpoint], extra=extra)
    (tmp_path / "solver.toml").write_text(solver_toml, encoding="utf-8")
    (tmp_path / "feed.toml").write_text(host_config("feedA", [], [endpoint]), encoding="utf-8")
    solver = RunProcess(["--config", str(tmp_path / "solver.toml")], tmp_path)
    feed = None
    try:
        url = solver.url(180)
        cmd = [sys.executable, "-m", "mocapd", "feed", "keypoints", "--config", str(tmp_path / "feed.toml"),
               "--calibration", str(tmp_path / "calibration.toml"), "--fps", str(FPS), *inputs]  # fmt: skip
        feed = subprocess.Popen(guarded_command(cmd), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True)  # fmt: skip
        lines: list[str] = []
        assert feed.stdout is not None
        out = feed.stdout
        threading.Thread(target=lambda: lines.extend(out), daemon=True).start()
        st = solver.wait_status(
            url,
            lambda s: len((s.get("frame") or {}).get("people") or []) == 2 and s["frame"]["missing_cameras"] == 0,
            60,
        )
        assert st["remote_hosts"]["feedA"]["lost"] is False
        for p in st["frame"]["people"]:  # where the simulated world has them: hips about a metre up, in the ring
            x, y, z = p["root_m"]
            assert 0.5 < y < 1.3 and abs(x) < 4 and abs(z) < 4, p
        assert feed.wait(timeout=60) == 0, "".join(lines)
        time.sleep(0.2)
        text = "".join(lines)
        assert "ready: host feedA feeding cam0, cam1, cam2, cam3" in text, text
        result = json.loads(text[text.index("{") :])
        assert result["keypoint_format"] == "body25" and result["sent"] == dict.fromkeys(CAMS, 200), result
    finally:
        if feed is not None and feed.poll() is None:
            feed.kill()
            feed.wait()
        solver.close()
