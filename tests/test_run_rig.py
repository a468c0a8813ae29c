"""``mocapd run`` on rigs of real components, configured the way a user writes config.toml (issue: run on a real
rig): four fake GigE Vision cameras in a private network namespace, video / webcam / image-folder cameras with
Xsens IMUs on pseudo-terminals, every rule of ``check-config``, a device that does not open, and Ctrl-C."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import pytest

from mocapd.io.calibration_files import read_qca, scale_calibration, write_mocapd_toml
from mocapd.io.session import open_session
from mocapd.service.cli import main
from tests.pose2sim_data import demo_root

REPO = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parent / "data"
MTW = DATA / "opensense_mtw"
SHUTDOWN_TIMEOUT_S = 1.5  # daemon.shutdown_timeout_s of the shipped config


def _calib() -> Path:
    return demo_root() / "Demo_MultiPerson" / "calibration" / "Calib.qca.txt"


def _video(cam: str) -> Path:
    return demo_root() / "Demo_MultiPerson" / "videos" / f"{cam}.mp4"


# ------------------------------------------------------------------------------------ four GigE Vision cameras
def test_run_on_four_gige_cameras_streams_both_people_and_stops_on_ctrl_c(tmp_path: Path) -> None:
    """The user's commands: calibrate convert, check-config, run. The fake cameras and `mocapd run` live in a
    private network namespace (Aravis must never broadcast on a real network); a WebSocket client there reads
    the stream; then SIGINT, as Ctrl-C sends it."""
    shutil.copy(DATA / "four_gige.toml", tmp_path / "four_gige.toml")
    assert main(["calibrate", "convert", str(_calib()), str(tmp_path / "calibration.toml"), "--scale", "0.5"]) == 0
    assert main(["check-config", str(tmp_path / "four_gige.toml")]) == 0
    proc = subprocess.run(
        ["unshare", "-rn", sys.executable, "-m", "tests.netns_rig", "--config", str(tmp_path / "four_gige.toml"),
         "--seconds", "150", "--want-two", "20"],
        cwd=REPO, capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    out = "".join(result["output"])
    stream = result["stream"]
    assert stream["max_subjects"] == 2 and stream["frames_with_two"] >= 20, out
    assert len(stream["identities"]) >= 2
    # Both walkers' hips about a metre above the floor, inside the Pose2Sim capture volume.
    for x, y, z in stream["roots"]:
        assert 0.5 < y < 1.3 and abs(x) < 3.0 and abs(z) < 3.0, (x, y, z)
    assert result["exit_code"] == 0, out
    assert result["stop_s"] < SHUTDOWN_TIMEOUT_S + 1.0, out
    assert result["camera_restarts_during_stop"] == 0
    assert "abandoned" not in out and "Traceback" not in out


# ------------------------------------------------------------------ video, webcam, image folder, Xsens on ptys
class RunProcess:
    """``mocapd run`` as a subprocess, its output collected by a thread."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "mocapd", "run", *args], cwd=cwd,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)  # fmt: skip
        self.lines: list[str] = []
        assert self.proc.stdout is not None
        stdout = self.proc.stdout
        threading.Thread(target=lambda: self.lines.extend(stdout), daemon=True).start()

    @property
    def output(self) -> str:
        return "".join(self.lines)

    def url(self, timeout: float) -> str:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for line in list(self.lines):
                if line.startswith("ready: status http://"):
                    return line.split()[2].rsplit("/status", 1)[0]
            assert self.proc.poll() is None, self.output
            time.sleep(0.1)
        raise AssertionError(f"not ready within {timeout} s:\n{self.output}")

    def wait_status(self, url: str, predicate: Callable[[dict[str, Any]], bool], timeout: float) -> dict[str, Any]:
        end = time.monotonic() + timeout
        st: dict[str, Any] = {}
        while time.monotonic() < end:
            with urllib.request.urlopen(f"{url}/status", timeout=5) as r:
                st = json.loads(r.read())
            if predicate(st):
                return st
            time.sleep(0.25)
        raise AssertionError(f"status never matched; last: {json.dumps(st)[:2000]}\n{self.output[-3000:]}")

    def interrupt(self) -> tuple[int, float]:
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGINT)
        code = self.proc.wait(timeout=30)
        return code, time.monotonic() - t0

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def _half_size(video: Path, out: Path) -> None:
    """The video at half size, as a video file (``out`` with a suffix) or a folder of JPEG images (without): what
    the cameras of this rig replay (a quarter of the pixels to decode, on a 2-core machine)."""
    cap = cv2.VideoCapture(str(video))
    fps = cap.get(cv2.CAP_PROP_FPS)
    writer = None if out.suffix == "" else cv2.VideoWriter(str(out), cv2.VideoWriter.fourcc(*"mp4v"), fps, (544, 960))
    if writer is None:
        out.mkdir()
    k = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        small = cv2.resize(frame, (544, 960), interpolation=cv2.INTER_AREA)
        if writer is not None:
            writer.write(small)
        else:
            cv2.imwrite(str(out / f"{k:04d}.jpg"), small, [cv2.IMWRITE_JPEG_QUALITY, 90])
        k += 1
    cap.release()
    if writer is not None:
        writer.release()


def test_run_with_video_webcam_and_image_cameras_and_xsens_imus_on_ptys(tmp_path: Path) -> None:
    """One rig of every replay kind: cam01 a video file, cam02 a webcam (`uvc`) opened on a video file through
    the same OpenCV path, cam03 a folder of images, all at half the size of the Pose2Sim videos (the calibration
    scaled to match), and two Xsens devices streaming real MTw recordings on pseudo-terminals named in
    ``[imu] ports``."""
    write_mocapd_toml(scale_calibration(read_qca(_calib()), 0.5), tmp_path / "calibration.toml")
    _half_size(_video("cam01"), tmp_path / "cam01.mp4")
    _half_size(_video("cam02"), tmp_path / "cam02.mp4")
    _half_size(_video("cam03"), tmp_path / "cam03")
    links = [tmp_path / "imu0", tmp_path / "imu1"]
    motions = sorted(MTW.glob("MT_*.txt"))[:2]
    sim = subprocess.Popen(
        [sys.executable, "-m", "mocapd.sim.xsens", *(a for link, m in zip(links, motions, strict=True)
                                                     for a in ("--link", str(link), "--motion", str(m)))],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    config = tmp_path / "rig.toml"
    config.write_text(
        f"""
[[cameras]]
name = "cam01"
source = "video"
path = "cam01.mp4"

[[cameras]]
name = "cam02"
source = "uvc"
device = "cam02.mp4"

[[cameras]]
name = "cam03"
source = "images"
path = "cam03"
fps = 60.0

[calibration]
file = "calibration.toml"

[imu]
ports = ["{links[0]}", "{links[1]}"]

[detector]
intra_op_threads = 2

[detector.packing]
enabled = false

[daemon]
http_port = 0
latency_s = 2.0
keypoint_max_age_s = 1.0
keypoint_max_gap_s = 5.0
capture_nice = 3
detector_nice = 7

[websocket]
enabled = false
""",
        encoding="utf-8",
    )
    run = None
    try:
        end = time.monotonic() + 30
        while not all(link.exists() for link in links):
            assert time.monotonic() < end and sim.poll() is None, "the Xsens simulators did not start"
            time.sleep(0.1)
        assert main(["check-config", str(config)]) == 0
        run = RunProcess(["--config", str(config), "--verbose"], cwd=tmp_path)
        url = run.url(300)

        def solved(st: dict[str, Any]) -> bool:
            frame = st.get("frame") or {}
            return len(frame.get("people", [])) >= 1 and all(c["detected"] > 5 for c in st["cameras"])

        st = run.wait_status(url, solved, 180)
        kinds = {c["name"]: c["kind"] for c in st["cameras"]}
        assert set(kinds) == {"cam01", "cam02", "cam03"}
        assert all(c["capture"]["up"] for c in st["cameras"])
        devices = st["imu"]["devices"]
        assert {d["path"] for d in devices} == {str(links[0]), str(links[1])}
        assert all(d["streaming"] and d["samples"] > 0 for d in devices)
        for person in st["frame"]["people"]:
            assert 0.4 < person["root_m"][1] < 1.4  # a standing adult's hips
        # [daemon] capture_nice, detector_nice: the event loop (main thread) keeps the daemon's priority; the capture
        # threads (each named once its device opened) run 3 nicer, the detector's, onnxruntime's included, 7.
        nice = _thread_nice(run.proc.pid)
        base = nice[run.proc.pid][1]
        by_name: dict[str, list[int]] = {}
        for name, n in nice.values():
            by_name.setdefault(name, []).append(n)
        # The three capture threads and the threads they start after opening (OpenCV's pool for the tracking).
        capture, detect = by_name.get("mocapd-capture", []), by_name.get("mocapd-detect", [])
        assert len(capture) >= 3 and set(capture) == {base + 3}, by_name
        assert len(detect) >= 2 and set(detect) == {base + 7}, by_name  # the worker and onnxruntime's thread
        code, elapsed = run.interrupt()
        assert code == 0, run.output
        assert elapsed < SHUTDOWN_TIMEOUT_S + 1.0
    finally:
        if run is not None:
            run.close()
        sim.send_signal(signal.SIGTERM)
        sim.wait(timeout=10)


def _thread_nice(pid: int) -> dict[int, tuple[str, int]]:
    """Every thread of process ``pid``: its OS-level name and nice value (/proc/PID/task/TID/stat, field 19)."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError):
            continue  # the thread ended meanwhile
        out[int(task.name)] = (name, int(fields[16]))
    return out


# ---------------------------------------------------------------------------------------------- check-config
def _rig(tmp: Path, cameras: str, extra: str = "") -> Path:
    calib = tmp / "calibration.toml"
    if not calib.exists():
        write_mocapd_toml(scale_calibration(read_qca(_calib()), 0.5), calib)
    config = tmp / "config.toml"
    config.write_text(f'{cameras}\n[calibration]\nfile = "calibration.toml"\n{extra}', encoding="utf-8")
    return config


GIGE = '[[cameras]]\nname = "{name}"\nsource = "aravis"\naddress = "127.0.0.1"\nregion = [0, 0, {w}, {h}]\n'
BAD_RIGS: list[tuple[str, str, str, str]] = [
    # (what, [[cameras]] tables, more tables, what the one error line must say)
    ("unknown source", '[[cameras]]\nname = "cam01"\nsource = "gopro"\n', "", "cameras[0].source = 'gopro'"),
    ("not in the calibration", GIGE.format(name="cam09", w=544, h=960), "",
     "cameras[0].name = 'cam09': not in the calibration"),
    ("size disagrees", GIGE.format(name="cam01", w=1088, h=1920), "",
     "cameras[0] (cam01) delivers 1088x1920 images, but the calibration has it at 544x960"),
    ("duplicate names", GIGE.format(name="cam01", w=544, h=960) + GIGE.format(name="cam01", w=544, h=960), "",
     "cameras[1].name = 'cam01': already the name of cameras[0]"),
    ("missing video", '[[cameras]]\nname = "cam01"\nsource = "video"\npath = "nope.mp4"\n', "",
     "video (path) {tmp}/nope.mp4: no such file"),
    ("unreadable video", '[[cameras]]\nname = "cam01"\nsource = "video"\npath = "calibration.toml"\n', "",
     "video (path) {tmp}/calibration.toml: cannot open (not a video OpenCV/FFmpeg reads?)"),
    ("empty image folder", '[[cameras]]\nname = "cam01"\nsource = "images"\npath = "."\n', "",
     "path = '{tmp}': holds no image"),
    ("two ways to open", GIGE.format(name="cam01", w=544, h=960).replace('source', 'serial = "X"\nsource'), "",
     "cameras[0]: set exactly one of address, serial, device_id"),
    ("bad fourcc", '[[cameras]]\nname = "cam01"\nsource = "uvc"\ndevice = 0\nfourcc = "MJPEG"\n', "",
     "fourcc = 'MJPEG': must be 4 characters"),
    ("bad name", '[[cameras]]\nname = "cam 1"\nsource = "uvc"\ndevice = 0\n', "", "cameras[0].name = 'cam 1'"),
    ("synthetic among real",
     GIGE.format(name="cam01", w=544, h=960) + '[[cameras]]\nname = "s"\nsource = "synthetic"\n', "",
     "a synthetic camera cannot be mixed with real ones"),
    ("offsets of an unknown camera", GIGE.format(name="cam01", w=544, h=960),
     "[daemon.offsets]\ncameras = { cam7 = 0.01 }\n", "daemon.offsets.cameras: unknown camera(s) ['cam7']"),
    ("nan exposure", GIGE.format(name="cam01", w=544, h=960) + "exposure_us = nan\n", "",
     "cameras[0].exposure_us = nan; allowed: a number in (0, 1e+07]"),
    ("unknown key", GIGE.format(name="cam01", w=544, h=960) + "exposure = 10\n", "",
     "unknown key cameras[0].exposure; allowed:"),
    ("no such interface",
     GIGE.format(name="cam01", w=544, h=960).replace('address = "127.0.0.1"', 'serial = "X"\ninterface = "gige9"'),
     "", "cameras[0].interface = 'gige9': no such network interface"),
    ("no cameras", "", "", "no cameras and no IMU source: add [[cameras]]"),
]  # fmt: skip


@pytest.mark.parametrize(("what", "cameras", "extra", "message"), BAD_RIGS, ids=[r[0] for r in BAD_RIGS])
def test_check_config_names_the_key_and_value_of_every_broken_rule(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], what: str, cameras: str, extra: str, message: str
) -> None:
    config = _rig(tmp_path, cameras, extra)
    assert main(["check-config", str(config)]) == 2, what
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err  # one line per problem, and this rig has one
    assert message.format(tmp=tmp_path) in lines[0], err
    assert main(["run", "--config", str(config)]) == 2  # run refuses it the same way, before opening anything
    assert message.format(tmp=tmp_path) in capsys.readouterr().err


def test_check_config_without_a_calibration_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "c.toml"
    config.write_text(GIGE.format(name="cam01", w=544, h=960), encoding="utf-8")
    assert main(["check-config", str(config)]) == 2
    assert "calibration.file is not set" in capsys.readouterr().err
    config.write_text(GIGE.format(name="cam01", w=544, h=960) + '[calibration]\nfile = "nope.toml"\n', "utf-8")
    assert main(["check-config", str(config)]) == 2
    assert f"calibration.file = '{tmp_path}/nope.toml'" in capsys.readouterr().err


def test_run_names_every_device_that_does_not_open_and_stops(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A webcam that is not plugged in and an IMU port that does not exist: ``mocapd run`` opens every device
    before READY and says which failed and why, exit 2, nothing left running."""
    config = _rig(
        tmp_path,
        '[[cameras]]\nname = "cam01"\nsource = "uvc"\ndevice = "/dev/video-not-there"\n'
        '[[cameras]]\nname = "cam02"\nsource = "uvc"\ndevice = "/dev/video-not-there-either"\n',
        f'[imu]\nports = ["{tmp_path}/no-such-imu"]\n[daemon]\nhttp_port = 0\n[websocket]\nport = 0\n',
    )
    run = RunProcess(["--config", str(config)], cwd=tmp_path)
    try:
        code = run.proc.wait(timeout=300)
    finally:
        run.close()
    time.sleep(0.2)
    out = run.output
    assert code == 2, out
    error = next(line for line in out.splitlines() if line.startswith("error: "))
    assert "camera cam01: camera 'cam01': cannot open '/dev/video-not-there'" in error
    assert "camera cam02" in error
    assert f"IMU {tmp_path}/no-such-imu" in error
    assert "ready:" not in out and "Traceback" not in out


# ---------------------------------------------------------------------------------------------------- Ctrl-C
def test_ctrl_c_stops_run_in_time_with_the_session_complete(tmp_path: Path) -> None:
    """SIGINT (Ctrl-C): every task ends, the simulated serial devices are closed, the session is complete, exit 0
    within shutdown_timeout_s plus a second."""
    config = tmp_path / "synthetic.toml"
    config.write_text(
        "".join(f'[[cameras]]\nname = "cam{i}"\nsource = "synthetic"\n' for i in range(4))
        + "[daemon]\nhttp_port = 0\n[websocket]\nport = 0\n",
        encoding="utf-8",
    )
    session = tmp_path / "session"
    run = RunProcess(["--config", str(config), "--record", str(session)], cwd=tmp_path)
    try:
        url = run.url(300)
        run.wait_status(url, lambda st: bool(st["frame"] and st["frame"]["people"]), 60)
        time.sleep(1.0)
        code, elapsed = run.interrupt()
    finally:
        run.close()
    assert code == 0, run.output
    assert elapsed < SHUTDOWN_TIMEOUT_S + 1.0, f"{elapsed:.2f} s"
    assert "abandoned" not in run.output and "Traceback" not in run.output
    s = open_session(session)
    assert s.closed_cleanly
    assert not any(r.damaged for r in s.check().values())
    assert len(s.poses()) > 10 and len(s.imu()) > 100
