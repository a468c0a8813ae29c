"""``mocapd bench``: the benchmarks a user runs, one home and one output convention (issue 46).

Each verb runs briefly in process and prints one JSON object on stdout whose ``"machine"`` entry names the CPU
(model, the instruction-set flags that matter, cores), and one summary line on stderr. The developer benchmarks
left in ``tools/`` say that they are.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from mocapd.service.bench.machine import SPEED_FLAGS, cpu
from mocapd.service.cli import main

ROOT = Path(__file__).resolve().parents[1]


def check_machine(report: dict[str, Any], err: str, verb: str) -> None:
    """The CPU fields every bench JSON carries, and the summary line on stderr."""
    c = report["machine"]["cpu"]
    assert isinstance(c["model"], str) and c["model"], c
    assert c["model"] == cpu()["model"]
    assert set(c["flags"]) <= set(SPEED_FLAGS) and isinstance(c["cores"], int) and 1 <= c["usable_cores"] <= c["cores"]
    assert len(report["machine"]["loadavg"]) == 3
    lines = [line for line in err.splitlines() if line.startswith(f"bench {verb}")]
    assert len(lines) == 1 and c["model"] in lines[0], err


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[dict[str, Any], str]:
    assert main(["bench", *argv]) == 0
    out = capsys.readouterr()
    report: dict[str, Any] = json.loads(out.out)
    return report, out.err


def test_cpu_description_reads_proc_cpuinfo(tmp_path: Path) -> None:
    info = tmp_path / "cpuinfo"
    info.write_text(
        "processor\t: 0\nmodel name\t: Example CPU @ 2.0GHz\nflags\t\t: fpu sse4_2 avx avx2 fma avx512f amx_tile\n\n"
        "processor\t: 1\nmodel name\t: Other\nflags\t\t: fpu\n"
    )
    c = cpu(info)
    assert c["model"] == "Example CPU @ 2.0GHz"
    assert c["flags"] == ["sse4_2", "avx", "avx2", "fma", "avx512f", "amx_tile"]  # in SPEED_FLAGS' order
    assert cpu(tmp_path / "missing")["flags"] == []  # not Linux: no flags, still a model (the platform's)


def test_bench_solver_names_the_cpu(capsys: pytest.CaptureFixture[str]) -> None:
    report, err = _run(capsys, "solver", "--frames", "2", "--scipy-frames", "2")
    check_machine(report, err, "solver")
    assert report["machine"]["blas_in_run"]  # the verb's own machine fields are kept


def test_bench_sorting_names_the_cpu(capsys: pytest.CaptureFixture[str]) -> None:
    report, err = _run(capsys, "sorting", "--frames", "3")
    check_machine(report, err, "sorting")
    assert report["4cam_3people"]["frames"] == 3


def test_bench_detector_times_whole_frames_and_packing(capsys: pytest.CaptureFixture[str]) -> None:
    report, err = _run(capsys, "detector", "--pairs", "2", "--threads", "1")
    check_machine(report, err, "detector")
    assert report["frame_pairs"] == 2 and report["camera_frames_per_pair"] == 8
    assert report["naive_camera_frames_per_s_median"] > 0 and report["packed_camera_frames_per_s_median"] > 0
    assert report["people_naive"] > 0  # the demo's people were found: it timed real detections


def test_bench_streams_costs_every_udp_stream(capsys: pytest.CaptureFixture[str]) -> None:
    report, err = _run(capsys, "streams", "--subjects", "2", "--frames", "10")
    check_machine(report, err, "streams")
    assert report["mvn"]["datagrams_per_frame"] == 2 and report["rokoko"]["datagrams_per_frame"] == 1
    assert report["budget_fraction"] > 0


def test_bench_record_measures_the_recorder(capsys: pytest.CaptureFixture[str]) -> None:
    report, err = _run(capsys, "record", "--seconds", "0.5", "--repeats", "1", "--resolve-seconds", "0.3")
    check_machine(report, err, "record")
    assert report["throughput"]["records_per_s"] > 0 and report["resolve"]["frames"] > 0


def test_bench_capture_measures_four_fake_gige_cameras(capsys: pytest.CaptureFixture[str]) -> None:
    """Four real Aravis fake cameras on loopback (in the rig's own network namespace), captured by mocapd."""
    report, err = _run(capsys, "capture", "--configs", "544x960_BayerRG8", "--duration", "3", "--fps", "10",
                       "--max-frames", "4")  # fmt: skip
    check_machine(report, err, "capture")
    r = report["configs"]["544x960_BayerRG8"]
    assert r["size"] == [544, 960] and r["format"] == "BayerRG8" and len(r["per_camera"]) == 4
    # Frames arrived from every camera, whole (the counters of a lost or torn frame are zero on loopback).
    assert all(c["frames"] > 0 and c["bad_buffers"] == 0 for c in r["per_camera"]), r["per_camera"]
    assert r["median_over_cameras"]["latency_ms_median"] > 0 and r["capture_cpu_pct_per_camera"] > 0
    assert r["per_frame_ms"]["lazy_raw_copy_ms"] > 0  # a Bayer format: the eager/lazy per-frame costs
    assert report["machine"]["loadavg_start"] and report["machine"]["loadavg_end"]  # its own fields kept


def test_benchmarks_left_in_tools_say_they_are_for_developers() -> None:
    scripts = sorted((ROOT / "tools").glob("bench_*.py"))
    assert scripts
    for path in scripts:
        doc = path.read_text(encoding="utf-8").split('"""')[1]
        assert "Developer benchmark" in doc, path.name
    # now mocapd bench detector, streams, record, capture
    moved = {"bench_detect.py", "bench_udp.py", "bench_record.py", "bench_capture.py"}
    assert not moved & {p.name for p in scripts}
