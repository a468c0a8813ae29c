"""``mocapd demo`` on the camera rig, as a process: four real Aravis fake GigE cameras in a private network
namespace streaming the Pose2Sim multi-person videos, the real onnxruntime detector, sorting and solving, /status
reachable from the host namespace; one camera server is SIGKILLed mid-run (the cable pulled) and comes back.

One demo process serves every test (starting it costs most of the time): the first test unplugs a camera while it
runs, the next ones wait for its ``--seconds`` to end, read its summary and check the recorded session against the
images' detections. Quarter-resolution images keep four streams well within what a loaded 2-core machine moves
(see the torn-frame note in docs/cameras.md); a fixed latency of 2 s lets a CPU detector starved by other jobs
still deliver every camera's detections in time.

The videos play in slow motion (``--speed 0.05``: 3 frames a second, the 100-frame clips forwards then backwards
over 67 s) with packed detection (``--packed``, all four cameras per detector pass). A CPU detector shared with
the rest of the suite manages about one pass a second, several seconds apart when the machine is loaded; at the
videos' own pace the people would move a metre between two detections of a camera and be re-enrolled again and
again. In slow motion they move a few centimetres, as on a rig whose detector keeps up, so the result can be
checked: both subjects found and kept, their solves fitting every camera's detections.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import signal
import socket
import subprocess
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from websockets.asyncio.client import connect

from mocapd.io.session import Session, open_session
from mocapd.protocols.ws_stream import decode
from mocapd.service.config import DEFAULT_CONFIG
from tests import session_checks
from tests.pose2sim_data import demo_root

ROOT = Path(__file__).resolve().parents[1]
MOCAPD = ROOT / ".venv" / "bin" / "mocapd"
SECONDS = 75.0
SPEED = 0.05  # video playback speed (3 fps): see the module docstring
GRACE_S = 10.0  # tracking.enrolment.grace_period_s for a detector that stalls under load
# [daemon] body_size_s: the shipped 2 s sizes a person from 120 ticks of motion at a rig's own pace; in slow motion
# they hold 6 video frames (one or two detections per camera on a loaded machine), from which CI measured an arm
# 20 % long (forearm 0.271 m against 0.209 triangulated) and a quiet run both of one person's arm segments 13-17 %
# short. 15 s here is 45 video frames, as many distinct postures as 1.5 s at 30 keypoint sets a second.
BODY_SIZE_S = 15.0
# The unplugged camera's server is started again after this long (the demo's default is 3 s). It is declared lost
# after 2 s of silence and reopened at once when its server is back: with 3 s it was reported down for about 4 s,
# and one /status answer took up to 4.7 s on the loaded 2-core machine, so a poll could miss the outage.
REPLUG_AFTER_S = 10.0
START_TIMEOUT_S = 300.0  # models loaded, four cameras streaming: 28-150 s on the loaded 2-core machine


@dataclass
class DemoProcess:
    proc: subprocess.Popen[str]
    udp: socket.socket  # where the demo's MVN stream is configured to go (host namespace)
    session: Path  # where it records
    lines: list[str] = field(default_factory=list)
    url: str = ""
    viewer: str = ""

    def status(self) -> dict[str, Any]:
        with urllib.request.urlopen(f"{self.url}/status", timeout=5) as r:
            data: dict[str, Any] = json.loads(r.read())
        return data

    def wait_status(self, predicate: Callable[[dict[str, Any]], bool], timeout_s: float, what: str) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        st: dict[str, Any] = {}
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, f"demo ended early:\n{''.join(self.lines[-30:])}"
            try:
                st = self.status()
            except OSError:  # the socket listens from the start; the daemon serves once its inputs are up
                time.sleep(0.5)
                continue
            if st.get("ready") and predicate(st):
                return st
            time.sleep(0.25)
        raise AssertionError(f"timed out waiting for {what}; last status cameras: {st.get('cameras')}")


def _capture(st: dict[str, Any], name: str) -> dict[str, Any]:
    cam = next(c for c in st["cameras"] if c["name"] == name)
    capture: dict[str, Any] = cam["capture"]
    return capture


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DemoProcess]:
    demo_root()  # the Pose2Sim data must be there (make setup)
    tmp = tmp_path_factory.mktemp("camera-demo")
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", 0))
    udp.settimeout(5.0)
    # The shipped config, with the WebSocket stream on any free port and MVN streaming to our socket: both leave
    # the demo's private network namespace through sockets its parent made on the host.
    text = DEFAULT_CONFIG.read_text(encoding="utf-8")
    text = text.replace("port = 8766 ", "port = 0 ", 1)
    mvn = text.index("[udp.mvn]")
    text = text[:mvn] + text[mvn:].replace("enabled = false", "enabled = true", 1).replace(
        '"127.0.0.1:9763"', f'"127.0.0.1:{udp.getsockname()[1]}"', 1
    )
    # A starved detector may deliver nothing for seconds: keep the subjects through it rather than re-enrol them.
    grace = "grace_period_s = 2.0 "
    assert grace in text
    text = text.replace(grace, f"grace_period_s = {GRACE_S} ", 1)
    body_size = "body_size_s = 2.0 "
    assert body_size in text
    text = text.replace(body_size, f"body_size_s = {BODY_SIZE_S} ", 1)
    config = tmp / "config.toml"
    config.write_text(text, encoding="utf-8")
    session = tmp / "session"
    proc = subprocess.Popen(
        [str(MOCAPD), "demo", "--seconds", str(SECONDS), "--scale", "0.25", "--latency", "2.0", "--http-port", "0",
         "--speed", str(SPEED), "--packed", "--replug-after", str(REPLUG_AFTER_S), "--config", str(config),
         "--record", str(session)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    d = DemoProcess(proc, udp, session)
    assert proc.stdout is not None
    stdout = proc.stdout

    def pump() -> None:
        for line in stdout:
            d.lines.append(line)

    threading.Thread(target=pump, daemon=True).start()
    # The first lines come once mocapd has imported and bound its sockets: 1-2 s alone, over 30 s under a load of 27
    # on 2 cores. A demo that ends instead says why in its output.
    deadline = time.monotonic() + START_TIMEOUT_S
    try:
        while not (d.url and d.viewer) and time.monotonic() < deadline and proc.poll() is None:
            for line in list(d.lines):
                if line.startswith("status: http://127.0.0.1:"):
                    d.url = line.split()[1].rsplit("/status", 1)[0]
                if line.startswith("viewer: http://127.0.0.1:"):
                    d.viewer = line.split()[1]
            time.sleep(0.1)
        assert d.url and d.viewer, "".join(d.lines)
        yield d
    finally:
        udp.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def test_daemon_survives_unplugging_a_camera_and_gets_it_back(demo: DemoProcess) -> None:
    st = demo.wait_status(
        lambda s: s["ready"] and all(_capture(s, c["name"])["frames"] >= 10 for c in s["cameras"]),
        START_TIMEOUT_S, "the four cameras streaming",
    )  # fmt: skip
    assert len(st["cameras"]) == 4 and len(st["fake_cameras"]) == 4
    victim = st["fake_cameras"][1]
    name, others = victim["name"], [c["name"] for c in st["cameras"] if c["name"] != victim["name"]]
    os.kill(victim["pid"], signal.SIGKILL)  # the cable is pulled: no goodbye on the wire
    # Reported lost: the failure counted and the camera down, in one answer, while its server is still out.
    down = demo.wait_status(
        lambda s: _capture(s, name)["failures"] >= 1 and not _capture(s, name)["up"], 30, f"{name} reported lost"
    )
    cap = _capture(down, name)
    assert cap["last_error"] and cap["state"] in ("waiting to reopen", "opening"), cap
    assert next(f for f in down["fake_cameras"] if f["name"] == name)["starts"] == 1  # not plugged back in yet
    before = {c["name"]: c for c in down["cameras"]}
    solves_before, frames_before = down["counters"]["person_solves"], down["output"]["frames"]
    # While it is out, the daemon keeps capturing, detecting and solving with the three others.
    during = demo.wait_status(
        lambda s: all(c["detected"] > before[c["name"]]["detected"] for c in s["cameras"] if c["name"] in others)
        and s["counters"]["person_solves"] > solves_before,
        40, "detections and solves from the other cameras",
    )  # fmt: skip
    assert during["output"]["frames"] > frames_before
    assert all(_capture(during, o)["up"] and _capture(during, o)["failures"] == 0 for o in others)
    # The fleet plugs the camera back in; the capture path reopens it on its own, after a back-off that doubled
    # while the camera was still missing.
    back = demo.wait_status(
        lambda s: _capture(s, name)["up"] and _capture(s, name)["frames"] > _capture(down, name)["frames"] + 10,
        60, f"{name} streaming again",
    )  # fmt: skip
    cap = _capture(back, name)
    assert cap["reopens"] >= 1 and cap["failures"] >= 1
    assert cap["last_backoff_s"] is not None and cap["last_backoff_s"] >= 0.5
    fleet = next(f for f in back["fake_cameras"] if f["name"] == name)
    assert fleet["starts"] == 2 and fleet["exits"] == 1 and fleet["pid"] != victim["pid"]
    assert all(t["failures"] == 0 for t in back["tasks"].values()), back["tasks"]
    detected_back = next(c for c in back["cameras"] if c["name"] == name)["detected"]
    demo.wait_status(
        lambda s: next(c for c in s["cameras"] if c["name"] == name)["detected"] > detected_back,
        40, f"{name} detected again",
    )  # fmt: skip


def test_streams_leave_the_private_namespace(demo: DemoProcess) -> None:
    """The viewer's page and the WebSocket pose stream are served, and MVN datagrams arrive, on the host."""
    demo.wait_status(lambda s: s["counters"]["person_solves"] > 0, 120, "people solved")
    with urllib.request.urlopen(demo.viewer, timeout=5) as r:
        assert b"<canvas" in r.read()

    async def frames() -> list[dict[str, Any]]:
        got: list[dict[str, Any]] = []
        async with connect(demo.viewer.replace("http://", "ws://")) as ws:
            assert decode(await ws.recv())["type"] == "hello"
            async with asyncio.timeout(30):
                while len(got) < 20:
                    m = decode(await ws.recv())
                    if m["type"] == "frame" and m["subjects"]:
                        got.append(m)
        return got

    assert all(m["subjects"][0]["root"] for m in asyncio.run(frames()))

    async def camera_views() -> dict[int, dict[str, Any]]:
        """The camera panels of the real video: the fake GigE cameras' frames, downscaled JPEG."""
        got: dict[int, dict[str, Any]] = {}
        async with connect(demo.viewer.replace("http://", "ws://")) as ws:
            await ws.send(json.dumps({"type": "subscribe", "encoding": "json", "cameras": True}))
            async with asyncio.timeout(60):
                while len(got) < 4 or not any(m["subjects"] for m in got.values()):
                    m = decode(await ws.recv())
                    if m["type"] == "camera" and m["image"]:
                        got[m["camera"]] = m
        return got

    views = asyncio.run(camera_views())
    for m in views.values():
        img = cv2.imdecode(np.frombuffer(base64.b64decode(m["image"]), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.shape[1] == m["image_width"] == min(320, m["width"])  # never upscaled
        assert abs(img.shape[0] / img.shape[1] - m["height"] / m["width"]) < 0.01
        assert float(img.std()) > 10.0  # a video frame, not a blank image
    data, _ = demo.udp.recvfrom(65536)
    assert data[:6] == b"MXTP02"


def _finished(demo: DemoProcess) -> dict[str, Any]:
    """Wait for the demo's ``--seconds`` to end; its summary."""
    code = demo.proc.wait(timeout=SECONDS + 150)
    text = "".join(demo.lines)
    assert code == 0, text[-3000:]
    summary: dict[str, Any] = json.loads(next(line for line in reversed(demo.lines) if line.startswith('{"summary"')))[
        "summary"
    ]
    return summary


def test_demo_runs_end_to_end_and_reports_people_solved(demo: DemoProcess) -> None:
    summary = _finished(demo)
    text = "".join(demo.lines)
    assert "ready: status http://127.0.0.1:" in text
    assert "packed (all cameras per pass)" in text and "slow motion" in text  # what --packed --speed run
    assert summary["frames"] > 100
    assert summary["frames_with_people"] > 0 and summary["max_people"] == 2, summary
    assert all(n > 0 for n in summary["detected"].values()), summary
    assert "with people solved" in text
    # The run was recorded: a clean session with the cameras' keypoints and the published poses.
    session = open_session(demo.session)
    assert session.closed_cleanly and len(session.keypoints()) > 10
    assert sum(1 for f in session.poses() if f.people) > 0


# What the recorded session must show. Measured on this rig on the shared 2-core machine (load averages 4-25; CI
# runs alone): per subject and camera, median reprojection 2.5-9.5 px over 3-171 compared frames (the acrobat in
# cam02 at 15 px before mirrored detections were allowed for); body-size estimates 1.29-1.39 m (the smaller
# subject: the estimator's leg-length proportion) and 1.49-1.65 m, their limb segments 0-36 % from the triangulated
# ones (forearms the most: wrists are a few pixels in these images, and a fresh machine's first run measured 36 %)
# while whole limbs (upper arm + forearm, thigh + shank) stayed within 12 %.
REPROJECTION_MAX_PX = 12.0  # median per subject and camera, in 272 x 480 images (2.5 % of their height)
SEGMENT_TOLERANCE = 0.45  # body-size estimate's limb segments vs their triangulation from the detections
LIMB_TOLERANCE = 0.2  # the same for whole arms and legs, where a misplaced elbow or knee cancels out
LIMBS = {"arm": ("upper arm", "forearm"), "leg": ("thigh", "shank")}
HEIGHT_RANGE_M = (1.2, 2.0)
BOTH_FRAMES_MIN = 60  # published frames with both subjects: one second of output (196 at load 25)
MATCH_TOLERANCE_NS = 100_000_000  # a detection vs the pose published nearest its capture (5 ms of slowed video)


def test_both_subjects_are_found_kept_and_fit_every_camera(demo: DemoProcess) -> None:
    """The result, checked against the images: the two people of the video are enrolled once each and kept to
    the end (no bystander, no re-enrolment), their solved limb joints reproject onto the detections in every
    camera, and their body-size estimates agree with limb lengths triangulated here from the detections."""
    _finished(demo)
    check_subjects(open_session(demo.session))


def check_subjects(session: Session) -> None:
    """The checks of the test above on a recorded session of this rig."""
    poses = session.poses()
    identities = sorted({p.identity for f in poses for p in f.people})
    assert len(identities) == 2, identities  # the two subjects, nobody else, never re-enrolled
    both = [f for f in poses if len(f.people) == 2]
    assert len(both) >= BOTH_FRAMES_MIN, len(both)
    for f in both:  # two different people inside the capture volume, hips at hip height
        a, b = (np.asarray(p.joints, np.float64)[0] for p in f.people)
        assert np.linalg.norm(a[[0, 2]] - b[[0, 2]]) > 0.3 and all(abs(v) < 2.5 for v in (a[0], a[2], b[0], b[2]))
        assert 0.4 < a[1] < 1.3 and 0.4 < b[1] < 1.3, (a, b)

    fits = session_checks.subject_fits(session, MATCH_TOLERANCE_NS)
    cameras = len(session.manifest["cameras"])
    window = round(1e9 / (60.0 * SPEED))  # one camera frame: within it the slow-motion people are still
    for who in identities:
        fit = fits[who]
        medians = {c: float(np.median(e)) for c, e in fit.errors_px.items()}
        print(who, "reprojection px (median per camera):", {c: round(m, 1) for c, m in sorted(medians.items())},
              "frames:", {c: len(e) for c, e in sorted(fit.errors_px.items())})  # fmt: skip
        assert sorted(medians) == list(range(cameras)) and all(len(e) >= 3 for e in fit.errors_px.values()), who
        assert all(m <= REPROJECTION_MAX_PX for m in medians.values()), (who, medians)

        sized = [p.skeleton for f in poses for p in f.people if p.identity == who and p.skeleton is not None]
        assert sized, f"{who} was never body-sized"
        estimate = sized[-1]
        assert HEIGHT_RANGE_M[0] <= estimate.height <= HEIGHT_RANGE_M[1], (who, estimate.height)
        # Every pose published on it has its bone lengths (the stream's joints are the estimate's): at most two
        # estimates, a provisional one from the first [daemon] body_size_first_s and the final one, each held
        # unchanged while it is published.
        published = session_checks.published_segments(poses, who)
        keys = [s.offsets.tobytes() for s in sized]
        runs = [i for i in range(1, len(keys)) if keys[i] != keys[i - 1]]
        assert len(runs) <= 1, (who, "body size changed at poses", runs)
        for part in (published[: runs[0]], published[runs[0] :]) if runs else (published,):
            for name in session_checks.SEGMENTS:
                values = np.array([s[name] for s in part])
                assert np.ptp(values) < 2e-3, (who, name, values.min(), values.max())
        triangulated = session_checks.triangulated_segments(session, fit, window)
        print(who, "height", round(estimate.height, 3), "segments published/triangulated:",
              {k: (round(published[-1][k], 3), round(v, 3)) for k, v in triangulated.items()})  # fmt: skip
        assert set(triangulated) == set(session_checks.SEGMENTS), triangulated
        for name, length in triangulated.items():
            assert abs(published[-1][name] / length - 1.0) <= SEGMENT_TOLERANCE, (who, name, published[-1], length)
        for limb, parts in LIMBS.items():
            ratio = sum(published[-1][p] for p in parts) / sum(triangulated[p] for p in parts)
            assert abs(ratio - 1.0) <= LIMB_TOLERANCE, (who, limb, published[-1], triangulated)


def test_the_closing_line_says_keypoint_and_detection_rates_and_latency() -> None:
    """``make demo``'s summary line: detections and keypoints per camera (per person in view), end to end."""
    from mocapd.service.demo.cameras import summary_line

    summary = {
        "frames": 4500, "frames_with_people": 4440, "max_people": 2, "identities": ["track:1", "track:2"],
        "seconds": 75.0, "detected": {"cam01": 450, "cam02": 480},
        "keypoint_hz_per_person": {"cam01": 30.1, "cam02": 31.4},
        "end_to_end_ms": {"p50": 98.2, "p95": 131.0},
    }  # fmt: skip
    line = summary_line(summary)
    assert line.startswith("done: 4500 frames, 4440 with people solved (at most 2 at once: track:1, track:2)")
    assert "detections 6.2 Hz per camera" in line and "keypoints 30-31 Hz per camera and person" in line
    assert line.endswith("end to end p50 98 ms, p95 131 ms")
    bare = summary_line({"frames": 3, "frames_with_people": 0, "max_people": 0, "identities": []})
    assert bare == "done: 3 frames, 0 with people solved (at most 0 at once: nobody)"


def test_the_closing_lines_rates_count_the_output_seconds_not_the_start_up() -> None:
    """The rates divide by the seconds from the first published frame to the last: a daemon that took 35 s to start
    (a fresh checkout compiling its kernels) and then ran 50 s reports its cameras' rates over the 50 s."""
    from mocapd.pipeline.scheduler import PoseFrame
    from mocapd.service.demo.cameras import PeopleCount

    now = [35.0]
    count = PeopleCount(clock=lambda: now[0])
    assert count.seconds() == 0.0
    for k in range(3001):
        now[0] = 35.0 + k / 60.0
        count.publish(PoseFrame(frame=k, t_solve_ns=k, tick_ns=k, people=[], missing_cameras=0))
    assert count.seconds() == pytest.approx(50.0) and count.frames == 3001


def test_the_recorded_keypoint_sets_replay_to_the_live_people_count(demo: DemoProcess) -> None:
    """``tools/replay_people.py`` on the recorded session (its keypoint sets through the people sorting at their
    live arrival times) finds the people the live daemon solved, tick by tick on average, and its two subjects."""
    from tools.replay_people import replay

    _finished(demo)
    r = replay(str(demo.session), [])
    assert r["ticks"] > 100 and r["identities_recorded"] == ["track:1", "track:2"]
    assert abs(r["person_solves_per_tick"] - r["recorded_person_solves_per_tick"]) <= 0.05, r
    assert [e[1] for e in r["tracking_events"]][:2] == ["enrolled", "enrolled"]
