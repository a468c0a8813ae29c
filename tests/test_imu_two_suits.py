"""Two suits from one config: ``[imu.assignment.<person>]`` tables, one suit each.

The config parser on both forms (flat: one suit, as before; per person: a suit each) and its refusals; then
``mocapd calibrate imu`` recording live from two simulated Xsens suits (the synthetic world's two suits, each sensor
a simulated device on its own pseudo-terminal): alice calibrated while bob's devices are not even plugged in, then
bob, and the daemon's :func:`~mocapd.service.suits.load_suits` finding the two suits with their own sensors.
"""

from __future__ import annotations

import asyncio
import json
import time
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from websockets.asyncio.client import connect

from mocapd.core.body_dims import segment_lengths
from mocapd.core.imu_calibration import ImuCalibration, heading_alignment
from mocapd.core.rotations import quat_angle, quat_conjugate, quat_multiply
from mocapd.errors import ConfigError
from mocapd.service.cli import main
from mocapd.service.config import config_document, load_config, parse_config
from mocapd.service.demo.imu_only import IMU_RATE_HZ
from mocapd.service.suits import load_suits
from mocapd.sim import xsens as xsens_sim
from mocapd.sim.suits import SimulatedSuits
from mocapd.sim.world import SuitTruth, SyntheticWorld
from tests.test_import_recordings import _write_exports
from tests.test_run_rig import RunProcess

ALICE = {"00B42000": "Hips", "00B42001": "Head", "00B42002": "LeftLowerLeg"}
BOB = {"00B4A000": "Hips", "00B4A001": "Head", "00B4A002": "LeftLowerLeg"}


def _toml(tables: dict[str, dict[str, str]], header: str = "imu.assignment") -> str:
    return "".join(
        f"[{header}.{person}]\n" + "".join(f'"{s}" = "{b}"\n' for s, b in table.items())
        for person, table in tables.items()
    )


def _imu(text: str) -> object:
    return parse_config(tomllib.loads(text)).imu


def test_the_flat_assignment_is_one_suit_as_before() -> None:
    imu = parse_config({"imu": {"assignment": {k.lower(): v for k, v in ALICE.items()}}}).imu
    assert imu.assignment == ALICE and imu.sensors == ALICE and imu.persons == {}
    assert imu.suit_sensors("anyone") == ALICE  # the flat form calibrates every sensor under any name
    with pytest.raises(ConfigError, match="bone Hips has more than one sensor"):
        parse_config({"imu": {"assignment": {**ALICE, **BOB}}})  # two suits cannot be flat


def test_one_table_per_person_is_a_suit_each() -> None:
    imu = parse_config(tomllib.loads("[imu]\n" + _toml({"alice": ALICE, "bob": BOB}))).imu
    assert imu.persons == {"alice": ALICE, "bob": BOB}
    assert imu.sensors == {**ALICE, **BOB}  # the daemon opens and keeps every person's sensors
    assert imu.suit_sensors("bob") == BOB
    with pytest.raises(ConfigError, match=r"--person 'carol' has no table in \[imu.assignment\].*alice, bob$"):
        imu.suit_sensors("carol")
    # a session records the tables, and reads them back
    cfg = parse_config(tomllib.loads("[imu]\n" + _toml({"alice": ALICE, "bob": BOB})))
    assert parse_config(json.loads(json.dumps(config_document(cfg)))) == cfg
    # imu_set is checked per person: each table a 6-sensor set, two Hips in all
    six = ["Hips", "Head", "LeftLowerArm", "RightLowerArm", "LeftLowerLeg", "RightLowerLeg"]
    tables = {p: {f"00B4{k:02X}{i:02X}": b for i, b in enumerate(six)} for k, p in enumerate(("alice", "bob"))}
    assert set(parse_config(tomllib.loads('[imu]\nimu_set = "6"\n' + _toml(tables))).imu.persons) == {"alice", "bob"}
    # SlimeVR trackers join their person's suit
    slime = {"bob": {"AA:BB:CC:DD:EE:FF/0": "RightLowerLeg"}}
    imu = parse_config(
        tomllib.loads("[imu]\n" + _toml({"alice": ALICE, "bob": BOB}) + _toml(slime, "imu.slimevr.assignment"))
    ).imu
    assert imu.persons["bob"] == {**BOB, "AA:BB:CC:DD:EE:FF/0": "RightLowerLeg"} and imu.persons["alice"] == ALICE


@pytest.mark.parametrize(
    ("text", "says"),
    [
        # a sensor entry beside per-person tables: named, with the key
        ('[imu.assignment]\n"00B42000" = "Hips"\n[imu.assignment.bob]\n"00B4A000" = "Hips"\n',
         r"imu.assignment = .*'00B42000' = 'Hips' is a sensor entry beside per-person tables \(bob\)"),
        # a sensor in two persons' tables: both named
        (_toml({"alice": ALICE, "bob": {**BOB, "00B42001": "Spine3"}}),
         r"imu.assignment = .*sensor 00B42001 is in the tables of both alice and bob"),
        # a person's table is one suit
        (_toml({"alice": {**ALICE, "00B42009": "Hips"}, "bob": BOB}),
         r"imu.assignment = .*alice's table: bone Hips has more than one sensor"),
        (_toml({"alice": {"00B42000": "Pelvis"}}), r"alice's table: 00B42000 -> 'Pelvis' is not a bone"),
        # person names as --person takes them
        ('[imu.assignment."../etc"]\n"00B42000" = "Hips"\n', r"person '../etc': allowed: 1 to 32 letters"),
        ('[imu.assignment."a b"]\n"00B42000" = "Hips"\n', r"person 'a b': allowed"),
        # imu_set per person, naming whose table
        ('[imu]\nimu_set = "6"\n' + _toml({"alice": ALICE, "bob": BOB}),
         r"imu.assignment = .* \(alice's table\) does not form imu.imu_set = '6'"),
        # a flat table beside a per-person one, across the two transports
        (_toml({"bob": BOB}) + '[imu.slimevr.assignment]\n"AA:BB:CC:DD:EE:FF/0" = "Hips"\n',
         r"imu.assignment = .* and imu.slimevr.assignment = .*: one is written per person and the other is not"),
        # one person's Xsens and SlimeVR tables are one suit
        (_toml({"bob": BOB}) + _toml({"bob": {"AA:BB:CC:DD:EE:FF/0": "Hips"}}, "imu.slimevr.assignment"),
         r"bob's tables: bone Hips has more than one sensor"),
        (_toml({"bob": BOB}) + _toml({"bob": {"00B4A009": "Spine"}}, "imu.slimevr.assignment"),
         r"imu.slimevr.assignment = .*\['00B4A009'\] are Xsens ids"),
    ],
)  # fmt: skip
def test_per_person_tables_refuse_what_is_not_a_suit_each(text: str, says: str) -> None:
    with pytest.raises(ConfigError, match=says) as err:
        parse_config(tomllib.loads(text if text.startswith("[imu]") else "[imu]\n" + text))
    assert "\n" not in str(err.value)


def _still_suit(world: SyntheticWorld, suit: SuitTruth, folder: Path, heading: float) -> list[xsens_sim.XsensSimulator]:
    """The suit's sensors held still in the T-pose facing ``heading``, each a device on a pseudo-terminal (not yet
    plugged in): R_i = R_ig⁻¹ · R_ib, every bone's world rotation the identity."""
    q_gi = quat_conjugate(heading_alignment(heading))
    return [
        xsens_sim.XsensSimulator(
            folder / f"imu-{sid:08X}",
            xsens_sim.SimDevice(xsens_sim.still_motion(quat_multiply(q_gi, q_ib), device_id=sid)),
        )
        for sid, q_ib in zip(suit.sensor_ids, suit.q_ib, strict=True)
    ]


def test_calibrate_imu_calibrates_each_persons_suit_of_one_config(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    heading = 30.0
    world = SyntheticWorld(0, 2, n_suits=2, motion="procedural")
    persons = dict(zip(("alice", "bob"), world.suits, strict=True))
    tables = {
        p: {f"{sid:08X}": m.bone for sid, m in zip(s.sensor_ids, s.mounts, strict=True)} for p, s in persons.items()
    }
    assert not set(tables["alice"]) & set(tables["bob"]) and len(tables["bob"]) == 13
    sims = {p: _still_suit(world, s, tmp_path, heading) for p, s in persons.items()}
    ports = ", ".join(json.dumps(str(sim.link)) for p in persons for sim in sims[p])
    config = tmp_path / "rig.toml"
    config.write_text(
        f'[imu]\nports = [{ports}]\nimu_set = "13"\ncalibration_dir = "cal"\n'
        "reconnect_min_s = 0.2\nreconnect_max_s = 0.5\n" + _toml(tables),
        encoding="utf-8",
    )
    # The simulated suits' mountings are random, not cases along their segments: the T-pose is held exactly.
    calibrate = ["calibrate", "imu", "--config", str(config), "--facing-heading", str(heading), "--seconds", "0.5",
                 "--window", "0.3", "--connect-timeout", "20", "--pose-exact"]  # fmt: skip
    assert main([*calibrate, "--person", "carol"]) == 1  # (a ConfigError here used to be said as a bad --window)
    said = capsys.readouterr().out
    assert said.strip() == (
        "mocapd calibrate imu: --person 'carol' has no table in [imu.assignment]: the assignment is per person, "
        "with tables for alice, bob"
    ), said
    # alice's suit on, bob's devices not plugged in yet: alice's recording waits for her sensors only
    loops = [xsens_sim.SimulatorLoop(sims["alice"]).start()]
    try:
        assert main([*calibrate, "--person", "alice"]) == 0, capsys.readouterr().out
        said = capsys.readouterr().out
        assert f"wrote {tmp_path / 'cal' / 'alice.imu.json'}" in said and "00B4A000" not in said, said
        assert main(["check-config", str(config)]) == 0
        said = capsys.readouterr().out
        assert "26 sensor(s) assigned to 2 persons (alice, bob)" in said, said
        assert f"suits calibrated in {tmp_path}/cal/: alice (13 sensors)" in said, said
        assert f"bob (13 sensors assigned) has no calibration in {tmp_path}/cal/ yet" in said, said
        command = f"`mocapd calibrate imu --config {config} --person bob --facing-heading 0`"
        assert f"stand bob still in a T-pose facing magnetic north and run {command}" in said, said
        assert "alice (13 sensors assigned)" not in said, said
        loops.append(xsens_sim.SimulatorLoop(sims["bob"]).start())
        assert main([*calibrate, "--person", "bob"]) == 0, capsys.readouterr().out
    finally:
        for loop in loops:
            loop.stop()
    capsys.readouterr()
    assert main(["check-config", str(config)]) == 0
    said = capsys.readouterr().out
    assert (
        f"suits calibrated in {tmp_path}/cal/: alice (13 sensors), bob (13 sensors)" in said
        and "no calibration" not in said
    )

    cfg = load_config(config)
    suits = load_suits(cfg.imu, world.skeleton, base=tmp_path)
    assert [s.id for s in suits] == ["alice", "bob"]
    for suit in suits:
        truth = persons[suit.id]
        assert dict(suit.calibration.bones) == tables[suit.id]
        assert suit.calibration.facing_heading_deg == pytest.approx(heading, abs=1e-3)
        for sid, q_ib in zip(truth.sensor_ids, truth.q_ib, strict=True):
            assert quat_angle(suit.calibration.q_ib[f"{sid:08X}"], q_ib) < 1e-4


def test_check_config_names_a_persons_calibration_of_other_sensors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    world = SyntheticWorld(0, 2, n_suits=2, motion="procedural")
    (tmp_path / "cal").mkdir()
    calibration = replace(world.calibration(world.suits[0]), person="alice")
    (tmp_path / "cal" / "alice.imu.json").write_text(json.dumps(calibration.to_json_dict()), encoding="utf-8")
    theirs = world.calibration(world.suits[1]).bones  # alice's table names the other suit's sensors
    config = tmp_path / "rig.toml"
    config.write_text(f'[imu]\nports = ["/dev/xsens0"]\ncalibration_dir = "cal"\n{_toml({"alice": dict(theirs)})}')
    assert main(["check-config", str(config)]) == 0
    said = capsys.readouterr().out
    assert f"alice's calibration in {tmp_path}/cal/ is of other sensors than their table (00B42000 Hips, " in said
    assert (
        f"calibrate them again with `mocapd calibrate imu --config {config} --person alice --facing-heading 0`" in said
    )


def test_calibrate_from_a_session_with_per_person_tables_takes_the_suits_table(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A session records its config; where that has one table per person, ``calibrate imu --from`` calibrates the
    suit's table (``--suit``, else the import's suit or ``--person``). The take is an imported lower-body suit
    (``suit0``) whose recorded config is then written as two persons' tables, as a two-suit rig records it."""
    assignment, _, _ = _write_exports(tmp_path, seconds=0.0)  # standing only
    session = tmp_path / "take"
    files = sorted(str(p) for p in tmp_path.glob("MT_*.txt"))
    assign = [a for sid, bone in assignment.items() for a in ("--assign", f"{sid}={bone}")]
    assert main(["import", "mtw", *files, "-o", str(session), *assign]) == 0
    manifest_path = session / "manifest.json"
    manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
    manifest["config"]["imu"]["assignment"] = {"suit0": assignment, "bob": BOB}
    manifest_path.write_text(json.dumps(manifest), encoding="utf-8")
    capsys.readouterr()
    base = ["calibrate", "imu", "--from", str(session), "--facing-heading", "0", "--out", str(tmp_path / "c.json")]
    assert main([*base, "--suit", "carol"]) == 1
    err = capsys.readouterr().err
    assert f"{session}: its [imu.assignment] has one table per person, none for 'carol': name one of suit0, bob" in err
    assert main(base) == 0, capsys.readouterr().err  # the import's suit, suit0: its table
    calib = ImuCalibration.from_json_dict(json.loads((tmp_path / "c.json").read_text(encoding="utf-8")))
    assert calib.person == "suit0" and dict(calib.bones) == assignment
    assert json.loads(capsys.readouterr().out)["suit"] == "suit0"


def test_two_xsens_suits_stream_from_one_run_and_its_session_resolves(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``mocapd run`` of two performers each in a 13-sensor Xsens suit (26 simulated devices on pseudo-terminals,
    walking recorded motion): both suits stream to a WebSocket client and follow their wearer; the recorded session
    keeps the per-person tables and ``mocapd resolve`` solves both suits from it."""
    world = SyntheticWorld(0, 2, n_suits=2, seed=0)
    folder = tmp_path / "cal"
    folder.mkdir()
    tables, index = {}, {}
    for person, suit in zip(("alice", "bob"), world.suits, strict=True):
        calibration = replace(world.calibration(suit), person=person)
        (folder / f"{person}.imu.json").write_text(json.dumps(calibration.to_json_dict()), encoding="utf-8")
        tables[person], index[f"suit:{person}"] = dict(calibration.bones), suit.person
    body = "".join(f"{k}_m = {v:.3f}\n" for k, v in segment_lengths(world.skeleton).items())
    epoch = time.monotonic_ns()
    sims = SimulatedSuits.start(world, IMU_RATE_HZ, epoch)
    config = tmp_path / "rig.toml"
    config.write_text(
        f"[imu]\nports = [{', '.join(json.dumps(p) for p in sims.ports)}]\nrate_hz = {IMU_RATE_HZ}\n"
        f'imu_set = "13"\ncalibration_dir = "cal"\nreconnect_min_s = 0.2\nreconnect_max_s = 1.0\n'
        f"stall_timeout_s = 1.0\n" + _toml(tables) + "[imu.body]\n" + body
        + "[daemon]\nhttp_port = 0\n[websocket]\nport = 0\n",
        encoding="utf-8",
    )  # fmt: skip
    session = tmp_path / "take"
    run = RunProcess(["--config", str(config), "--record", str(session)], cwd=tmp_path)
    try:
        run.url(300)
        ws_url = next(line.split()[-1] for line in run.lines if line.startswith("viewer "))
        frames = asyncio.run(_frames(ws_url))
        code, _ = run.interrupt()
    finally:
        run.close()
        sims.close()
    assert code == 0 and "Traceback" not in run.output, run.output[-4000:]
    assert "26 sensor(s) assigned to 2 persons (alice, bob)" in run.output, run.output[:2000]
    by_id: dict[str, list[dict[str, Any]]] = {}
    for f in frames:
        for s in f["subjects"]:
            by_id.setdefault(s["id"], []).append(s)
    assert set(by_id) == {"suit:alice", "suit:bob"}, sorted(by_id)
    for name, subject in by_id.items():  # each suit follows its own wearer (roots put together)
        assert max(s["imus"] for s in subject) == 13
        errors = []
        for s in subject[-60:]:
            truth = world.joints_at(index[name], (s["t_pose_ns"] - epoch) / 1e9)
            joints = np.array(s["joints"]).reshape(21, 3)
            errors.append(np.linalg.norm((joints - joints[0]) - (truth - truth[0]), axis=1).mean())
        assert float(np.median(errors)) < 0.08, (name, np.median(errors))

    manifest = json.loads((session / "manifest.json").read_text(encoding="utf-8"))
    assert manifest["config"]["imu"]["assignment"] == tables
    capsys.readouterr()
    assert main(["resolve", str(session), "--iterations", "3"]) == 0, capsys.readouterr()
    summary = json.loads(capsys.readouterr().out)
    assert set(summary["plausibility"]) == {"suit:alice", "suit:bob"}, summary
    assert summary["person_solves"] >= 2 * summary["frames"] - 4 and summary["frames"] > 60, summary  # both, each frame


async def _frames(ws_url: str) -> list[dict[str, Any]]:
    """A WebSocket client's frames until both suits streamed 120 frames with their IMUs (at most 60 s)."""
    frames: list[dict[str, Any]] = []
    count = {"suit:alice": 0, "suit:bob": 0}
    loop = asyncio.get_running_loop()
    async with connect(ws_url, max_size=None) as ws:
        await ws.send(json.dumps({"type": "subscribe", "encoding": "json", "globals": True}))
        end = loop.time() + 60
        while loop.time() < end and min(count.values()) < 120:
            raw = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(raw, bytes):  # the first hello, msgpack, before the subscribe took effect
                continue
            msg = json.loads(raw)
            if msg["type"] == "frame":
                frames.append(msg)
                for s in msg["subjects"]:
                    count[s["id"]] = count.get(s["id"], 0) + (s["imus"] >= 10)
    return frames
