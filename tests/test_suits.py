"""Suits loaded from the calibration files ``mocapd calibrate imu`` writes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mocapd.errors import ConfigError
from mocapd.service.config.imu import ImuConfig
from mocapd.service.suits import load_suits
from mocapd.sim.world import SyntheticWorld
from tests.rigs import synthetic_toml, video_rig_toml, write


def _write(folder: Path, world: SyntheticWorld, suit: int, person: str | None = None) -> Path:
    data = world.calibration(world.suits[suit]).to_json_dict()
    if person is not None:
        data["person"] = person
    path = folder / f"{data['person']}.imu.json"
    path.write_text(json.dumps(data), encoding="utf-8")
    return path


def test_every_calibration_file_is_a_suit(tmp_path: Path) -> None:
    world = SyntheticWorld(n_cams=2, n_people=2, n_suits=2, motion="procedural")
    for k in range(2):
        _write(tmp_path, world, k)
    suits = load_suits(ImuConfig(calibration_dir=str(tmp_path)), world.skeleton)
    assert [s.id for s in suits] == ["suit0", "suit1"]
    truth = world.suits[1]
    ids = [f"{s:08X}" for s in truth.sensor_ids]
    assert set(suits[1].sensors) == set(ids)
    for sid, q in zip(ids, truth.q_ib, strict=True):
        np.testing.assert_allclose(suits[1].calibration.q_ib[sid], q, atol=1e-12)
    # Mount bones follow the calibration's sensor -> bone map.
    assert [m.bone for m in suits[1].mounts] == [suits[1].calibration.bones[s] for s in suits[1].sensors]


def test_no_directory_means_no_suits(tmp_path: Path) -> None:
    world = SyntheticWorld(n_cams=2, n_people=1, n_suits=0, motion="procedural")
    assert load_suits(ImuConfig(calibration_dir=str(tmp_path / "absent")), world.skeleton) == []
    # Relative paths resolve from the base given.
    assert load_suits(ImuConfig(calibration_dir="absent"), world.skeleton, base=tmp_path) == []


def test_a_configs_suits_are_found_beside_it_from_any_working_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A relative ``calibration_dir`` is the config file's folder's, as the rig's other files are: ``mocapd run
    --config ~/mocap/suit.toml`` started elsewhere (a service runs in /) found no suit and streamed nothing."""
    from mocapd.service.config import load_config

    world = SyntheticWorld(n_cams=2, n_people=1, n_suits=1, motion="procedural")
    (tmp_path / "mocap" / "cal").mkdir(parents=True)
    _write(tmp_path / "mocap" / "cal", world, 0)
    cfg = write(tmp_path / "mocap" / "suit.toml", '[imu]\ncalibration_dir = "cal"\n')
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    imu = load_config(cfg).imu
    assert imu.calibration_dir == str(tmp_path / "mocap" / "cal")
    assert [s.id for s in load_suits(imu, world.skeleton)] == ["suit0"]
    assert load_config().imu.calibration_dir == "calibration"  # no --config: where mocapd is run


def test_bad_files_are_errors_naming_the_file(tmp_path: Path) -> None:
    world = SyntheticWorld(n_cams=2, n_people=1, n_suits=1, motion="procedural")
    cfg = ImuConfig(calibration_dir=str(tmp_path))
    bad = tmp_path / "broken.imu.json"
    bad.write_text("{not json", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"broken\.imu\.json"):
        load_suits(cfg, world.skeleton)
    bad.write_text(json.dumps({"format": "something else"}), encoding="utf-8")
    with pytest.raises(ConfigError, match=r"broken\.imu\.json.*version-1"):
        load_suits(cfg, world.skeleton)
    bad.unlink()
    _write(tmp_path, world, 0)
    _write(tmp_path, world, 0, person="other")  # the same sensors in a second suit
    with pytest.raises(ConfigError, match=r"suit0\.imu\.json: sensor 00B42000 is already in suit 'other'"):
        load_suits(cfg, world.skeleton)


def test_run_refuses_to_start_with_a_broken_calibration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from mocapd.service.cli import main

    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "anna.imu.json").write_text("[]", encoding="utf-8")
    cfg = write(tmp_path / "config.toml", video_rig_toml(f'[imu]\ncalibration_dir = "{tmp_path / "cal"}"\n'))
    assert main(["check-config", str(cfg)]) == 2
    assert "anna.imu.json" in capsys.readouterr().err
    assert main(["run", "--config", str(cfg), "--http-port", "0"]) == 2
    assert "anna.imu.json" in capsys.readouterr().err


def test_run_into_an_existing_session_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Recording over a session would destroy a take: the run refuses, names the file, exits 2, no traceback."""
    from mocapd.service.cli import main

    session = tmp_path / "take1"
    session.mkdir()
    (session / "poses.mcs").write_bytes(b"")
    cfg = write(tmp_path / "config.toml", synthetic_toml())  # on free ports: 8766 may be in use
    assert main(["run", "--config", str(cfg), "--http-port", "0", "--record", str(session)]) == 2
    err = capsys.readouterr().err
    assert "exists already" in err and "Traceback" not in err
