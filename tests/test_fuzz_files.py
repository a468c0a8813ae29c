"""Fuzzing the file doors (issue 18): config files, recorded sessions, calibration files of every format
``mocapd calibrate convert`` reads, motion files (BVH, ASF/AMC, MVNX) and MT Manager exports (``mocapd import mtw``).

The property at every door: a damaged or hostile file ends as the command's one clear error line and exit 2, or a
counted note and a normal run (a session stream's corrupt records are skipped and reported) — never a traceback,
never an exception other than the project's own (:class:`~mocapd.errors.MocapdError`) out of a reader.

Hypothesis draws the damage from a fixed seed (``derandomize``) with a small budget; the explicit tests below the
fuzzers are the regressions of the issue's table (D8–D10) and of what the fuzzers found.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import re
import shutil
import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mocapd.errors import CalibrationError, ConfigError, InputError, MocapdError
from mocapd.eval.data import default_data_root
from mocapd.io.asfamc import AsfSkeleton, read_amc, read_asf
from mocapd.io.bvh import read_bvh
from mocapd.io.calibration_files import read_any
from mocapd.io.mt_export import MtExport, read_mt_export
from mocapd.io.mvnx import read_mvnx
from mocapd.io.pose2sim_demo import demo_calibration
from mocapd.io.session import open_session
from mocapd.protocols.session_format import (
    T_IMU,
    T_KEYPOINTS,
    T_POSE,
    decode_frame,
    decode_imu,
    decode_keypoints,
    decode_pose,
    encode_record,
)
from mocapd.service.cli import main
from mocapd.service.config import DEFAULT_CONFIG, load_config
from mocapd.service.session.solve import session_rig, solve_times
from mocapd.service.session.truth import synthetic_of

FUZZ = settings(
    derandomize=True,  # the fixed seed: the same examples every run
    database=None,
    deadline=None,  # the machine is shared: no per-example wall-clock limit
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture, HealthCheck.data_too_large],
)
DATA = default_data_root()
MTW = Path(__file__).parent / "data" / "opensense_mtw"


def run_cli(argv: list[str]) -> tuple[int, str]:
    """``mocapd ARGV`` in this process: exit status and what it wrote to stderr. Any exception fails the test."""
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, err.getvalue()


def assert_clear(code: int, stderr: str) -> None:
    """Exit 0, or exit 2 with its reason on the last line, ``error: ...``; never a traceback."""
    assert "Traceback" not in stderr, stderr
    assert code in (0, 2), (code, stderr)
    if code == 2:
        assert stderr.strip().splitlines()[-1].startswith("error: "), stderr


# ---------------------------------------------------------------------------------------------- damage
@st.composite
def damaged(draw: st.DrawFn, data: bytes) -> bytes:
    """``data`` with one kind of damage: flipped bits, a cut, inserted hostile bytes, a zeroed stretch."""
    if not data:
        return draw(st.binary(max_size=64))
    kind = draw(st.sampled_from(["flip", "cut", "insert", "zero"]))
    b = bytearray(data)
    if kind == "flip":
        for _ in range(draw(st.sampled_from([1, 3, 30]))):
            b[draw(st.integers(0, len(b) - 1))] ^= 1 << draw(st.integers(0, 7))
    elif kind == "cut":
        b = b[: draw(st.integers(0, len(b) - 1))]
    elif kind == "insert":
        at = draw(st.integers(0, len(b)))
        junk = [b"nan", b"-1", b"1e999", b"\x00", b"9" * 30, b"\xff\xfe", b"\n", b"[", b"{", b'"', b"<"]
        b[at:at] = draw(st.sampled_from(junk))
    else:
        at = draw(st.integers(0, len(b) - 1))
        b[at : at + 50] = bytes(len(b[at : at + 50]))
    return bytes(b)


# ---------------------------------------------------------------------------------------------- config files
SHIPPED_LINES = DEFAULT_CONFIG.read_text(encoding="utf-8").splitlines()
# One-line `key = value` settings of the shipped config (multi-line arrays left out): the values to mutate.
VALUE_LINES = [
    i for i, line in enumerate(SHIPPED_LINES)
    if re.match(r"^[a-z_0-9]+ = ", line) and not (line.split("=", 1)[1].strip().startswith("[") and "]" not in line)
]  # fmt: skip
EXTREMES = ["nan", "inf", "-inf", "0", "-1", "9223372036854775807", "-9223372036854775808", "1e308", "5e-324",
            '"x"', '""', "true", "[]", "[" + "1," * 5000 + "]", "[nan, 1]", "{}", '"\\u0000"',
            '"' + "a" * 100_000 + '"', "1979-05-27T07:32:00Z", "[[1, 2], [3]]", '["a", 1]']  # fmt: skip
NON_FINITE = {"nan", "inf", "-inf", "[nan, 1]"}


@settings(FUZZ, max_examples=300)
@given(st.sampled_from(VALUE_LINES), st.sampled_from(EXTREMES), st.booleans(), st.integers(0, 10**9))
def test_config_values_mutated_to_the_extremes(
    tmp_path_factory: pytest.TempPathFactory, line: int, value: str, non_utf8: bool, where: int
) -> None:
    """The shipped config with one setting's value replaced by an extreme (NaN, ±inf, 0, negative, 2^63, huge
    lists and strings, wrong types), sometimes with a non-UTF-8 byte: a valid config or one ConfigError."""
    lines = list(SHIPPED_LINES)
    key = lines[line].split(" = ", 1)[0]
    lines[line] = f"{key} = {value}"
    data = "\n".join(lines).encode()
    if non_utf8:
        at = where % len(data)
        data = data[:at] + b"\xff" + data[at:]
    path = tmp_path_factory.mktemp("cfg") / "config.toml"
    path.write_bytes(data)
    try:
        load_config(path)
    except ConfigError as exc:
        assert "\n" not in str(exc).strip(), str(exc)  # one line
    else:
        assert value not in NON_FINITE, f"{key} = {value} was accepted"


# ---------------------------------------------------------------------------------------------- sessions
@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real recorded session: `mocapd demo --synthetic` for 1.5 s with --record."""
    path = tmp_path_factory.mktemp("recorded") / "session"
    subprocess.run([sys.executable, "-m", "mocapd", "demo", "--synthetic", "--seconds", "1.5", "--record", str(path)],
                   check=True, capture_output=True, timeout=300)  # fmt: skip
    assert sorted(p.name for p in path.iterdir()) == [
        "events.mcs", "imu.mcs", "keypoints.mcs", "manifest.json", "poses.mcs", "prior.npz"
    ]  # fmt: skip
    return path


@pytest.fixture(scope="module")
def replay_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replay") / "replay.toml"
    path.write_text("[websocket]\nport = 0\n")  # any free port: the shipped one may be taken
    return path


SESSION_FILES = ["manifest.json", "prior.npz", "poses.mcs", "keypoints.mcs", "imu.mcs", "events.mcs"]


@st.composite
def session_damage(draw: st.DrawFn, session: Path) -> tuple[str, bytes | None]:
    """One file of the session and what becomes of it: None = deleted, else its new bytes."""
    name = draw(st.sampled_from(SESSION_FILES))
    action = draw(st.sampled_from(["damage", "damage", "delete", "empty", "json"]))
    data = (session / name).read_bytes()
    if action == "delete":
        return name, None
    if action == "empty":
        return name, b""
    if action == "json" and name == "manifest.json":  # valid JSON, one value of the wrong type or size
        manifest = json.loads(data)
        key = draw(st.sampled_from(sorted(manifest)))
        manifest[key] = draw(st.sampled_from([None, -1, 0, 2**63, 1e308, "x", [], {}, [1, 2], True]))
        return name, json.dumps(manifest).encode()
    return name, draw(damaged(data))


@settings(FUZZ, max_examples=50)
@given(st.data())
def test_damaged_sessions(
    session: Path, replay_config: Path, tmp_path_factory: pytest.TempPathFactory, data: st.DataObject
) -> None:
    """Each file of a recorded session flipped, cut, emptied, deleted (the manifest also given wrong values):
    `mocapd session`, `replay` and `export` answer with notes and exit 0, or one error line and exit 2."""
    name, new = data.draw(session_damage(session))
    copy = tmp_path_factory.mktemp("damaged") / "session"
    shutil.copytree(session, copy)
    if new is None:
        (copy / name).unlink()
    else:
        (copy / name).write_bytes(new)
    out = copy.parent
    for argv in (["session", str(copy)],
                 ["replay", str(copy), "--speed", "1000", "--config", str(replay_config)],
                 ["export", str(copy), "--csv", str(out / "x.csv"), "--gltf", str(out / "x.glb")]):  # fmt: skip
        assert_clear(*run_cli(argv))


@pytest.mark.parametrize("name", SESSION_FILES)
@pytest.mark.parametrize("action", ["flip", "delete", "empty"])
def test_resolve_on_damaged_sessions(session: Path, tmp_path: Path, name: str, action: str) -> None:
    """`mocapd resolve` (a few iterations) on each file flipped, deleted or emptied in turn."""
    copy = tmp_path / "session"
    shutil.copytree(session, copy)
    path = copy / name
    if action == "delete":
        path.unlink()
    elif action == "empty":
        path.write_bytes(b"")
    else:
        data = bytearray(path.read_bytes())
        for k in range(30):
            data[(k * 7919) % len(data)] ^= 0xFF
        path.write_bytes(bytes(data))
    code, err = run_cli(["resolve", str(copy), "--iterations", "2", "--no-smooth", "-o", str(tmp_path / "r.mcs")])
    assert_clear(code, err)
    if (name in ("manifest.json", "prior.npz", "keypoints.mcs") and action != "flip") or name == "manifest.json":
        # the rig, the prior, the camera evidence: nothing to re-solve without them
        assert code == 2 and name in err.strip().splitlines()[-1], err


# --- the rows


def _flip(path: Path, n: int = 30) -> None:
    data = bytearray(path.read_bytes())
    for k in range(n):
        data[(k * 104729) % len(data)] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.fixture
def copy(session: Path, tmp_path: Path) -> Path:
    out = tmp_path / "session"
    shutil.copytree(session, out)
    return out


@pytest.mark.parametrize("command", ["session", "replay", "resolve", "export"])
def test_d8_a_flipped_manifest_is_one_error_line(copy: Path, replay_config: Path, tmp_path: Path, command: str) -> None:
    """D8: 30 flipped bytes in manifest.json were a UnicodeDecodeError traceback in all four commands."""
    _flip(copy / "manifest.json")
    extra = {"session": [], "replay": ["--speed", "1000", "--config", str(replay_config)],
             "resolve": ["-o", str(tmp_path / "r.mcs")], "export": ["--csv", str(tmp_path / "x.csv")]}  # fmt: skip
    code, err = run_cli([command, str(copy), *extra[command]])
    assert code == 2 and err.strip().splitlines()[-1].startswith(f"error: {copy / 'manifest.json'}: damaged"), err


@pytest.mark.parametrize("command", ["replay", "resolve"])
def test_d9_a_damaged_prior_is_one_error_line(copy: Path, replay_config: Path, tmp_path: Path, command: str) -> None:
    """D9: flipped bytes in the session's prior file were a traceback in replay and resolve; `mocapd session`
    now says so too."""
    _flip(copy / "prior.npz", 5)
    extra = ["--speed", "1000", "--config", str(replay_config)] if command == "replay" else ["-o", str(tmp_path / "r")]
    code, err = run_cli([command, str(copy), *extra])
    assert code == 2 and err.strip().splitlines()[-1].startswith(f"error: {copy / 'prior.npz'}: cannot read"), err
    code, err = run_cli(["session", str(copy)])
    assert code == 0 and f"note: {copy / 'prior.npz'}: cannot read" in err


@pytest.mark.parametrize("how", ["missing", "empty"])
def test_d10_a_missing_or_empty_pose_stream_is_named(copy: Path, replay_config: Path, tmp_path: Path, how: str) -> None:
    """D10: without poses.mcs (or with a zero-length one) `mocapd session` said nothing and `replay` exited 0 having
    sent 0 frames. Now session names it, replay and export stop with one line naming it."""
    poses = copy / "poses.mcs"
    if how == "missing":
        poses.unlink()
    else:
        poses.write_bytes(b"")
    code, err = run_cli(["session", str(copy)])
    assert code == 0 and f"note: {poses}: {how}" in err, err
    for argv in (["replay", str(copy), "--speed", "1000", "--config", str(replay_config)],
                 ["export", str(copy), "--csv", str(tmp_path / "x.csv")]):  # fmt: skip
        code, err = run_cli(argv)
        assert code == 2 and err.strip().splitlines()[-1].startswith(f"error: {poses}: {how}"), err


def test_resolve_without_the_recorded_keypoints_refuses(copy: Path, tmp_path: Path) -> None:
    """Found by the fuzzer: a camera session's resolve without keypoints.mcs ran and wrote a different, IMU-only
    answer with exit 0."""
    (copy / "keypoints.mcs").unlink()
    code, err = run_cli(["resolve", str(copy), "-o", str(tmp_path / "r.mcs")])
    assert code == 2 and "keypoints.mcs: missing" in err.strip().splitlines()[-1], err


# ---------------------------------------------------------------------------------------------- calibration files
@pytest.fixture(scope="module")
def calibrations(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The demo's Qualisys calibration and its conversions: every format `calibrate convert` reads."""
    out = tmp_path_factory.mktemp("calib")
    qca = out / "Calib.qca.txt"
    shutil.copy(demo_calibration("Demo_MultiPerson"), qca)
    files = {"qca": qca, "mocapd": out / "calibration.toml", "pose2sim": out / "Calib_pose2sim.toml",
             "opencv-yaml": out / "calibration.yml"}  # fmt: skip
    for fmt in ("mocapd", "pose2sim", "opencv-yaml"):
        assert run_cli(["calibrate", "convert", str(qca), str(files[fmt]), "--to", fmt])[0] == 0
    return files


@settings(FUZZ, max_examples=120)
@given(st.sampled_from(["qca", "mocapd", "pose2sim", "opencv-yaml"]), st.data())
def test_damaged_calibration_files(
    calibrations: dict[str, Path], tmp_path_factory: pytest.TempPathFactory, fmt: str, data: st.DataObject
) -> None:
    src = calibrations[fmt]
    path = tmp_path_factory.mktemp("c") / src.name
    path.write_bytes(data.draw(damaged(src.read_bytes())))
    assert_clear(*run_cli(["calibrate", "convert", str(path), str(path.parent / "out.toml")]))


@pytest.mark.parametrize(
    ("fmt", "damage"),
    [("pose2sim", b"\xf4"), ("mocapd", b"\xf4"), ("opencv-yaml", b"\n: ["), ("opencv-yaml", b"]]")],
)
def test_calibration_files_the_fuzzer_broke(
    calibrations: dict[str, Path], tmp_path: Path, fmt: str, damage: bytes
) -> None:
    """Found by the fuzzer: a non-UTF-8 byte in a TOML calibration (UnicodeDecodeError) and a YAML syntax error
    (cv2.error through SystemError) escaped as tracebacks; `calibrate convert` also said 'cannot read' with exit 1."""
    src = calibrations[fmt]
    data = src.read_bytes()
    path = tmp_path / src.name
    path.write_bytes(data[: len(data) // 2] + damage + data[len(data) // 2 :])
    with pytest.raises(MocapdError):
        read_any(path)
    code, err = run_cli(["calibrate", "convert", str(path), str(tmp_path / "out.toml")])
    assert code == 2 and err.strip().splitlines()[-1].startswith(f"error: cannot read {path}"), err


# ---------------------------------------------------------------------------------------------- motion files
def _head(path: Path, lines: int) -> bytes:
    return b"".join(path.read_bytes().splitlines(keepends=True)[:lines])


MOTION: dict[str, tuple[Callable[[], bytes], Callable[[Path], Any], str]] = {
    "bvh": ((DATA / "mocap/bandai/dataset-1_bow_angry_001.bvh").read_bytes, read_bvh, "x.bvh"),
    "asf": ((DATA / "mocap/cmu/asfamc/02.asf").read_bytes, read_asf, "x.asf"),
    "amc": (lambda: _head(DATA / "mocap/cmu/asfamc/02_01.amc", 300),
            lambda p: read_amc(p, read_asf(DATA / "mocap/cmu/asfamc/02.asf")), "x.amc"),
    "mvnx": ((DATA / "imu/mvnx/mpiea_upperbody_test_mocap.mvnx").read_bytes, read_mvnx, "x.mvnx"),
    "mt": ((MTW / "MT_012005D6_009-001_00B421E6.txt").read_bytes, read_mt_export,
           "MT_012005D6_009-001_00B421E6.txt"),
}  # fmt: skip
ORIGINALS: dict[str, bytes] = {}


@settings(FUZZ, max_examples=150)
@given(st.sampled_from(sorted(MOTION)), st.data())
def test_damaged_motion_files(tmp_path_factory: pytest.TempPathFactory, kind: str, data: st.DataObject) -> None:
    """BVH, ASF, AMC, MVNX and MT Manager exports damaged: each reader returns a motion or raises InputError."""
    load, read, name = MOTION[kind]
    if kind not in ORIGINALS:
        ORIGINALS[kind] = load()
    path = tmp_path_factory.mktemp(kind) / name
    path.write_bytes(data.draw(damaged(ORIGINALS[kind])))
    with contextlib.suppress(InputError):
        read(path)


@pytest.mark.parametrize(
    ("kind", "find", "replace"),
    [("bvh", b"Frame Time:", b"Frame Time: x"), ("asf", b"length ", b"length 7.2\x00"),
     ("amc", b"lradius ", b"lradius 1.\xff"), ("mvnx", b'<sensorOrientation>', b"<sensorOrientation>1 2 ")],
)  # fmt: skip
def test_motion_files_the_fuzzer_broke(tmp_path: Path, kind: str, find: bytes, replace: bytes) -> None:
    """Found by the fuzzer: a number that does not parse (BVH, ASF, AMC: ValueError) or a frame with a wrong count
    of numbers (MVNX: ValueError from reshape) escaped the readers."""
    load, read, name = MOTION[kind]
    path = tmp_path / name
    path.write_bytes(load().replace(find, replace, 1))
    with pytest.raises(InputError, match="malformed"):
        read(path)


@settings(FUZZ, max_examples=15)
@given(st.data())
def test_import_mtw_with_damaged_exports(tmp_path_factory: pytest.TempPathFactory, data: st.DataObject) -> None:
    """`mocapd import mtw` on the two real MT Manager exports, one of them damaged."""
    folder = tmp_path_factory.mktemp("mtw")
    files = sorted(MTW.glob("MT_*.txt"))
    hit = data.draw(st.sampled_from(files))
    for f in files:
        (folder / f.name).write_bytes(data.draw(damaged(f.read_bytes())) if f == hit else f.read_bytes())
    argv = ["import", "mtw", *map(str, sorted(folder.glob("MT_*.txt"))), "-o", str(folder / "session"),
            "--assign", "00B421E6=Hips", "--assign", "00B421ED=RightUpperLeg"]  # fmt: skip
    assert_clear(*run_cli(argv))


# ---------------------------------------------------------------------------------------------- manifest values
def _set(doc: Any, path: tuple[str | int, ...], value: Any) -> None:
    for part in path[:-1]:
        doc = doc[part]
    doc[path[-1]] = value


def _leaves(doc: Any, path: tuple[str | int, ...] = ()) -> list[tuple[str | int, ...]]:
    """Every value's path in a manifest, arrays of numbers (matrices, offsets) as one value each."""
    if isinstance(doc, dict):
        return [p for k, v in doc.items() for p in _leaves(v, (*path, k))]
    if isinstance(doc, list) and doc and any(isinstance(v, dict | list) for v in doc):
        return [p for i, v in enumerate(doc) for p in _leaves(v, (*path, i))]
    return [path]


MANIFEST_EXTREMES = [math.nan, math.inf, -math.inf, 0, -1, 2**63, 1e308, 1e-300, "x", None, True, [], {},
                     [math.nan] * 3, [0] * 10_000]  # fmt: skip


@settings(FUZZ, max_examples=120)
@given(st.data())
def test_manifest_values_mutated_to_the_extremes(
    session: Path, tmp_path_factory: pytest.TempPathFactory, data: st.DataObject
) -> None:
    """One value anywhere in the manifest (the scheduler's numbers, a camera's matrices, the skeleton, a suit's
    calibration, the synthetic world) set to an extreme (JSON carries NaN and Infinity too): the session opens
    and its rig rebuilds, or one InputError naming a file of the session. Library calls: what every command
    does first (session, replay, resolve and export alike)."""
    manifest = json.loads((session / "manifest.json").read_text())
    leaves = [p for p in _leaves(manifest) if p[:1] not in (("config",), ("format",))]  # config: fuzzed above
    path = data.draw(st.sampled_from(leaves))
    value = data.draw(st.sampled_from(MANIFEST_EXTREMES))
    _set(manifest, path, value)
    copy = tmp_path_factory.mktemp("manifest") / "session"
    shutil.copytree(session, copy)
    (copy / "manifest.json").write_text(json.dumps(manifest))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # nan or inf computed from a value: a silent wrong rig
            s = open_session(copy)
            rig = session_rig(s)
            solve_times(s, rig.options.rate_hz)
            synthetic_of(s)
    except InputError as exc:
        assert str(copy) in str(exc) and "\n" not in str(exc), str(exc)


@pytest.mark.parametrize(
    ("path", "value", "problem"),
    [
        (("scheduler", "rate_hz"), 0, "scheduler.rate_hz = 0; allowed"),  # ZeroDivisionError in resolve
        (("scheduler", "rate_hz"), math.nan, "scheduler.rate_hz = nan; allowed"),  # ValueError in resolve
        (("scheduler", "rate_hz"), -60.0, "scheduler.rate_hz = -60.0; allowed"),  # resolve solved nothing, exit 0
        (("scheduler", "latency_ns"), math.inf, "scheduler.latency_ns = inf; allowed"),  # OverflowError in all four
        (("scheduler", "imu_offsets_ns"), {"X": math.inf}, "scheduler.imu_offsets_ns.X = inf; allowed"),
        (("targets", "bones", 0), 10**6, "track target bones must be bone indices"),  # IndexError in resolve
        (("config", "imu"), {"buffer_capacity": 2**63, "baudrate": -1}, "its copy of the config: "),  # 2 lines
        (("cameras", 0, "width"), 0, "camera 'cam0': image size must be positive"),  # did not name the manifest
        (("skeleton", "height"), math.nan, "skeleton root_height and height must be finite"),  # nan IMU mounts
    ],
    ids=[
        "rate-0",
        "rate-nan",
        "rate-negative",
        "latency-inf",
        "imu-offset-inf",
        "bone-index",
        "config",
        "camera",
        "height-nan",
    ],
)
@pytest.mark.parametrize("command", ["replay", "resolve"])
def test_manifest_values_the_fuzzer_broke(
    copy: Path, replay_config: Path, tmp_path: Path, command: str, path: tuple[str | int, ...], value: Any,
    problem: str,
) -> None:  # fmt: skip
    """Found by the manifest fuzzer: numbers JSON carries (NaN, Infinity, 0) or indices out of range escaped as
    ZeroDivisionError, OverflowError, ValueError or IndexError tracebacks; a bad config copy, camera or suit in
    the manifest was an error (or several lines) that did not say it came from the manifest."""
    manifest = json.loads((copy / "manifest.json").read_text())
    _set(manifest, path, value)
    (copy / "manifest.json").write_text(json.dumps(manifest))
    extra = {"replay": ["--speed", "1000", "--config", str(replay_config)],
             "resolve": ["--iterations", "1", "-o", str(tmp_path / "r.mcs")]}[command]  # fmt: skip
    code, err = run_cli([command, str(copy), *extra])
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"error: {copy / 'manifest.json'}: damaged") and problem in err, err


@pytest.mark.parametrize(
    ("path", "value"),
    [(("extra",), "synthetic"), (("extra", "synthetic"), "x"), (("extra", "synthetic", "camera_names"), ["a"])],
    ids=["extra-a-string", "synthetic-a-string", "camera-names-short"],
)
def test_a_damaged_synthetic_table_is_a_note_in_resolve(
    copy: Path, tmp_path: Path, path: tuple[str, ...], value: Any
) -> None:
    """Found by the manifest fuzzer: resolve's error against the synthetic truth read extra.synthetic unchecked
    (TypeError or ValueError tracebacks after the resolved stream was written; a count of a million people
    would build a world of a million people). Now the solve runs and a note says why there is no truth report."""
    manifest = json.loads((copy / "manifest.json").read_text())
    _set(manifest, path, value)
    (copy / "manifest.json").write_text(json.dumps(manifest))
    code, err = run_cli(["resolve", str(copy), "--iterations", "1", "--no-smooth", "-o", str(tmp_path / "r.mcs")])
    assert code == 0 and "Traceback" not in err, err
    if path != ("extra",):  # a string there is no synthetic table at all: nothing to note
        assert f"note: {copy / 'manifest.json'}: damaged: extra.synthetic" in err, err
    assert synthetic_of(open_session(copy)) is None if path == ("extra",) else True


@pytest.mark.parametrize("name", ["poses.mcs", "imu.mcs", "keypoints.mcs"])
def test_a_stream_that_is_a_directory_is_one_error_line(copy: Path, replay_config: Path, name: str) -> None:
    """Found by hand beside the fuzzer: a directory named like a stream was an IsADirectoryError traceback."""
    (copy / name).unlink()
    (copy / name).mkdir()
    for argv in (["session", str(copy)], ["replay", str(copy), "--speed", "1000", "--config", str(replay_config)]):
        code, err = run_cli(argv)
        assert (code, err) == (2, f"error: {copy / name}: not a regular file, not a session stream\n")


PAYLOADS = {
    "poses.mcs": (T_POSE, b"\xff" * 40),  # counts say 65535 people: struct.error
    "imu.mcs": (T_IMU, bytes(28) + b"\x05\x00" + b"\xff" * 60),  # a sensor id that is not UTF-8
    "keypoints.mcs": (T_KEYPOINTS, bytes(10)),  # shorter than its header: struct.error
}


@settings(FUZZ, max_examples=200)
@given(st.sampled_from([decode_pose, decode_imu, decode_keypoints, decode_frame]), st.binary(max_size=2000))
def test_record_payloads_decode_or_raise_input_error(decode: Callable[[bytes], Any], payload: bytes) -> None:
    """A record whose CRC is intact holds any bytes (written by another tool, or a CRC collision): its payload
    decoder returns a record or raises InputError, nothing else."""
    with contextlib.suppress(InputError):
        decode(payload)


@pytest.mark.parametrize("name", list(PAYLOADS))
def test_an_intact_record_that_does_not_decode_is_counted_and_skipped(
    copy: Path, replay_config: Path, tmp_path: Path, name: str
) -> None:
    """Found by the payload fuzzer: a record with a valid CRC but a payload mocapd did not write escaped the
    session reader as struct.error / UnicodeDecodeError in every command. Now it is counted in the stream's
    report (``undecodable``) and skipped, like a corrupt record."""
    frames = len(open_session(copy).poses())
    rtype, payload = PAYLOADS[name]
    with (copy / name).open("ab") as fh:
        fh.write(encode_record(rtype, payload))
    session = open_session(copy)
    assert len(session.poses()) == frames and len(session.imu()) > 0 and len(session.keypoints()) > 0
    assert session.reports[name.removesuffix(".mcs")].undecodable == 1
    code, err = run_cli(["replay", str(copy), "--speed", "1000", "--config", str(replay_config)])
    assert code == 0 and "Traceback" not in err, err
    code, err = run_cli(["resolve", str(copy), "--iterations", "1", "--no-smooth", "-o", str(tmp_path / "r.mcs")])
    assert code == 0 and f"note: {copy / name}: 1 intact records did not decode (skipped)" in err, err


# ---------------------------------------------------------------------------------------------- motion file values
_NUMBER = re.compile(rb"(?<![\w.])-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?(?![\w.])")
NUMBER_EXTREMES = [b"nan", b"inf", b"-inf", b"0", b"-1", b"-5", b"1e-300", b"1e308", b"9223372036854775807"]


def _finite(result: Any) -> bool:
    """Every number a reader returned is finite (a motion's arrays and rate, a skeleton's bones and scale)."""
    if isinstance(result, AsfSkeleton):
        return math.isfinite(result.length_scale) and all(
            np.isfinite(b.direction).all() and math.isfinite(b.length) for b in result.bones
        )
    arrays = [v for v in vars(result).values() if isinstance(v, np.ndarray) and v.dtype.kind == "f"]
    fps = float(result.rate_hz if isinstance(result, MtExport) else result.fps)
    if isinstance(result, MtExport):  # device counters: the unwrapped ticks only ever grow (no int64 garbage)
        arrays += [np.diff(c).astype(np.float64) for c in (result.ticks, result.counter) if c is not None]
        if any((np.diff(c) < 0).any() for c in (result.ticks, result.counter) if c is not None):
            return False
    return math.isfinite(fps) and 0 < fps <= 10_000 and all(np.isfinite(a).all() for a in arrays)


@settings(FUZZ, max_examples=150)
@given(st.sampled_from(["bvh", "asf", "amc", "mvnx", "mt"]), st.data())
def test_motion_file_numbers_set_to_the_extremes(
    tmp_path_factory: pytest.TempPathFactory, kind: str, data: st.DataObject
) -> None:
    """Structure-aware: one number of a real file (its hierarchy, units, rate, frame count or a value) replaced by
    an extreme. The reader raises InputError or returns only finite numbers and a plausible rate — never a
    silent NaN skeleton or a 1e300 Hz motion."""
    load, read, name = MOTION[kind]
    if kind not in ORIGINALS:
        ORIGINALS[kind] = load()
    text = ORIGINALS[kind][:200_000] if kind != "mvnx" else ORIGINALS[kind]  # the hierarchy and first frames
    numbers = [m.span() for m in _NUMBER.finditer(text)][:3000]
    start, end = data.draw(st.sampled_from(numbers))
    value = data.draw(st.sampled_from(NUMBER_EXTREMES))
    path = tmp_path_factory.mktemp(kind) / name
    path.write_bytes(ORIGINALS[kind][:start] + value + ORIGINALS[kind][end:])
    try:
        result = read(path)
    except InputError:
        return
    assert _finite(result), f"{kind}: {text[max(0, start - 40) : end + 20]!r} -> {value!r} gave non-finite numbers"


@pytest.mark.parametrize(
    ("kind", "pattern", "value", "problem"),
    [
        ("bvh", rb"Frame Time:\s*\S+", b"Frame Time: 1e-300", "frame time must be in"),  # fps = 1e300
        ("bvh", rb"Frames:\s*\d+", b"Frames: -5", "Frames: -5"),  # the last 2 frames silently dropped
        ("bvh", rb"OFFSET\s+\S+", b"OFFSET nan", "non-finite OFFSET"),  # a nan offset sized the skeleton
        ("asf", rb"length\s+\S+\s*\n\s*axis", b"length nan\n axis", "non-finite direction or length"),
        ("asf", rb"direction\s+\S+", b"direction inf", "non-finite direction or length"),
        ("asf", rb":units\s+mass\s+\S+\s+length\s+\S+", b":units\n  mass 1.0\n  length 0", "':units length 0"),
        ("mvnx", rb'(type="tpose">\s*<orientation>)\S+', rb"\1nan", "non-finite values"),  # the T-pose frame
        ("mt", rb"\n00473\t", b"\n1e308\t", "PacketCounter = 1e+308 in data row 2"),  # int64 garbage counter
    ],
    ids=[
        "bvh-frame-time",
        "bvh-frames-negative",
        "bvh-offset-nan",
        "asf-bone-length",
        "asf-direction",
        "asf-unit",
        "mvnx-tpose",
        "mt-counter",
    ],
)
def test_motion_file_values_the_fuzzer_broke(
    tmp_path: Path, kind: str, pattern: bytes, value: bytes, problem: str
) -> None:
    """Found by the structure-aware motion fuzzer: values every reader accepted silently (a rate of 1e300 Hz,
    frames dropped by a negative count, nan bone offsets, directions and lengths, a zero length unit that scaled
    every bone to infinity)."""
    load, read, name = MOTION[kind]
    original = load()
    assert re.search(pattern, original), pattern
    path = tmp_path / name
    path.write_bytes(re.sub(pattern, value, original, count=1))
    with pytest.raises(InputError, match=re.escape(problem)):
        read(path)


# ---------------------------------------------------------------------------------------------- calibration values
def _plausible(calib: Any) -> bool:
    """Every camera of a calibration that was read is usable: finite numbers, positive focal lengths and size."""
    return all(
        np.isfinite(c.K).all() and np.isfinite(c.dist).all() and np.isfinite(c.R).all() and np.isfinite(c.t).all()
        and c.K[0, 0] > 0 and c.K[1, 1] > 0 and c.size[0] > 0 and c.size[1] > 0
        and (c.error_px is None or (math.isfinite(c.error_px) and c.error_px >= 0))
        for c in calib.cameras
    )  # fmt: skip


@settings(FUZZ, max_examples=120)
@given(st.sampled_from(["qca", "mocapd", "pose2sim", "opencv-yaml"]), st.data())
def test_calibration_numbers_set_to_the_extremes(
    calibrations: dict[str, Path], tmp_path_factory: pytest.TempPathFactory, fmt: str, data: st.DataObject
) -> None:
    """Structure-aware: one number of a valid calibration file of each format (a focal length, a distortion
    coefficient, a rotation, a translation, the image size, the error) replaced by an extreme: the reader raises
    the project's error or returns only usable cameras — never a nan distortion or a zero-pixel image."""
    src = calibrations[fmt]
    original = src.read_bytes()
    numbers = [m.span() for m in _NUMBER.finditer(original)]
    start, end = data.draw(st.sampled_from(numbers))
    value = data.draw(st.sampled_from(NUMBER_EXTREMES))
    path = tmp_path_factory.mktemp("cv") / src.name
    path.write_bytes(original[:start] + value + original[end:])
    try:
        calib = read_any(path)
    except MocapdError:
        return
    context = original[max(0, start - 40) : end + 10]
    assert _plausible(calib), f"{fmt}: {context!r} -> {value!r} was accepted"


@pytest.mark.parametrize(
    ("fmt", "find", "replace", "problem"),
    [
        ("pose2sim", b"distortions = [-0.046183,", b"distortions = [nan,", "non-finite calibration values"),
        ("pose2sim", b"size = [1088.0, 1920.0]", b"size = [0.0, 1920.0]", "image size 0x1920"),
        ("pose2sim", b"matrix = [[1681.244873046875,", b"matrix = [[-1681.2,", "focal lengths must be positive"),
        ("qca", b'<fov_video bottom="1919"', b'<fov_video bottom="inf"', "OverflowError"),
        ("mocapd", b'name = "cam01"\n', b'name = "cam01"\nreprojection_error_px = -1.0\n', "reprojection error -1.0"),
    ],
    ids=["dist-nan", "size-0", "focal-negative", "qca-size-inf", "error-negative"],
)
def test_calibration_values_the_fuzzer_broke(
    calibrations: dict[str, Path], tmp_path: Path, fmt: str, find: bytes, replace: bytes, problem: str
) -> None:
    """Found by the structure-aware calibration fuzzer: a nan distortion coefficient, a zero image size, a negative
    focal length or reprojection error were accepted; an infinite QCA image bound escaped as OverflowError."""
    src = calibrations[fmt]
    data = src.read_bytes()
    assert find in data, find
    path = tmp_path / src.name
    path.write_bytes(data.replace(find, replace, 1))
    with pytest.raises(CalibrationError, match=re.escape(problem)):
        read_any(path)


@pytest.mark.parametrize(
    ("find", "replace"),
    [(b"rows: 3\n   cols: 1\n", b"rows: 3\n   cols: -1\n"), (b"sizes: [ 2 ]", b"sizes: [ 7 ]"),
     (b"rows: 3\n   cols: 1\n", b"rows: 3\n   cols: 9223372036854775807\n"), (b"dt: d", b"dt: x")],
    ids=["cols-negative", "sizes-wrong", "cols-2**63", "dt-unknown"],
)  # fmt: skip
def test_an_opencv_matrix_header_that_disagrees_with_its_data_is_one_error_line(
    calibrations: dict[str, Path], tmp_path: Path, find: bytes, replace: bytes
) -> None:
    """Found by the calibration fuzzer: OpenCV's FileNode.mat() trusts a matrix's rows/cols/sizes. With
    `cols: 2**63-1` a bare `read_any` aborted the process (malloc(): invalid size, SIGABRT: no except can catch
    it), and a run of bad headers in one process (cols 0, -1, sizes -5) corrupted the heap until a later read
    aborted or segfaulted; through `calibrate convert` each was a garbled multi-line cv2 assertion. Now it exits 2
    with one line, the header checked before OpenCV reads the data; the case that aborted runs in a child process,
    as a user runs it (an abort there fails this test instead of ending the test run)."""
    src = calibrations["opencv-yaml"]
    data = src.read_bytes()
    assert find in data, find
    path = tmp_path / src.name
    path.write_bytes(data.replace(find, replace, 1))
    argv = ["calibrate", "convert", str(path), str(tmp_path / "o.toml")]
    if b"9223372036854775807" in replace:
        proc = subprocess.run([sys.executable, "-m", "mocapd", *argv],
                              check=False, capture_output=True, text=True, timeout=120)  # fmt: skip
        code, err = proc.returncode, proc.stderr
    else:
        code, err = run_cli(argv)
    assert code == 2, (code, err[-2000:])
    assert err.count("\n") == 1 and err.startswith(f"error: cannot read {path}"), err


def test_huge_channel_values_are_refused_before_the_rotation_math(tmp_path: Path) -> None:
    """A finite but absurd channel value (1e308 degrees) is refused by the reader itself, not left to become NaN
    (with numpy's RuntimeWarnings) in the Euler-angle conversion and be caught later."""
    bvh = (DATA / "mocap/bandai/dataset-1_bow_angry_001.bvh").read_text()
    head, frames = bvh.split("Frame Time:", 1)
    time_line, first, *rest = frames.split("\n")
    values = first.split()
    values[5] = "1e308"
    path = tmp_path / "x.bvh"
    path.write_text("\n".join([head + "Frame Time:" + time_line, " ".join(values), *rest]))
    with pytest.raises(InputError, match="within"):
        read_bvh(path)
    amc = _head(DATA / "mocap/cmu/asfamc/02_01.amc", 60).replace(b"lradius ", b"lradius 1e308 ", 1)
    (tmp_path / "x.amc").write_bytes(amc)
    with pytest.raises(InputError, match="within"):
        read_amc(tmp_path / "x.amc", read_asf(DATA / "mocap/cmu/asfamc/02.asf"))
