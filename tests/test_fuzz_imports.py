"""Hostile input, round two (issue 34), the file doors: ``mocapd import mtw|mvnx``, the MT Manager and MVNX readers,
``calibrate convert``, ``export`` and every output path.

The property: a hostile file or path ends as one ``error:`` line and exit 2 (or the reader's ``InputError``), or a
result whose every value is plausible — never a traceback, a hang, unbounded memory, a silent NaN, a file
written half or where it must not be. Hypothesis draws structure-aware damage from a fixed seed (``derandomize``)
with small budgets; the explicit tests are the regressions of the issue's items 1, 3, 6 and 7 (each fails on the
code before it: named in its docstring).

Special files (a FIFO, a link to ``/dev/zero``) are read in a child process with a 2 GiB address-space limit and
a 60 s time-out, so a regression fails the test (a MemoryError traceback, or no answer) instead of hanging CI or
eating the machine's memory.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mocapd.errors import CalibrationError, InputError
from mocapd.eval.data import default_data_root
from mocapd.io.calibration_files import read_any
from mocapd.io.imu_recordings import SensorStream, write_imported_session
from mocapd.io.mt_export import parse_mt_export
from mocapd.io.mvnx import read_mvnx
from mocapd.service.cli import main
from mocapd.sim.camera_hosts import write_ring_calibration

FUZZ = settings(
    derandomize=True,
    database=None,
    deadline=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture, HealthCheck.data_too_large],
)
REPO = Path(__file__).resolve().parents[1]
MTW = Path(__file__).parent / "data" / "opensense_mtw"
MTW_FILE = MTW / "MT_012005D6_009-001_00B421E6.txt"
MVNX = default_data_root() / "imu/mvnx/mpiea_upperbody_test_mocap.mvnx"


def run_cli(argv: list[str]) -> tuple[int, str]:
    """``mocapd ARGV`` in this process: exit status and stderr (any exception fails the test)."""
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, err.getvalue()


@contextlib.contextmanager
def alarm(seconds: int) -> Iterator[None]:
    """Fail instead of hanging: SIGALRM after ``seconds`` raises in the blocked call (an open() of a FIFO waits for
    its other end; PEP 475 retries it unless the handler raises)."""

    def expired(*_: object) -> None:
        raise TimeoutError(f"no answer within {seconds} s (a FIFO waited on?)")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def assert_refused(code: int, err: str, *needles: str) -> None:
    """Exit 2 and one line ``error: ...`` (containing each needle)."""
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), (code, err)
    for needle in needles:
        assert needle in lines[0], (needle, err)


# ---------------------------------------------------------------------------------------------- special files
_GUARD = """
import contextlib, io, json, resource, signal, sys
resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))  # /dev/zero read whole: MemoryError, not the machine
from mocapd.service.cli import main
out = []
for argv in json.loads(sys.argv[1]):
    def timeout(*_):
        raise TimeoutError("no answer within 20 s")
    signal.signal(signal.SIGALRM, timeout)
    signal.alarm(20)  # a FIFO waited on: the open is interrupted, the case fails
    err = io.StringIO()
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            code = main(argv)
    except BaseException as exc:
        code, err = None, io.StringIO(f"{type(exc).__name__}: {exc}")
    signal.alarm(0)
    out.append([code, err.getvalue()])
print(json.dumps(out))
"""


def run_guarded(cases: list[list[str]]) -> list[tuple[int | None, str]]:
    """Each ``mocapd ARGV`` of ``cases`` in one child process (2 GiB of address space, 20 s per case, 120 s in
    all): its exit status (None: an exception escaped, or the time-out) and stderr."""
    proc = subprocess.run([sys.executable, "-c", _GUARD, json.dumps(cases)], cwd=REPO, capture_output=True,
                          text=True, timeout=120, check=False)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    return [(code, err) for code, err in json.loads(proc.stdout.strip().splitlines()[-1])]


def test_special_files_are_refused_not_waited_on_or_read_without_end(tmp_path: Path) -> None:
    """Issue 34 item 1: `import mtw` on a link to /dev/zero grew memory at ~350 MiB/s until the machine ran out (here:
    MemoryError under the child's 2 GiB limit); a FIFO made `import mtw` and `import mvnx` (and `calibrate convert`,
    `session`) wait forever (here: the 20 s alarm). Now each is one line naming the file and what it is."""
    fifo = tmp_path / "MT_fifo_00B40001.txt"
    os.mkfifo(fifo)
    zero = tmp_path / "MT_zero_00B40002.txt"
    zero.symlink_to("/dev/zero")
    (tmp_path / "take.mvnx").symlink_to(fifo)
    (tmp_path / "zero.mvnx").symlink_to("/dev/zero")
    (tmp_path / "calib.toml").symlink_to(fifo)
    (tmp_path / "calib.qca.txt").symlink_to("/dev/zero")
    (tmp_path / "calib.yml").symlink_to(fifo)
    session = tmp_path / "session"
    session.mkdir()
    os.mkfifo(session / "manifest.json")
    o = str(tmp_path / "out")
    cases = [
        ["import", "mtw", str(fifo), "-o", o, "--assign", "00B40001=Hips"],
        ["import", "mtw", str(zero), "-o", o, "--assign", "00B40002=Hips"],
        ["import", "mvnx", str(tmp_path / "take.mvnx"), "-o", o],
        ["import", "mvnx", str(tmp_path / "zero.mvnx"), "-o", o],
        ["calibrate", "convert", str(tmp_path / "calib.toml"), str(tmp_path / "a.toml")],
        ["calibrate", "convert", str(tmp_path / "calib.qca.txt"), str(tmp_path / "b.toml")],
        ["calibrate", "convert", str(tmp_path / "calib.yml"), str(tmp_path / "c.toml")],
        ["session", str(session)],
    ]
    for argv, (code, err) in zip(cases, run_guarded(cases), strict=True):
        assert code == 2 and err.count("\n") == 1 and err.startswith("error: "), (argv, code, err)
        assert "not a regular file" in err, (argv, err)
        assert ("a FIFO" in err) or ("a character device" in err), (argv, err)


# ---------------------------------------------------------------------------------------------- MT exports
QUAT_EXTREMES = [(0.0, 0.0, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0), (1e308, 1e308, 0.0, 0.0), (math.inf, 0.0, 0.0, 0.0),
                 (-1.0, 0.0, 0.0, 0.0), (0.5, 0.5, 0.5, 0.5), (1e-300, 0.0, 0.0, 0.0)]  # fmt: skip
RATE_HEADERS = ["100Hz", "100.0Hz", "1e6Hz", "1e-6Hz", "0Hz", "-100Hz", "nanHz", "infHz", "fast", "1" * 400, "60Hz",
                "2000Hz", "2001Hz", ""]  # fmt: skip


@st.composite
def mt_exports(draw: st.DrawFn) -> str:
    """An MT Manager export built field by field, each field valid or hostile: header lines (rate, coordinate
    system, device id, many of them), column names (duplicated, many), counters (running backwards, constant,
    jumping, wrapping, beyond their range), orientations (zero, huge, non-unit), vectors beyond any IMU."""
    n = draw(st.integers(1, 40))
    header = [f"// Update Rate: {draw(st.sampled_from(RATE_HEADERS))}"] if draw(st.booleans()) else []
    header.append(f"// Coordinate system: {draw(st.sampled_from(['ENU', 'NED', 'NWU', 'XYZ', '', 'enu' * 100]))}")
    if draw(st.booleans()):
        header.append(f"// DeviceId: {draw(st.sampled_from(['00B40001', 'zz', '1' * 100, '00b40001']))}")
    header += ["// x: y"] * draw(st.sampled_from([0, 0, 1001]))
    layout = draw(st.sampled_from(["quat", "mat", "euler"]))
    orient = {"quat": [f"Quat_q{i}" for i in range(4)], "euler": ["Roll", "Pitch", "Yaw"],
              "mat": [f"Mat[{i}][{j}]" for i in (1, 2, 3) for j in (1, 2, 3)]}[layout]  # fmt: skip
    cols = ["PacketCounter", "SampleTimeFine", *orient, "Acc_X", "Acc_Y", "Acc_Z"]
    if draw(st.integers(0, 9)) == 0:
        cols.append(draw(st.sampled_from(["Acc_X", "PacketCounter", *[f"X{i}" for i in range(600)]])))
    step = draw(st.sampled_from([1, 1, 1, 0, -1, 2, 40000, -65535]))
    tick_step = draw(st.sampled_from([100, 100, 0, -100, 2**31, 1]))
    start_pc = draw(st.sampled_from([0, 65530, 65535, 70000]))
    start_t = draw(st.sampled_from([0, 2**32 - 150, 2**32]))
    bad_row = draw(st.integers(0, n - 1))
    bad_quat = draw(st.sampled_from([None, None, *QUAT_EXTREMES]))
    acc = draw(st.sampled_from([9.81, 9.81, 1e6, -math.inf, math.nan]))
    rows = []
    for i in range(n):
        values: dict[str, float] = {"PacketCounter": (start_pc + i * step) % 70000,
                                    "SampleTimeFine": (start_t + i * tick_step) % (2**32 + 5)}  # fmt: skip
        q = bad_quat if (bad_quat is not None and i == bad_row) else (1.0, 0.0, 0.0, 0.0)
        if layout == "quat":
            values |= dict(zip(orient, q, strict=True))
        elif layout == "euler":
            values |= dict(zip(orient, (q[1] * 800, 0.0, 10.0), strict=True))
        else:
            with np.errstate(invalid="ignore"):
                m = np.eye(3) * q[0]  # inf * 0 off the diagonal: nan, a hostile matrix either way
            values |= {name: float(v) for name, v in zip(orient, m.reshape(-1), strict=True)}
        values |= {"Acc_X": 0.0, "Acc_Y": 0.0, "Acc_Z": acc if i == bad_row else 9.81}
        rows.append("\t".join(repr(values.get(c, 0.0)) for c in cols))
    return "\n".join([*header, "\t".join(cols), *rows]) + "\n"


def _plausible_export(text: str) -> None:
    """Read: an InputError of one line, or every number plausible (finite, unit quaternions, increasing times)."""
    try:
        e = parse_mt_export(text, name="MT_x_00B40001.txt")
    except InputError as exc:
        assert "\n" not in str(exc), str(exc)
        return
    assert 1.0 <= e.rate_hz <= 2000.0
    assert np.isfinite(e.quat).all() and np.allclose(np.linalg.norm(e.quat, axis=1), 1.0)
    assert np.isfinite(e.acc).all() and np.abs(e.acc).max() <= 2000.0 + 10.0
    assert np.isfinite(e.time_s).all() and (np.diff(e.time_s) > 0).all(), e.time_s


@settings(FUZZ, max_examples=250)
@given(mt_exports())
def test_hostile_mt_exports(text: str) -> None:
    _plausible_export(text)


@pytest.mark.parametrize(
    ("name", "edit", "problem"),
    [
        ("zero-quaternions", lambda r: [r[0], "0", "0", "0", "0"], "Quat_q0..q3 = (0, 0, 0, 0) in data row 1"),
        ("counter-backwards", None, "PacketCounter goes from 200 to 199 at data row 2"),
        ("counter-constant", None, "PacketCounter goes from 7 to 7 at data row 2"),
    ],
    ids=["zero-quaternions", "counter-backwards", "counter-constant"],
)
def test_import_values_the_probe_found(tmp_path: Path, name: str, edit: Any, problem: str) -> None:
    """Issue 34 items 3 and 7: an export whose quaternions are all zero imported with exit 0 (every sample NaN,
    and `calibrate imu --from` then died with LinAlgError); a PacketCounter running backwards gave negative times,
    a constant one 200 samples at one instant. Each is now one line naming the column and the row, exit 2."""
    lines = ["// Update Rate: 100Hz", "PacketCounter\tQuat_q0\tQuat_q1\tQuat_q2\tQuat_q3"]
    for i in range(200):
        counter = {"counter-backwards": 200 - i, "counter-constant": 7}.get(name, i)
        row = [str(counter), "1", "0", "0", "0"]
        lines.append("\t".join(edit(row) if edit else row))
    path = tmp_path / "MT_x_00B40001.txt"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    code, err = run_cli(["import", "mtw", str(path), "-o", str(tmp_path / "s"), "--assign", "00B40001=Hips"])
    assert_refused(code, err, problem)
    assert not (tmp_path / "s").exists()


def test_an_absurd_update_rate_is_refused_not_read_as_1_hz(tmp_path: Path) -> None:
    """Issue 34 item 7: '// Update Rate: 1e6Hz' was read as 1 Hz (the digits before the exponent). Now the whole
    number is read and refused outside 1..2000 Hz; a rate that disagrees with SampleTimeFine is refused too."""
    text = MTW_FILE.read_text(encoding="utf-8")
    for header, problem in (("1e6Hz", "update rate of 1e+06 Hz"), ("0.001Hz", "update rate of 0.001 Hz")):
        path = tmp_path / "MT_012005D6_009-001_00B421E6.txt"
        path.write_text(text.replace("// Update Rate: 100.0Hz", f"// Update Rate: {header}"), encoding="utf-8")
        code, err = run_cli(["import", "mtw", str(path), "-o", str(tmp_path / "s"), "--assign", "00B421E6=Hips"])
        assert_refused(code, err, problem)
    lines = ["// Update Rate: 60Hz", "PacketCounter\tSampleTimeFine\tQuat_q0\tQuat_q1\tQuat_q2\tQuat_q3",
             *(f"{i}\t{i * 100}\t1\t0\t0\t0" for i in range(10))]  # fmt: skip
    with pytest.raises(InputError, match="disagrees with SampleTimeFine, whose steps give 100 Hz"):
        parse_mt_export("\n".join(lines), name="MT_x_00B40001.txt")


def test_a_calibration_from_a_session_with_nan_samples_is_one_line(tmp_path: Path) -> None:
    """Issue 34 item 3: a session an older import wrote with NaN samples made `calibrate imu --from` die with
    `LinAlgError: Eigenvalues did not converge`. Now it names the sensor and says what to do (exit 1, as the
    command's other calibration failures)."""
    n = 300
    t = np.arange(n, dtype=np.int64) * 10_000_000
    stream = SensorStream("00B40001", t, np.full((n, 4), np.nan), np.tile([0.0, 0.0, 9.81], (n, 1)), None, None,
                          {"file": "x", "samples": n})  # fmt: skip
    from mocapd.service.session.importer import imported_manifest

    manifest = imported_manifest([stream], {"00B40001": "Hips"}, source="mt-manager", suit="suit0", height=1.75)
    write_imported_session(tmp_path / "s", [stream], manifest)
    code, err = run_cli(["calibrate", "imu", "--from", str(tmp_path / "s"), "--facing-heading", "0",
                         "--out", str(tmp_path / "c.json")])  # fmt: skip
    assert code == 1 and err.count("\n") == 1 and "Traceback" not in err, err
    assert "sensor 00B40001: 300 of 300 samples hold no rotation" in err and "import the recording again" in err


def test_assignments_and_names_the_probe_found(tmp_path: Path) -> None:
    """Issue 34 item 7: the same sensor assigned twice (the last one silently won), suit names with a newline or
    `../` (they name files and go into manifests), a person named `../x` (its calibration file is
    <calibration_dir>/<person>.imu.json)."""
    base = ["import", "mtw", str(MTW_FILE), "-o", str(tmp_path / "s")]
    code, err = run_cli([*base, "--assign", "00B421E6=Hips", "--assign", "00b421e6=Head"])
    assert_refused(code, err, "sensor 00B421E6 is assigned twice (Hips and Head)")
    for suit in ("a\nb", "../x", "x" * 33, ""):
        code, err = run_cli([*base, "--assign", "00B421E6=Hips", "--suit", suit])
        assert_refused(code, err, "--suit", "allowed: 1 to 32 letters")
    assert not (tmp_path / "s").exists()
    code, _ = run_cli([*base, "--assign", "00B421E6=Hips"])
    assert code == 0
    code, err = run_cli(["calibrate", "imu", "--from", str(tmp_path / "s"), "--facing-heading", "0", "--person",
                         "../../x"])  # fmt: skip
    assert code == 1 and "--person '../../x': allowed" in err, err


def test_calibration_camera_names_follow_the_config_rule(tmp_path: Path) -> None:
    """Issue 34 item 7: calibration camera names far beyond the config's limit (and with characters it refuses)
    were accepted: no camera of a config can ever match them. Two cameras of one name: which one is meant?"""
    write_ring_calibration(["cam0", "cam1"], tmp_path / "c.toml")
    text = (tmp_path / "c.toml").read_text(encoding="utf-8")
    for name in ("c" * 5000, "cam\n0", "../cam"):
        (tmp_path / "x.toml").write_text(text.replace('name = "cam0"', f"name = {json.dumps(name)}"), "utf-8")
        with pytest.raises(CalibrationError, match="allowed: 1 to 32 letters"):
            read_any(tmp_path / "x.toml")
    (tmp_path / "x.toml").write_text(text.replace('name = "cam1"', 'name = "cam0"'), encoding="utf-8")
    with pytest.raises(CalibrationError, match=r"\['cam0'\] appear more than once"):
        read_any(tmp_path / "x.toml")


def test_a_large_export_is_read_with_bounded_memory(tmp_path: Path) -> None:
    """Issue 34 item 7: a 265 MB MT export took 2.5 GiB (tools/bench_import.py: 2405 MiB over the CLI's own
    memory before, 379 MiB now). Here a 30 MB export in a child process that first imports the small real export
    (so that every module the import loads is loaded): the big import's peak memory beyond that must stay under
    twice the file (before: ~9 times)."""
    from tools.bench_import import write_export

    export = tmp_path / "MT_bench_00B421E6.txt"
    write_export(export, 30.0)
    script = (
        "import resource, sys\nfrom mocapd.service.cli import main\n"
        f"assert main(['import', 'mtw', {str(MTW_FILE)!r}, '-o', {str(tmp_path / 'warm')!r}, '--assign', "
        "'00B421E6=Hips']) == 0\n"
        "before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
        f"code = main(['import', 'mtw', {str(export)!r}, '-o', {str(tmp_path / 's')!r}, '--assign', "
        "'00B421E6=Hips'])\n"
        "print(code, (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) * 1024)\n"
    )
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=300,
                          check=False)  # fmt: skip
    code, grown = proc.stdout.strip().splitlines()[-1].split()
    size = export.stat().st_size
    assert code == "0", proc.stderr[-2000:]
    assert int(grown) < 2 * size, f"the import grew by {int(grown) / 2**20:.0f} MiB for a {size / 2**20:.0f} MiB file"


# ---------------------------------------------------------------------------------------------- MVNX
MVNX_TEXT: list[str] = []


def _mvnx() -> str:
    if not MVNX_TEXT:
        MVNX_TEXT.append(MVNX.read_text(encoding="utf-8"))
    return MVNX_TEXT[0]


@settings(FUZZ, max_examples=40)
@given(
    st.sampled_from(["frameRate", "time"]),
    st.sampled_from(["0", "-60", "1e308", "1e6", "nan", "0.5", "59", "240", "x", "-1", "1e12", "120"]),
    st.integers(0, 100),
)
def test_hostile_mvnx_rates_and_times(tmp_path_factory: pytest.TempPathFactory, attr: str, value: str, k: int) -> None:
    """The frame rate, or one normal frame's time, set to an extreme: InputError, or a plausible recording (rate
    1..1000 Hz agreeing with the frames' times, times from >= 0 increasing)."""
    text = _mvnx()
    if attr == "frameRate":
        text = text.replace('frameRate="60"', f'frameRate="{value}"', 1)
    else:
        marker = f'<frame time="{_times()[k]}" index="{k}"'
        assert marker in text
        text = text.replace(marker, f'<frame time="{value}" index="{k}"', 1)
    path = tmp_path_factory.mktemp("mvnx") / "x.mvnx"
    path.write_text(text, encoding="utf-8")
    try:
        rec = read_mvnx(path)
    except InputError as exc:
        assert "\n" not in str(exc)
        return
    assert 1.0 <= rec.fps <= 1000.0 and rec.time_ms[0] >= 0 and (np.diff(rec.time_ms) > 0).all()
    assert abs(rec.fps * float(np.median(np.diff(rec.time_ms))) / 1000.0 - 1.0) <= 0.1


def _times() -> list[str]:
    import re

    return re.findall(r'<frame time="([^"]+)" index="\d+"', _mvnx())


def test_an_absurd_mvnx_frame_rate_is_refused(tmp_path: Path) -> None:
    """Issue 34 item 7: frameRate="1e6" (or "0.5", which the frames' 17 ms steps contradict) was accepted."""
    for value, problem in (("1e6", "frameRate 1e+06; allowed: 1 to 1000 Hz"),
                           ("120", "frameRate 120 Hz disagrees with the frames' times")):  # fmt: skip
        path = tmp_path / "x.mvnx"
        path.write_text(_mvnx().replace('frameRate="60"', f'frameRate="{value}"', 1), encoding="utf-8")
        code, err = run_cli(["import", "mvnx", str(path), "-o", str(tmp_path / "s")])
        assert_refused(code, err, problem)


# ---------------------------------------------------------------------------------------------- output paths
@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An imported MTw recording, calibrated and resolved (a few iterations): something to export."""
    path = tmp_path_factory.mktemp("imported") / "session"
    assert run_cli(["import", "mtw", *map(str, sorted(MTW.glob("MT_*.txt"))), "-o", str(path), "--assign",
                    "00B421E6=Hips", "--assign", "00B421ED=RightUpperLeg"])[0] == 0  # fmt: skip
    assert run_cli(["calibrate", "imu", "--from", str(path), "--facing-heading", "0", "--window", "0.5", "--out",
                    str(path.parent / "suit0.imu.json")])[0] == 0  # fmt: skip
    assert run_cli(["resolve", str(path), "--iterations", "2", "--no-smooth"])[0] == 0
    return path


@pytest.mark.parametrize(
    ("target", "problem"),
    [
        ("missing/x.bvh", "the folder {tmp}/missing does not exist"),
        (".", "a directory; give a file name"),
        ("/proc/x.bvh", "cannot create a file in /proc"),
        ("/dev/full", "not a regular file (a character device)"),
        ("file/x.bvh", "{tmp}/file is not a folder (a regular file)"),
        ("existing.bvh", "exists already; give --force to replace it"),
    ],
    ids=["missing-folder", "directory", "proc", "dev-full", "file-as-folder", "existing"],
)
def test_export_output_paths_the_probe_found(session: Path, tmp_path: Path, target: str, problem: str) -> None:
    """Issue 34 item 6: `export` to a missing folder, a directory, /proc, /dev/full gave a Python traceback and
    exit 1 (after the work); an existing file was overwritten without a word. Now each is refused before the work,
    one line, exit 2, and nothing is written."""
    (tmp_path / "file").write_text("x")
    (tmp_path / "existing.bvh").write_text("keep me")
    path = target if target.startswith("/") else str(tmp_path / target)
    code, err = run_cli(["export", str(session), "--resolved", "--bvh", path])
    assert_refused(code, err, problem.format(tmp=tmp_path))
    assert (tmp_path / "existing.bvh").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["existing.bvh", "file"]  # no partial or temporary file
    if target == "existing.bvh":
        assert run_cli(["export", str(session), "--resolved", "--bvh", path, "--force"])[0] == 0
        assert (tmp_path / "existing.bvh").read_text().startswith("HIERARCHY")


@pytest.mark.parametrize(
    ("argv", "problem"),
    [
        (["export", "{s}", "--resolved", "--csv", "{t}/x.csv", "--rate", "nan"], "argument --rate: 'nan'; allowed"),
        (["export", "{s}", "--resolved", "--csv", "{t}/x.csv", "--rate", "1e-9"], "argument --rate: '1e-9'; allowed"),
        (["calibrate", "imu", "--from", "{s}", "--facing-heading", "nan"], "argument --facing-heading: 'nan'"),
        (["resolve", "{s}", "--iterations", "-5"], "argument --iterations: '-5'; allowed: an integer"),
        (["replay", "{s}", "--speed", "0"], "argument --speed: '0'; allowed"),
        (["calibrate", "convert", "{t}/c.toml", "{t}/d.toml", "--scale", "inf"], "argument --scale: 'inf'"),
    ],
    ids=["export-rate-nan", "export-rate-tiny", "facing-heading-nan", "iterations-negative", "speed-0", "scale-inf"],
)
def test_numbers_on_the_command_line_are_checked(
    session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], problem: str
) -> None:
    """Found beside the probe's list (the principle, applied to the command line): `export --rate nan` was a
    ValueError traceback; `calibrate imu --from S --facing-heading nan` wrote NaN into the calibration file and into
    the session's manifest with exit 0 (every later command then called the session damaged). Now argparse refuses
    each number outside its range with one `error:` line and exit 2, before anything is touched."""
    manifest = (session / "manifest.json").read_bytes()
    args = [a.format(s=session, t=tmp_path) for a in argv]
    with pytest.raises(SystemExit) as exit_:
        main(args)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and problem in err.strip().splitlines()[-1], err
    assert (session / "manifest.json").read_bytes() == manifest


def test_two_outputs_of_one_export_must_differ(session: Path, tmp_path: Path) -> None:
    """Issue 34 item 6: `export --bvh F --csv F` reported both written while F held only the CSV."""
    f = tmp_path / "F"
    code, err = run_cli(["export", str(session), "--resolved", "--bvh", str(f), "--csv", str(f)])
    assert_refused(code, err, "given to both --bvh and --csv")
    assert not f.exists()
    (tmp_path / "link").symlink_to(f)
    code, err = run_cli(["export", str(session), "--resolved", "--bvh", str(f), "--gltf", str(tmp_path / "link")])
    assert_refused(code, err, "given to both --bvh and --gltf")


def test_calibrate_convert_output_paths(tmp_path: Path) -> None:
    """Issue 34 item 6: `calibrate convert` to a directory was a traceback; `calibrate convert X X` overwrote its
    own input (even through a link); an existing output was overwritten silently."""
    src = tmp_path / "c.toml"
    write_ring_calibration(["cam0", "cam1"], src)
    original = src.read_bytes()
    code, err = run_cli(["calibrate", "convert", str(src), str(tmp_path)])
    assert_refused(code, err, "a directory")
    (tmp_path / "same.toml").symlink_to(src)
    for out in (src, tmp_path / "same.toml"):
        code, err = run_cli(["calibrate", "convert", str(src), str(out), "--force"])
        assert_refused(code, err, "is an input of this command")
    assert src.read_bytes() == original
    (tmp_path / "p.toml").write_text("keep")
    code, err = run_cli(["calibrate", "convert", str(src), str(tmp_path / "p.toml"), "--to", "pose2sim"])
    assert_refused(code, err, "exists already; give --force")
    assert run_cli(["calibrate", "convert", str(src), str(tmp_path / "p.toml"), "--to", "pose2sim", "--force"])[0] == 0
    assert (tmp_path / "p.toml").read_text() != "keep"


def test_import_output_paths(tmp_path: Path) -> None:
    """Issue 34 item 6: `import mtw -o` an existing file was a traceback (NotADirectoryError); into a non-empty
    directory it wrote beside what was there. Now a new or empty directory only, checked before reading."""
    (tmp_path / "file").write_text("x")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("x")
    (tmp_path / "empty").mkdir()
    base = ["import", "mtw", str(MTW_FILE), "--assign", "00B421E6=Hips", "-o"]
    for target, problem in (("file", "exists and is a regular file"), ("full", "exists and is not empty"),
                            ("missing/s", "the folder")):  # fmt: skip
        assert_refused(*run_cli([*base, str(tmp_path / target)]), problem)
    assert run_cli([*base, str(tmp_path / "empty")])[0] == 0
    assert (tmp_path / "empty" / "manifest.json").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary directory left


OUTPUT_KINDS = ["new", "existing", "directory", "missing-folder", "dev-full", "fifo", "zero-link", "input",
                "file-as-folder", "long-name", "dot", "proc", "dangling-link"]  # fmt: skip


def _make_output(kind: str, folder: Path, session: Path) -> str:
    """The output path of one kind (see OUTPUT_KINDS), made in ``folder``."""
    p = folder / "out.csv"
    (folder / "f").write_text("x")
    made: dict[str, Callable[[], object]] = {
        "existing": lambda: p.write_text("keep"),
        "directory": p.mkdir,
        "fifo": lambda: os.mkfifo(p),
        "zero-link": lambda: p.symlink_to("/dev/zero"),
        "dangling-link": lambda: p.symlink_to(folder / "nowhere"),
    }
    if kind in made:
        made[kind]()
    elsewhere = {
        "missing-folder": str(folder / "no" / "out.csv"),
        "dev-full": "/dev/full",
        "input": str(session / "manifest.json"),
        "file-as-folder": str(folder / "f" / "out.csv"),
        "long-name": str(folder / ("x" * 300)),
        "dot": str(folder / "."),
        "proc": "/proc/self/out.csv",
    }
    return elsewhere.get(kind, str(p))


@settings(FUZZ, max_examples=40)
@given(st.sampled_from(OUTPUT_KINDS), st.sampled_from(["--csv", "--bvh", "--gltf"]), st.booleans())
def test_export_output_path_fuzz(
    session: Path, tmp_path_factory: pytest.TempPathFactory, kind: str, option: str, force: bool
) -> None:
    """Any output path: the export is written whole (exit 0; a regular file where the path says), or refused with
    one line and exit 2 — never a traceback, never a device or a session file written, never a temporary file
    left behind."""
    folder = tmp_path_factory.mktemp("out")
    manifest = (session / "manifest.json").read_bytes()
    target = _make_output(kind, folder, session)
    before = sorted(p.name for p in folder.iterdir())
    with alarm(60):  # a FIFO opened for writing waits for a reader: before issue 34, forever
        code, err = run_cli(["export", str(session), "--resolved", option, target, *(["--force"] if force else [])])
    assert "Traceback" not in err and code in (0, 2), (kind, code, err)
    assert (session / "manifest.json").read_bytes() == manifest
    leftovers = [p.name for p in folder.iterdir() if p.name.startswith(".")]
    assert not leftovers, leftovers
    if code == 2:
        assert err.count("\n") == 1 and err.startswith("error: "), err
        assert sorted(p.name for p in folder.iterdir()) == before
    else:
        assert kind in ("new", "existing", "dangling-link") and (kind != "existing" or force), (kind, err)
        written = Path(target)
        assert written.is_file() and not written.is_symlink() and written.stat().st_size > 100


def test_an_interrupted_export_leaves_the_old_file(session: Path, tmp_path: Path, monkeypatch: Any) -> None:
    """Outputs are written atomically: a write that fails half-way (here the CSV writer raises after the header)
    leaves the previous file untouched and no temporary file."""
    from mocapd.io import session_export

    out = tmp_path / "take.csv"
    out.write_text("previous take")

    def header_then_fail() -> list[str]:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(session_export, "csv_header", header_then_fail)
    code, err = run_cli(["export", str(session), "--resolved", "--csv", str(out), "--force"])
    assert_refused(code, err, f"cannot write {out}: No space left on device")
    assert out.read_text() == "previous take" and sorted(p.name for p in tmp_path.iterdir()) == ["take.csv"]


def test_output_files_are_plain_files_with_the_usual_permissions(session: Path, tmp_path: Path) -> None:
    """The atomic write's temporary file is private (0600) while written; the output gets what open() gives."""
    old = os.umask(0o022)
    try:
        assert run_cli(["export", str(session), "--resolved", "--csv", str(tmp_path / "a.csv")])[0] == 0
    finally:
        os.umask(old)
    assert (tmp_path / "a.csv").stat().st_mode & 0o777 == 0o644


def test_importing_leaves_nothing_when_it_fails(tmp_path: Path) -> None:
    """An import refused after reading (a second file whose values are refused) leaves no session directory and
    no temporary one."""
    good = tmp_path / "MT_012005D6_009-001_00B421E6.txt"
    shutil.copy(MTW_FILE, good)
    bad = tmp_path / "MT_x_00B40001.txt"
    bad.write_text("// Update Rate: 100Hz\nPacketCounter\tQuat_q0\tQuat_q1\tQuat_q2\tQuat_q3\n1\t0\t0\t0\t0\n")
    code, err = run_cli(["import", "mtw", str(good), str(bad), "-o", str(tmp_path / "s"), "--assign",
                         "00B421E6=Hips"])  # fmt: skip
    assert_refused(code, err, "not a rotation")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([good.name, bad.name])


def test_output_names_of_four_byte_characters_up_to_the_longest_a_file_may_have(tmp_path: Path) -> None:
    """Issue 45: the temporary file beside an output took the output name's first 100 *characters*: 62 emoji (248
    bytes) plus the suffix went over the 255 bytes a file name may have. Now its first 100 bytes."""
    from mocapd.io.output_files import atomic_file, check_output_file

    out = tmp_path / ("🦴" * 62 + "a.txt")
    assert len(out.name.encode()) == 253
    check_output_file(out)
    with atomic_file(out) as fh:
        fh.write("bones")
    assert out.read_text() == "bones" and list(tmp_path.iterdir()) == [out]
