"""``[daemon]`` validation and ``mocapd check-config``: every bad key or value named with what is allowed."""

from __future__ import annotations

from pathlib import Path

import pytest

from mocapd.errors import ConfigError
from mocapd.service.cli import main
from mocapd.service.config import DEFAULT_CONFIG, load_config, parse_config


def test_shipped_config_is_valid_and_check_config_says_so(capsys: pytest.CaptureFixture[str]) -> None:
    cfg = load_config()
    assert cfg.daemon.output_rate_hz == 60.0 and cfg.daemon.http_host == "127.0.0.1"
    assert main(["check-config"]) == 0
    assert f"{DEFAULT_CONFIG}: ok" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        ("[daemon]\nlatncy_s = 0.1\n", "unknown key(s) ['latncy_s'] in [daemon]; allowed:"),
        ("[daemon]\nlatency_s = -1\n", "daemon.latency_s = -1; allowed: a number in [0, 2]"),
        ("[daemon]\noutput_rate_hz = true\n", "daemon.output_rate_hz = True; allowed: a number"),
        ("[daemon]\nhttp_port = 70000\n", "daemon.http_port = 70000; allowed: an integer in [0, 65535]"),
        ('[daemon]\nhttp_host = "0.0.0.0"\n', "allowed: a loopback address"),
        ('[daemon]\nrig = "cameras"\n', "daemon.rig = 'cameras'; allowed: ['synthetic']"),
        ("[daemon]\nrestart_min_s = 5.0\nrestart_max_s = 1.0\n", "must be >= daemon.restart_min_s"),
        ("[daemon.offsets]\ncameras = { cam1 = 3.0 }\n", "daemon.offsets.cameras.cam1 = 3.0; allowed:"),
        ("[daemon.offsets]\nclocks = {}\n", "unknown key(s) ['clocks'] in [daemon.offsets]"),
        ("[daemon.synthetic]\npeople = 1\nsuits = 2\n", "daemon.synthetic.suits = 2; allowed: at most"),
        ("[daemon.synthetic]\ncameras = 1.5\n", "daemon.synthetic.cameras = 1.5; allowed: an integer"),
        ("[deamon]\n", "unknown section(s) ['deamon']"),
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
    with pytest.raises(ConfigError, match=r"daemon.output = 'future'; allowed: \['delayed', 'predicted'\]"):
        parse_config({"daemon": {"output": "future"}})
    with pytest.raises(ConfigError, match=r"daemon\.heading_correction = 1; allowed: true or false"):
        parse_config({"daemon": {"heading_correction": 1}})
