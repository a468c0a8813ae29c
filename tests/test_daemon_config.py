"""``[daemon]`` validation and ``mocapd check-config``: every bad key or value named with what is allowed."""

from __future__ import annotations

from pathlib import Path

import pytest

from mocapd.errors import ConfigError
from mocapd.service.cli import main
from mocapd.service.config import DEFAULT_CONFIG, load_config, parse_config
from tests.rigs import synthetic_toml, write


def test_shipped_config_is_valid_and_check_config_says_it_describes_no_rig(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = load_config()
    assert cfg.daemon.output_rate_hz == 60.0 and cfg.daemon.http_host == "127.0.0.1" and cfg.cameras == ()
    # Valid, and it describes no rig on purpose: check-config with no file says both, exit 0 (issue 32) ...
    assert main(["check-config"]) == 0
    out = capsys.readouterr()
    assert out.err == ""
    assert out.out.startswith(f"{DEFAULT_CONFIG}: ok: the shipped config is valid and describes no rig")
    # ... while `mocapd run` on it says what is missing, before starting anything.
    assert main(["run"]) == 2
    assert f"{DEFAULT_CONFIG}: error: no cameras and no IMU source: add [[cameras]] tables or an IMU source" in (
        capsys.readouterr().err
    )
    # A file of the user's without cameras or IMUs is a rig that is not there: exit 2.
    empty = write(tmp_path / "empty.toml", "[daemon]\nhttp_port = 0\n")
    assert main(["check-config", str(empty)]) == 2
    assert f"{empty}: error: no cameras and no IMU source" in capsys.readouterr().err
    config = write(tmp_path / "synthetic.toml", synthetic_toml())
    assert main(["check-config", str(config)]) == 0
    assert f"{config}: ok (4 camera(s): cam0 (synthetic simulated);" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        (
            "[daemon]\nlatncy_s = 0.1\n",
            "unknown key daemon.latncy_s; allowed: body_size_first_s, body_size_s, capture_nice, detector_nice,",
        ),
        ("[daemon]\nlatency_s = -1\n", "daemon.latency_s = -1; allowed: a number in [0, 2]"),
        ("[daemon]\noutput_rate_hz = true\n", "daemon.output_rate_hz = true; allowed: a number in [1, 500]"),
        ("[daemon]\nhttp_port = 70000\n", "daemon.http_port = 70000; allowed: an integer in [0, 65535]"),
        (
            '[daemon]\nhttp_host = "0.0.0.0"\n',
            'daemon.http_host = \'0.0.0.0\'; allowed: "127.0.0.1", "::1" or "localhost"',
        ),
        ('[daemon]\nrig = "synthetic"\n', "unknown key daemon.rig; allowed:"),
        (
            "[daemon]\nrestart_min_s = 5.0\nrestart_max_s = 1.0\n",
            "daemon.restart_min_s = 5.0 must be <= daemon.restart_max_s = 1.0",
        ),
        (
            "[daemon.offsets]\ncameras = { cam1 = 3.0 }\n",
            "daemon.offsets.cameras.cam1 = 3.0; allowed: a number in [-1, 1]",
        ),
        ("[daemon.offsets]\nclocks = {}\n", "unknown key daemon.offsets.clocks; allowed: cameras, imus"),
        ("[synthetic]\npeople = 1\nsuits = 2\n", "synthetic.suits = 2 must be <= synthetic.people = 1"),
        ("[synthetic]\npeople = 1.5\n", "synthetic.people = 1.5; allowed: an integer in [1, 4]"),
        ("[deamon]\n", "unknown section deamon; allowed:"),
    ],
)
def test_bad_daemon_config_is_rejected_with_a_clear_message(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], toml: str, message: str
) -> None:
    path = tmp_path / "config.toml"
    path.write_text(toml)
    assert main(["check-config", str(path)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.startswith(f"{path}: error:")


def test_offsets_for_unknown_cameras_are_rejected_when_the_rig_is_known() -> None:
    cfg = parse_config({"daemon": {"offsets": {"cameras": {"cam9": 0.01}, "imus": {"00b421e6": -0.004}}}})
    assert cfg.daemon.imu_offsets_s == {"00B421E6": -0.004}
    with pytest.raises(ConfigError, match=r"unknown camera\(s\) \['cam9'\]"):
        cfg.daemon.scheduler_options(["cam0", "cam1"])
    opts = parse_config({"daemon": {"offsets": {"cameras": {"cam1": 0.012}}}}).daemon.scheduler_options(
        ["cam0", "cam1"]
    )
    assert opts.camera_offsets_ns == (0, 12_000_000)


def test_missing_and_malformed_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-config", str(tmp_path / "absent.toml")]) == 2
    assert "config file not found" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text("[daemon\n")
    assert main(["check-config", str(bad)]) == 2
    assert "not valid TOML" in capsys.readouterr().err


def test_output_mode_and_heading_correction() -> None:
    opts = parse_config({"daemon": {"output": "predicted", "heading_correction": False}}).daemon.scheduler_options([])
    assert opts.prediction.predicted and not opts.heading.enabled
    shipped = load_config().daemon.scheduler_options([])
    assert shipped.prediction.output == "delayed" and shipped.heading.enabled
    with pytest.raises(ConfigError, match=r'daemon.output = .future.; allowed: "delayed" or "predicted"'):
        parse_config({"daemon": {"output": "future"}})
    with pytest.raises(ConfigError, match=r"daemon\.heading_correction = 1; allowed: true or false"):
        parse_config({"daemon": {"heading_correction": 1}})
