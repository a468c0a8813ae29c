"""Broken config files and hostile values: ``check-config`` and ``run`` answer with one line and exit 2.

Regressions of issue 18 (D5: a non-UTF-8 byte, a binary file, a directory gave a traceback; D6: a buffer of 2**63
samples was accepted; D7: nan was accepted) and of the values issue 19 found accepted.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import pytest

from mocapd.service.cli import main
from mocapd.service.config import DEFAULT_CONFIG

SHIPPED = DEFAULT_CONFIG.read_bytes()


def _line_of(needle: bytes) -> int:
    return SHIPPED[: SHIPPED.index(needle)].count(b"\n") + 1


def _non_utf8(p: Path) -> None:
    p.write_bytes(SHIPPED.replace(b'calibration_dir = "calibration"', b'calibration_dir = "calibr\xe9tion"'))


def _binary(p: Path) -> None:
    p.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + bytes(range(256)))


def _binary_without_nul(p: Path) -> None:
    p.write_bytes(bytes(range(128, 256)) * 4)


def _directory(p: Path) -> None:
    p.mkdir()


def _fifo(p: Path) -> None:
    os.mkfifo(p)  # opening it would wait for a writer forever


def _huge(p: Path) -> None:
    p.write_bytes(SHIPPED + b"#" * (2 << 20))


def _deep(p: Path) -> None:
    p.write_bytes(b"x = " + b"[" * 100_000 + b"]" * 100_000 + b"\n")


FILES: list[tuple[Callable[[Path], None], str]] = [
    (
        _non_utf8,
        f"line {_line_of(b'calibration_dir =')}, column 26: byte 0xe9 is not UTF-8 (TOML files are UTF-8 "
        "text), after 'calibration_dir = \"calibr'",
    ),
    (_binary, "a binary file, not TOML text (a NUL byte at line 3, column 1)"),
    (_binary_without_nul, "line 1, column 1: byte 0x80 is not UTF-8"),
    (_directory, "is a directory, not a config file"),
    (_fifo, "not a regular file (a device, pipe or socket)"),
    (_huge, "larger than 1024 KiB"),
    (_deep, "not valid TOML: arrays or tables nested too deeply"),
]


@pytest.mark.parametrize("command", ["check-config", "run"])
@pytest.mark.parametrize(("make", "problem"), FILES, ids=[f.__name__.strip("_") for f, _ in FILES])
def test_a_file_that_is_no_config_is_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str, make: Callable[[Path], None], problem: str
) -> None:
    path = tmp_path / "config.toml"
    make(path)
    argv = (
        ["check-config", str(path)] if command == "check-config" else ["run", "--config", str(path), "--http-port", "0"]
    )
    assert main(argv) == 2
    out = capsys.readouterr()
    assert out.err.count("\n") == 1 and "Traceback" not in out.err, out.err
    assert out.err.count(str(path)) == 1 and problem in out.err, out.err  # the file named once, not twice
    assert out.out == ""


BAD_VALUES = [
    ("[imu]\nbuffer_capacity = 9223372036854775807\n",
     "imu.buffer_capacity = 9223372036854775807; allowed: an integer in [16, 8192]"),  # D6
    ("[record]\nqueue_size = 9223372036854775807\n", "record.queue_size = 9223372036854775807; allowed"),
    ("[websocket]\nmax_clients = 9223372036854775807\n", "websocket.max_clients = 9223372036854775807; allowed"),
    ("[tracking.enrolment]\nvolume_min = [nan, -2.5]\n",
     "tracking.enrolment.volume_min[0] = nan; allowed: a number in [-1000, 1000]"),  # D7
    ("[daemon]\nlatency_s = inf\n", "daemon.latency_s = inf; allowed: a number in [0, 2]"),
    ("[solver.terms.floor]\nweight = -inf\n", "solver.terms.floor.weight = -inf; allowed: a number in [0, 1e+06]"),
    ("[imu]\nbaudrate = -1\n", "imu.baudrate = -1; allowed: an integer in [1200, 4000000]"),  # issue 19
    ("[detector.model]\npixel_scale = 0\n", "detector.model.pixel_scale = 0; allowed: a number in (0, 1000]"),
    ("[tracking.enrolment]\nvolume_min = [3.0, -2.5]\n",
     "tracking.enrolment.volume_min = [3.0, -2.5] must be < tracking.enrolment.volume_max = [2.5, 2.5]"),
    ("[tracking.enrolment]\nvolume_min = [1.0, 1.0]\nvolume_max = [1.0, 1.0]\n",
     "tracking.enrolment.volume_min = [1.0, 1.0] must be < tracking.enrolment.volume_max = [1.0, 1.0]"),
    ('[imu.awinda]\nupdate_rate_mid = "x"\n', "imu.awinda.update_rate_mid = 'x'; allowed: an integer in [0, 254]"),
]  # fmt: skip


@pytest.mark.parametrize("command", ["check-config", "run"])
@pytest.mark.parametrize(("toml", "message"), BAD_VALUES, ids=[m.split(" ")[0] for _, m in BAD_VALUES])
def test_hostile_values_are_refused_before_anything_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str, toml: str, message: str
) -> None:
    path = tmp_path / "config.toml"
    path.write_text(toml, encoding="utf-8")
    argv = (
        ["check-config", str(path)] if command == "check-config" else ["run", "--config", str(path), "--http-port", "0"]
    )
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err, err
