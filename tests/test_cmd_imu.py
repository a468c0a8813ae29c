"""``mocapd calibrate imu`` end to end against simulated devices on ptys, and the [imu] config parser."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.imu_calibration import ImuCalibration, bone_orientation, heading_alignment
from mocapd.core.rotations import quat_angle, quat_conjugate, quat_from_rotvec, quat_multiply, random_quat
from mocapd.errors import ConfigError
from mocapd.service.cli import main
from mocapd.service.config import DEFAULT_CONFIG, load_config, parse_config
from mocapd.service.config.imu import ImuConfig
from mocapd.sim import xsens as xsens_sim

REPO = Path(__file__).resolve().parents[1]


def test_calibrate_imu_writes_a_calibration_that_reproduces_the_tpose(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rng = np.random.default_rng(5)
    heading = 200.0
    bones = {"00B40011": "Hips", "00B40012": "LeftLowerArm"}
    mountings = {sid: random_quat(rng) for sid in bones}
    # The sensors' orientations while the subject stands in the T-pose: R_i = R_ig^-1 · R_ib.
    q_ig = heading_alignment(heading)
    sims = [
        xsens_sim.XsensSimulator(
            tmp_path / f"imu{k}",
            xsens_sim.SimDevice(
                xsens_sim.still_motion(quat_multiply(quat_conjugate(q_ig), mountings[sid]), device_id=int(sid, 16))
            ),
        ).start()
        for k, sid in enumerate(bones)
    ]
    config = tmp_path / "config.toml"
    ports = ", ".join(f'"{s.link}"' for s in sims)
    assignment = "\n".join(f'"{sid}" = "{bone}"' for sid, bone in bones.items())
    config.write_text(f"[imu]\nports = [{ports}]\nrate_hz = 100\n\n[imu.assignment]\n{assignment}\n")
    out = tmp_path / "calib" / "alice.imu.json"
    try:
        # Random mountings, not cases along their segments: the T-pose is held exactly (--pose-exact).
        args = ["calibrate", "imu", "--config", str(config), "--person", "alice", "--pose-exact"]
        status = main(
            [
                *args,
                "--facing-heading",
                str(heading),
                "--seconds",
                "0.8",
                "--window",
                "0.5",
                "--out",
                str(out),
            ]
        )
    finally:
        for s in sims:
            s.stop()
    printed = capsys.readouterr().out
    assert status == 0, printed
    assert "wrote" in printed and "LeftLowerArm" in printed
    calib = ImuCalibration.from_json_dict(json.loads(out.read_text()))
    assert calib.person == "alice" and calib.bones == bones
    for sid in bones:
        assert quat_angle(calib.q_ib[sid], mountings[sid]) < 1e-5
        q_i = quat_multiply(quat_conjugate(q_ig), mountings[sid])
        assert quat_angle(bone_orientation(calib.q_ig, q_i, calib.q_ib[sid]), np.array([1.0, 0, 0, 0])) < 1e-5


def test_facing_heading_from_a_sensor_axis(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # The pelvis sensor's -z axis points forward; the subject faces 75° (east-north-east).
    heading = 75.0
    q_ig = heading_alignment(heading)
    # Mounting: sensor -z along the bone's forward (+Z world in the T-pose), i.e. a half turn about y.
    q_ib = quat_from_rotvec(np.array([0.0, np.pi, 0.0]))
    q_i = quat_multiply(quat_conjugate(q_ig), q_ib)
    sim = xsens_sim.XsensSimulator(
        tmp_path / "imu0", xsens_sim.SimDevice(xsens_sim.still_motion(q_i, device_id=0x00B40011))
    ).start()
    config = tmp_path / "config.toml"
    config.write_text(f'[imu]\nports = ["{sim.link}"]\n[imu.assignment]\n"00B40011" = "Hips"\n')
    out = tmp_path / "bob.imu.json"
    try:
        args = [
            "calibrate",
            "imu",
            "--config",
            str(config),
            "--person",
            "bob",
            "--facing-from",
            "00b40011:-z",
        ]
        status = main([*args, "--seconds", "0.5", "--window", "0.3", "--out", str(out)])
    finally:
        sim.stop()
    assert status == 0, capsys.readouterr().out
    calib = ImuCalibration.from_json_dict(json.loads(out.read_text()))
    assert calib.facing_heading_deg == pytest.approx(heading, abs=1e-3)
    assert quat_angle(calib.q_ib["00B40011"], q_ib) < 1e-5
    bad = main(["calibrate", "imu", "--config", str(config), "--person", "x", "--facing-from", "00B40011:w"])
    assert bad == 1


def test_calibrate_imu_reports_missing_sensors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "config.toml"
    config.write_text(f'[imu]\nports = ["{tmp_path / "absent"}"]\n[imu.assignment]\n"00B40011" = "Hips"\n')
    args = ["calibrate", "imu", "--config", str(config), "--person", "x", "--facing-heading", "0"]
    status = main([*args, "--connect-timeout", "0.3"])
    printed = capsys.readouterr().out
    assert status == 1
    assert "['00B40011'] sent nothing" in printed and "cannot open serial port" in printed


def test_shipped_config_parses() -> None:
    cfg = load_config(DEFAULT_CONFIG).imu
    assert cfg.ports == () and not cfg.bridge.enabled and not cfg.awinda.experimental


def test_config_errors_name_the_key() -> None:
    with pytest.raises(ConfigError, match=r"unknown key imu.rate; allowed: assignment, attempts, awinda"):
        imu({"rate": 100})
    with pytest.raises(ConfigError, match=r"imu.rate_hz = 200; allowed: an integer in \[60, 120\]"):
        imu({"rate_hz": 200})
    with pytest.raises(
        ConfigError, match=r"imu.bridge.host = '0.0.0.0'; allowed: \"127.0.0.1\", \"::1\" or \"localhost\""
    ):
        imu({"bridge": {"enabled": True, "host": "0.0.0.0"}})
    with pytest.raises(ConfigError, match=r"unknown key imu.awinda.scale; allowed: delta_q_scale"):
        imu({"awinda": {"scale": 1}})
    with pytest.raises(ConfigError, match=r"imu\.ports = '/dev/ttyUSB0'; allowed: an array of at most 64 items"):
        imu({"ports": "/dev/ttyUSB0"})
    with pytest.raises(
        ConfigError, match=r"imu.assignment = \{'00B40011': 'Pelvis'\}: 00B40011 -> 'Pelvis' is not a bone"
    ):
        imu({"assignment": {"00B40011": "Pelvis"}})
    cfg = imu({"ports": ["/dev/a", "/dev/b"], "rate_hz": 120, "attempts": 5})
    ports = cfg.port_configs()
    assert [p.path for p in ports] == ["/dev/a", "/dev/b"] and ports[1].attempts == 5 and ports[0].rate_hz == 120


def imu(table: dict[str, object]) -> ImuConfig:
    return parse_config({"imu": table}).imu
