"""The command line: the benchmark prints its JSON, the demo runs, bad usage says so."""

from __future__ import annotations

import json

import pytest

from mocapd.service.cli import main


def test_bench_solver_prints_every_configuration(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "solver", "--frames", "3", "--scipy-frames", "2"]) == 0
    report = json.loads(capsys.readouterr().out)
    for key in ("a_8cam_13imu", "b_4cam_6imu", "c_0cam_13imu", "d_1cam_13imu", "e_4people_8cam_13imu"):
        assert report[key]["frames"] == 3 and report[key]["median_ms"] > 0
    assert report["e_4people_8cam_13imu"]["people"] == 4
    assert report["speedup_vs_scipy_same_frames"] > 1
    assert all(b["num_threads"] == 1 for b in report["machine"]["blas_in_run"])


def test_synthetic_demo_runs_briefly(capsys: pytest.CaptureFixture[str]) -> None:
    # The camera demo (``mocapd demo`` without --synthetic) runs as a process in tests/test_demo_cameras.py.
    assert main(["demo", "--synthetic", "--seconds", "2.5", "--http-port", "0"]) == 0
    out = capsys.readouterr().out
    assert "mocapd demo --synthetic" in out
    assert "ready: status http://127.0.0.1:" in out and "output" in out and "done:" in out


def test_no_command_prints_help(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().out
