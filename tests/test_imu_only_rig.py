"""An IMU-only rig, as a suit owner configures it: ``mocapd run --config`` with no ``[[cameras]]``.

One run carries both IMU transports: an Xsens suit (13 simulated devices on real pseudo-terminals, speaking Xbus)
and a SlimeVR suit (13 sensors of the PyPI ``slimevr-tracker-emulator`` on loopback UDP). A real WebSocket client
reads both wearers' poses, and VRChat's OSC trackers arrive on a UDP socket the test bound. One daemon start for
both transports keeps the suite's time down."""

from __future__ import annotations

import asyncio
import json
import socket
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pythonosc.osc_bundle import OscBundle
from websockets.asyncio.client import connect

from mocapd.core.body_dims import segment_lengths
from mocapd.core.people import PeopleTracker
from mocapd.core.sorting import DetectionSorter
from mocapd.core.tracking import SubjectTracker
from mocapd.pipeline.imu_ingest import ImuIngest
from mocapd.pipeline.scheduler import FixedLatencyScheduler
from mocapd.service.cli import main
from mocapd.service.config import load_config
from mocapd.service.demo.imu_only import IMU_RATE_HZ, simulated_suit, suit_rig_config
from mocapd.service.rig import build_rig
from mocapd.service.rig_plan import plan_rig
from mocapd.sim.world import SyntheticWorld
from tests.test_run_rig import RunProcess
from tools.slimevr_rig import emulated_trackers, slimevr_calibration


def _toml(value: Any) -> str:
    return json.dumps(value)  # strings, numbers and lists of strings read the same in TOML


def test_imu_only_run_streams_an_xsens_suit_and_slimevr_trackers_to_websocket_and_vrchat(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    osc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    osc.bind(("127.0.0.1", 0))
    osc.settimeout(0.2)
    vrchat = f"127.0.0.1:{osc.getsockname()[1]}"
    slime_world = SyntheticWorld(0, 1, 1, seed=3, motion="procedural")
    slime = replace(slimevr_calibration(slime_world, slime_world.suits[0]), person="slime")
    with simulated_suit(load_config()) as xsens:
        imu = xsens.config.imu
        folder = Path(imu.calibration_dir)
        (folder / "slime.imu.json").write_text(json.dumps(slime.to_json_dict()), encoding="utf-8")
        body = segment_lengths(xsens.world.skeleton)  # the Xsens wearer, measured with a tape
        config = tmp_path / "suit.toml"
        config.write_text(
            "[imu]\n"
            f"ports = [{', '.join(_toml(p) for p in imu.ports)}]\n"
            f"calibration_dir = {_toml(str(folder))}\n"
            # No [imu.assignment] for the Xsens suit: a flat one assigns each bone once, and two wearers have two
            # of each (per-person tables would: tests/test_imu_two_suits.py); the daemon takes every suit's sensors
            # from its calibration file.
            "[imu.body]\n" + "".join(f"{k}_m = {v:.3f}\n" for k, v in body.items())
            + "[imu.slimevr]\nenabled = true\nport = 0\n"
            "[imu.slimevr.assignment]\n" + "".join(f"{_toml(k)} = {_toml(v)}\n" for k, v in slime.bones.items())
            + "[daemon]\nhttp_port = 0\noutput = \"predicted\"\n"
            "[websocket]\nport = 0\n"
            f"[udp.vrchat]\nenabled = true\ndestination = \"127.0.0.1:{osc.getsockname()[1]}\"\n"
            "subject = \"suit:slime\"\n",
            encoding="utf-8",
        )  # fmt: skip
        assert main(["check-config", str(config)]) == 0
        said = capsys.readouterr().out
        assert "IMUs only (no cameras): 13 Xsens serial ports" in said and "SlimeVR server on udp" in said, said
        assert "slime (13 sensors), suit0 (13 sensors)" in said, said

        run = RunProcess(["--config", str(config), "--verbose"], cwd=tmp_path)
        try:
            url = run.url(300)
            ws_url = next(line.split()[-1] for line in run.lines if line.startswith("viewer "))
            st = run.wait_status(url, lambda s: s["imu"]["slimevr"] is not None, 30)
            port = int(st["imu"]["slimevr"]["listen"].rsplit(":", 1)[1])
            frames, osc_bundles = asyncio.run(_stream(ws_url, port, slime_world, osc))
            st = run.wait_status(url, lambda s: True, 5)
            code, _ = run.interrupt()
        finally:
            run.close()
            osc.close()
        assert code == 0, run.output
        assert "Traceback" not in run.output, run.output[-4000:]
        # --verbose says what happens to the devices (info lines, hidden before): each device streaming (every one
        # named: mocapd.io.log_throttle's limit of five lines per call site held eight of thirteen back, said only
        # as a count), the tracker connecting.
        streaming = [p for p in imu.ports if f"imu {p}: MTw2-3A7G6 " in run.output]
        assert streaming == list(imu.ports) and "firmware 4.6.0 streaming at 100 Hz" in run.output, run.output[-4000:]
        assert "slimevr: tracker 00:78:78:78:78:78 connected from 127.0.0.1:" in run.output, run.output[-4000:]
        # and each tracker sensor's id, the key of [imu.slimevr.assignment] (read from /status's JSON before)
        for index in range(13):
            assert f'slimevr: sensor "00:78:78:78:78:78/{index}" streaming (the key' in run.output, run.output[-4000:]
        assert f"VRChat OSC trackers to {vrchat}: suit:slime\n" in run.output, run.output[-4000:]

        # Every device opened before READY; no camera, no detector.
        assert st["cameras"] == [] and "detector" not in st
        assert all(d["streaming"] for d in st["imu"]["devices"]) and len(st["imu"]["devices"]) == 13
        (tracker,) = st["imu"]["slimevr"]["trackers"]
        assert tracker["connected"] and len(tracker["sensors"]) == 13

        # The WebSocket client saw both wearers, with their IMUs, on the ground.
        by_id: dict[str, list[dict[str, Any]]] = {}
        for f in frames:
            for s in f["subjects"]:
                by_id.setdefault(s["id"], []).append({**s, "t_solve_ns": f["t_solve_ns"]})
        assert {"suit:suit0", "suit:slime"} <= set(by_id), sorted(by_id)
        for subject in by_id.values():
            assert max(s["imus"] for s in subject) >= 10
            heights = [s["root"][1] for s in subject]
            assert 0.6 < float(np.median(heights)) < 1.2, heights[-5:]
        # The Xsens wearer's joints follow the simulated body (roots put together: nothing fixes where a suit
        # alone is in the room).
        errors = []
        for s in by_id["suit:suit0"][-120:]:
            truth = xsens.world.joints_at(0, (s["t_pose_ns"] - xsens.epoch_ns) / 1e9)
            joints = np.array(s["joints"]).reshape(21, 3)
            errors.append(np.linalg.norm((joints - joints[0]) - (truth - truth[0]), axis=1).mean())
        assert float(np.median(errors)) < 0.08, np.median(errors)

    # VRChat got the SlimeVR wearer's trackers.
    assert len(osc_bundles) >= 30
    hips = [m.params for b in osc_bundles for m in OscBundle(b) if m.address == "/tracking/trackers/1/position"]
    assert hips and all(np.isfinite(p).all() for p in hips)
    assert 0.6 < float(np.median([p[1] for p in hips])) < 1.2


async def _stream(
    ws_url: str, port: int, world: SyntheticWorld, osc: socket.socket
) -> tuple[list[dict[str, Any]], list[bytes]]:
    """Emulated trackers streaming to the daemon; meanwhile a WebSocket client's frames and the OSC bundles."""
    frames: list[dict[str, Any]] = []
    bundles: list[bytes] = []
    loop = asyncio.get_running_loop()
    async with emulated_trackers(world, time.monotonic_ns(), port):
        async with connect(ws_url, max_size=None) as ws:
            await ws.send(json.dumps({"type": "subscribe", "encoding": "json", "globals": True}))
            end = loop.time() + 120
            seen: set[str] = set()
            while loop.time() < end and (len(seen) < 2 or len(frames) < 300):
                raw = await asyncio.wait_for(ws.recv(), 10)
                if isinstance(raw, bytes):  # the first hello, msgpack, before the subscribe took effect
                    continue
                msg = json.loads(raw)
                if msg["type"] == "frame":
                    frames.append(msg)
                    seen |= {s["id"] for s in msg["subjects"] if s["imus"] >= 10}
        osc.setblocking(False)
        while len(bundles) < 60:  # a second of VRChat's stream (queued since the run began, at 60 Hz)
            bundles.append(await asyncio.wait_for(loop.sock_recv(osc, 65536), 5))
    return frames, bundles


def test_check_config_of_a_tracker_rig_names_what_is_still_missing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """SlimeVR trackers switched on, nothing assigned or calibrated yet: the rig is valid (run it to see the
    trackers), and check-config says what is missing with the command that gives it."""
    config = tmp_path / "trackers.toml"
    config.write_text(f'[imu]\ncalibration_dir = "{tmp_path}/cal"\n[imu.slimevr]\nenabled = true\n', encoding="utf-8")
    assert main(["check-config", str(config)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(f"{config}: ok (IMUs only (no cameras): SlimeVR server on udp 127.0.0.1:6969;"), out
    assert "[imu.slimevr.assignment] is empty" in out[1] and "imu.slimevr.trackers in /status" in out[1]
    assert f"run `mocapd calibrate imu --config {config} --person NAME --facing-heading 0`" in out[2]
    assert "north" not in out[2]  # trackers without a compass: their headings are reset at calibration
    # An Xsens suit's heading is the compass's: the note says that 0 is north, and what a wrong heading does.
    suit = tmp_path / "suit.toml"
    suit.write_text(f'[imu]\ncalibration_dir = "{tmp_path}/cal"\nports = ["/dev/xsens0"]\n', encoding="utf-8")
    assert main(["check-config", str(suit)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "[imu.assignment] is empty" in out[1] and "`mocapd devices` lists Xsens ids" in out[1]
    assert "stand still in a T-pose facing magnetic north and run `mocapd calibrate imu" in out[2]
    assert "--facing-from SENSOR:AXIS" in out[2] and "bends the knees sideways or backwards" in out[2]


def test_demo_imu_only_runs_a_simulated_suit_to_the_viewer_and_vrchat(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`mocapd demo --imu-only`, as the README has it, with a config that enables VRChat's OSC stream (and VMC and
    Rokoko: each stream enabled is said where it goes; only VRChat's was, so a VMC or Rokoko receiver listening on
    another port than the config's had nothing to go on)."""
    osc, vmc, rokoko = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3))
    for s in (osc, vmc, rokoko):
        s.bind(("127.0.0.1", 0))
        s.settimeout(10)
    port = {name: s.getsockname()[1] for name, s in (("osc", osc), ("vmc", vmc), ("rokoko", rokoko))}
    config = tmp_path / "vr.toml"
    config.write_text(
        f'[websocket]\nport = 0\n[udp.vrchat]\nenabled = true\ndestination = "127.0.0.1:{port["osc"]}"\n'
        f'[udp.vmc]\nenabled = true\ndestinations = ["127.0.0.1:{port["vmc"]}"]\n'
        f'[udp.rokoko]\nenabled = true\ndestinations = ["127.0.0.1:{port["rokoko"]}"]\n',
        encoding="utf-8",
    )
    try:
        assert main(["demo", "--imu-only", "--seconds", "4", "--http-port", "0", "--config", str(config),
                     "--record", str(tmp_path / "take")]) == 0  # fmt: skip
        bundle = osc.recv(65536)
        assert vmc.recv(65536) and rokoko.recv(65536)
    finally:
        for s in (osc, vmc, rokoko):
            s.close()
    out = capsys.readouterr().out
    assert "13 simulated Xsens IMUs on pseudo-terminals" in out and "viewer http://127.0.0.1:" in out, out
    assert f"VRChat OSC trackers to 127.0.0.1:{port['osc']}: the first subject\n" in out, out
    assert f"VMC (OSC) avatars to 127.0.0.1:{port['vmc']}: a subject per avatar\n" in out, out
    assert f"Rokoko Studio Live (lz4) to 127.0.0.1:{port['rokoko']}: every subject as actors\n" in out, out
    # and the session recorded: where, and what to type next (nothing said it, nor where [record] enabled put it)
    take = tmp_path / "take"
    assert f"recording the session to {take} (then `mocapd resolve {take}`, `mocapd export {take} --resolved" in out
    assert (take / "manifest.json").is_file()
    done = next(line for line in out.splitlines() if line.startswith("done: "))
    frames = int(done.split()[1])
    error_mm = float(done.split("median ")[1].split()[0])
    assert frames > 0 and error_mm < 80.0, done  # the suit poses the walker (roots put together)
    assert any(m.address == "/tracking/trackers/1/position" for m in OscBundle(bundle))


def test_run_of_an_imu_rig_without_a_calibrated_suit_says_why_no_pose_comes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`mocapd run` of a suit not yet calibrated streamed `people []` for as long as it ran, saying nothing of why
    (only `check-config` did): it now says what check-config says before it opens the devices."""
    config = tmp_path / "suit.toml"
    config.write_text(
        f'[imu]\nports = ["{tmp_path}/no-such-port"]\ncalibration_dir = "{tmp_path}/cal"\n'
        '[imu.assignment]\n"00B42279" = "Hips"\n[daemon]\nhttp_port = 0\n[websocket]\nport = 0\n',
        encoding="utf-8",
    )
    assert main(["run", "--config", str(config)]) == 2  # the port does not open: the start stops with its name
    said = capsys.readouterr()
    assert f"mocapd run: note: no suit is calibrated in {tmp_path}/cal/ yet, so no pose is streamed" in said.out
    assert f"`mocapd calibrate imu --config {config} --person NAME --facing-heading 0`" in said.out
    assert "no-such-port" in said.err
    assert "mocapd run: opening every device ...\n" in said.out  # no "loading models": no detector here


def test_check_config_names_a_stream_whose_suit_is_not_calibrated(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`[udp.vrchat] subject = "suit:alice"` with the suit calibrated as `bob` (or an actor name keyed by a typo):
    valid, and VRChat got no tracker with no word anywhere. check-config (and run) now say so."""
    world = SyntheticWorld(0, 1, 1, seed=3, motion="procedural")
    bob = replace(slimevr_calibration(world, world.suits[0]), person="bob")
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "bob.imu.json").write_text(json.dumps(bob.to_json_dict()), encoding="utf-8")
    config = tmp_path / "vr.toml"
    config.write_text(
        f'[imu]\ncalibration_dir = "{tmp_path}/cal"\n[imu.slimevr]\nenabled = true\n'
        '[udp.vrchat]\nenabled = true\nsubject = "suit:alice"\n'
        '[udp.rokoko]\nenabled = true\nactor_names = { "suit:bob" = "Bob", "suit:bbo" = "Bob 2" }\n',
        encoding="utf-8",
    )
    assert main(["check-config", str(config)]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if "not a calibrated suit" in line]
    assert notes == [
        f"{config}: note: [udp.vrchat] subject names 'suit:alice', which is not a calibrated suit of this rig "
        "(suits: suit:bob): that stream never gets its pose; name one of them, or calibrate it (`mocapd calibrate "
        "imu --person alice`)",
        f"{config}: note: [udp.rokoko] actor_names names 'suit:bbo', which is not a calibrated suit of this rig "
        "(suits: suit:bob): that stream never gets its pose; name one of them, or calibrate it (`mocapd calibrate "
        "imu --person bbo`)",
    ]


# When each of the 13 simulated devices' first sample reached the daemon (ms after the first could have), in the
# suit's sensor order (Hips, Spine3, Head, upper arms, forearms, thighs, shanks, feet): devices brought up one after
# another on a loaded machine. The first solve sees two arm sensors only.
_BRING_UP_MS = (135, 239, 69, 16, 121, 60, 27, 174, 90, 202, 60, 283, 110)


def test_a_suit_whose_sensors_come_up_one_by_one_is_posed_once_all_stream(tmp_path: Path) -> None:
    """The demo's suit (shipped solver, prior and latency) solved by the daemon's scheduler, its devices starting
    to stream over 0.3 s as they do under load: after a second of the whole suit the wearer is posed as well as
    when all start together. A solve that started from two arm sensors used to wind the joints no sensor fixes
    (spine, neck, hands, toes) by whole turns, where the pose prior no longer pulls, and kept that pose for good
    (the demo at 110-190 mm in about half of its runs at load 12)."""
    world = SyntheticWorld(0, 1, 1, seed=0, motion="recorded")
    suit = world.suits[0]
    calibration = replace(world.calibration(suit), person="suit0")
    (tmp_path / "suit0.imu.json").write_text(json.dumps(calibration.to_json_dict()), encoding="utf-8")
    config = suit_rig_config(load_config(), ("/dev/null",), dict(calibration.bones), tmp_path)
    body = {f"{k}_m": round(v, 3) for k, v in segment_lengths(world.skeleton).items()}
    config = config.model_copy(update={"imu": config.imu.model_copy(update={
        "body": config.imu.body.model_copy(update={"height_m": world.skeleton.height, **body})})})  # fmt: skip
    rig = build_rig(config, plan_rig(config)).rig
    ingest = ImuIngest()
    sched = FixedLatencyScheduler(
        [], rig.skeleton, rig.targets, PeopleTracker(SubjectTracker(DetectionSorter([])), None), prior=rig.prior,
        ingest=ingest, suits=rig.suits, options=config.daemon.scheduler_options([]), cost=config.solver.cost,
        lm=config.solver.lm.options(), backend=config.solver.backend,
    )  # fmt: skip
    q, a = world.imu_motion(suit, IMU_RATE_HZ)
    ids = [f"{s:08X}" for s in suit.sensor_ids]
    assert len(ids) == len(_BRING_UP_MS)
    s = 1_000_000_000
    k0 = 3 * IMU_RATE_HZ  # 3 s into the recorded walk
    period = s // round(config.daemon.output_rate_hz)
    tick = k0 * s // IMU_RATE_HZ + sched.latency_ns
    errors, imus = [], []
    for k in range(k0, k0 + 3 * IMU_RATE_HZ):
        t = k * s // IMU_RATE_HZ
        for j, sid in enumerate(ids):
            if t >= (k0 * s // IMU_RATE_HZ) + _BRING_UP_MS[j] * 1_000_000:
                ingest.add(sid, t, device_ticks=None, packet_counter=None, quat=tuple(q[j, k]), acc=tuple(a[j, k]))
        while tick <= t:
            frame = sched.tick(tick)
            for p in frame.people:
                truth = world.joints_at(0, frame.pose_time_ns(p) / 1e9)
                errors.append(float(np.linalg.norm((p.joints - p.joints[0]) - (truth - truth[0]), axis=1).mean()))
                imus.append(p.imus)
                assert np.all(np.linalg.norm(p.theta[3:].reshape(-1, 3), axis=1) <= np.pi + 1e-9)
            tick += period
    assert imus[0] < 13 and imus[-1] == 13, imus[:5]  # solved from the first sensors on, as the daemon does
    last = float(np.median(errors[-60:]))  # the last second
    assert last < 0.065, (last, errors[:: len(errors) // 10])  # 0.048 m when every device starts at once
