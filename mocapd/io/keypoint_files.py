"""Reading other detectors' 2D keypoint files from disk: one camera per folder or file (``mocapd import keypoints``).

The parsing is :mod:`mocapd.protocols.keypoint_files`; this module finds the files, numbers the frames and says
which camera each input is. Layouts (``--format``, else told from the path):

* ``openpose``: a folder of per-frame files ``<anything><frame>_keypoints.json`` (OpenPose ``--write_json``,
  Pose2Sim, RTMLib); the frame number is the last run of digits in the name (else the files' sorted order);
* ``mmpose``: one prediction file of a video (``.json``), or a folder of per-frame prediction files
  (``pred_out_dir``), numbered as OpenPose's;
* ``pose2sim``: a Pose2Sim project folder: ``pose/<camera>_json/`` OpenPose folders, the calibration in
  ``calibration/`` (``Calib*.toml``, else a ``.qca.txt``) and the frame rate in ``Config.toml``;
* ``mediapipe``: MediaPipe Pose landmarks (normalised x, y and visibility, :func:`~mocapd.protocols.keypoint_files.
  parse_mediapipe`): one file of a video's frames or a folder of per-frame files (told by their landmark fields);
* ``freemocap``: FreeMoCap's ``mediapipe2dData_numCams_numFrames_numTrackedPoints_pixelXY.npy`` (every camera in
  one array, BlazePose's body landmarks first).

A camera's name is the input's: ``NAME=PATH`` names it, else the folder's or file's name without ``_json``,
``_keypoints`` or an extension (``cam01_json`` -> ``cam01``); :func:`match_cameras` pairs the names with the
calibration's.
"""

from __future__ import annotations

import io
import json
import re
import tomllib
import zipfile
from dataclasses import dataclass
from pathlib import Path
from tokenize import TokenError  # numpy's header parser raises it for a damaged .npy header

import numpy as np

from mocapd.errors import InputError
from mocapd.io.input_files import open_input, read_input_bytes
from mocapd.protocols.keypoint_files import (
    ParsedFrames,
    parse_landmark_array,
    parse_mediapipe,
    parse_mmpose,
    parse_openpose,
    parse_timestamps,
)

FORMATS = ("auto", "openpose", "mmpose", "pose2sim", "freemocap", "mediapipe")
MAX_FRAME_FILE_BYTES = 16 << 20
"""Largest per-frame JSON file read (OpenPose's with faces and hands of a crowd is a few hundred KB)."""
MAX_VIDEO_FILE_BYTES = 1 << 30
"""Largest one-file prediction of a whole video (MMPose's JSON; FreeMoCap's array)."""
MAX_FILES = 1_000_000
MIN_FPS, MAX_FPS = 1.0, 500.0
"""Frame rates accepted (the daemon's output rates: one solve per frame)."""
_DIGITS = re.compile(r"(\d+)(?!.*\d)")


@dataclass
class CameraKeypoints:
    """One camera's detections as read: its name (from the path), where from, and the frames."""

    name: str
    source: Path
    parsed: ParsedFrames


@dataclass
class KeypointInput:
    """What a set of inputs holds: the cameras, and what a Pose2Sim project also gives."""

    cameras: list[CameraKeypoints]
    layout: str
    calibration: Path | None = None
    fps: float | None = None


def camera_name(path: Path) -> str:
    """``cam01_json`` -> ``cam01``, ``cam2_keypoints.json`` -> ``cam2``, ``results_cam3.json`` -> ``cam3``."""
    name = path.name
    for suffix in (".json", ".npy"):
        name = name.removesuffix(suffix)
    for suffix in ("_json", "_keypoints", "_predictions", "_results"):
        name = name.removesuffix(suffix)
    return name.removeprefix("results_").removeprefix("predictions_") or path.name


def _json(path: Path, max_bytes: int) -> object:
    data = read_input_bytes(path, "keypoint file", max_bytes=max_bytes)
    try:
        return json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{path}: not JSON: {exc}") from None


def _frame_files(folder: Path) -> list[tuple[int, Path]]:
    files = [f for f in folder.iterdir() if f.suffix.lower() == ".json" and f.is_file()]
    if not files:
        raise InputError(f"{folder}: no .json keypoint files")
    if len(files) > MAX_FILES:
        raise InputError(f"{folder}: {len(files)} files; at most {MAX_FILES}")
    numbered = [(_number(f), f) for f in files]
    if any(n is None for n, _ in numbered) or len({n for n, _ in numbered}) != len(files):
        return list(enumerate(sorted(files)))  # no frame numbers in the names (or repeated ones): their order
    return sorted((n, f) for n, f in numbered if n is not None)


def _number(path: Path) -> int | None:
    m = _DIGITS.search(path.name.removesuffix(".json").removesuffix("_keypoints"))
    return int(m.group(1)) if m else None


def _merge(folder: Path, parts: list[tuple[int, ParsedFrames]]) -> ParsedFrames:
    normalized = any(p.normalized for _, p in parts)
    sets = {p.keypoint_set for _, p in parts if p.keypoint_set}
    if len(sets) > 1:
        raise InputError(f"{folder}: files of different keypoint sets {sorted(sets)}")
    name = sets.pop() if sets else ""
    frames = {}
    for n, p in parts:
        for k, v in p.frames.items():
            frames[n + k] = v if p.keypoint_set else (np.zeros((0, 0, 2)), np.zeros((0, 0)))
    return ParsedFrames(name, frames, normalized)


def read_openpose_folder(folder: Path, keypoint_set: str | None = None) -> ParsedFrames:
    """A folder of OpenPose per-frame files (see the module docstring)."""
    parts = [(n, parse_openpose(_json(f, MAX_FRAME_FILE_BYTES), keypoint_set, str(f))) for n, f in _frame_files(folder)]
    return _merge(folder, parts)


def read_mmpose(path: Path, keypoint_set: str | None = None) -> ParsedFrames:
    """An MMPose prediction file, or a folder of per-frame ones."""
    if path.is_dir():
        parts = [(n, parse_mmpose(_json(f, MAX_FRAME_FILE_BYTES), keypoint_set, str(f))) for n, f in _frame_files(path)]
        return _merge(path, parts)
    return parse_mmpose(_json(path, MAX_VIDEO_FILE_BYTES), keypoint_set, str(path))


def read_mediapipe(path: Path) -> ParsedFrames:
    """MediaPipe Pose landmarks: one file of a video's frames, or a folder of per-frame files."""
    if path.is_dir():
        parts = [(n, parse_mediapipe(_json(f, MAX_FRAME_FILE_BYTES), str(f))) for n, f in _frame_files(path)]
        return _merge(path, parts)
    return parse_mediapipe(_json(path, MAX_VIDEO_FILE_BYTES), str(path))


def read_freemocap(path: Path, keypoint_set: str | None = None) -> list[ParsedFrames]:
    """FreeMoCap's 2D array (``.npy``), one :class:`ParsedFrames` per camera."""
    data = read_input_bytes(path, "FreeMoCap 2D array", max_bytes=MAX_VIDEO_FILE_BYTES)
    try:
        arr = np.load(io.BytesIO(data), allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, TokenError) as exc:
        raise InputError(f"{path}: not a numpy array file: {exc}") from None
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "fiu":
        raise InputError(f"{path}: expected an array of numbers")
    return parse_landmark_array(arr.astype(np.float64), keypoint_set or "blazepose33", str(path))


def _layout(path: Path, layout: str) -> str:
    if layout != "auto":
        return layout
    if path.is_dir() and ((path / "pose").is_dir() or (path / "Config.toml").is_file()):
        return "pose2sim"  # a project: its keypoints in pose/ once Pose2Sim's pose estimation has run
    if path.suffix.lower() == ".npy":
        return "freemocap"
    if path.is_file():
        return "mediapipe" if _looks_mediapipe(path) else "mmpose"
    if path.is_dir():
        first = next((f for _, f in _frame_files(path)), None)
        doc = _json(first, MAX_FRAME_FILE_BYTES) if first is not None else None
        if isinstance(doc, dict) and "people" in doc:
            return "openpose"
        return "mediapipe" if first is not None and _looks_mediapipe(first) else "mmpose"
    raise InputError(f"{path}: no such file or folder")


def _looks_mediapipe(path: Path) -> bool:
    """Whether a JSON file's first 64 KB name MediaPipe's landmark fields (a whole video's file is not decoded
    twice to tell)."""
    with open_input(path, "keypoint file", max_bytes=MAX_VIDEO_FILE_BYTES) as fh:
        head = fh.read(1 << 16)
    return b'"visibility"' in head or b'"pose_landmarks"' in head or b'"landmark"' in head


def _named(spec: str) -> tuple[str | None, Path]:
    """``NAME=PATH`` or ``PATH``."""
    name, sep, rest = spec.partition("=")
    if sep and name and "/" not in name and not Path(spec).exists():
        return name, Path(rest)
    return None, Path(spec)


def read_keypoint_inputs(specs: list[str], layout: str = "auto", keypoint_set: str | None = None) -> KeypointInput:
    """Every camera of the inputs (``[NAME=]PATH``, one per camera; one Pose2Sim project or FreeMoCap array
    holds them all)."""
    if layout not in FORMATS:
        raise InputError(f"--format {layout!r}; choose from {', '.join(FORMATS)}")
    if not specs:
        raise InputError("no keypoint inputs given")
    named = [_named(s) for s in specs]
    layouts = {_layout(p, layout) for _, p in named}
    if len(layouts) > 1:
        raise InputError(f"inputs of different layouts {sorted(layouts)}: give one kind (or --format)")
    kind = layouts.pop()
    if kind in ("pose2sim", "freemocap") and len(named) != 1:
        raise InputError(f"a {kind} input holds every camera: give one, not {len(named)}")
    for _, p in named:
        if not p.exists():
            raise InputError(f"{p}: no such file or folder")
    if kind == "pose2sim":
        return read_pose2sim_project(named[0][1], keypoint_set)
    if kind == "freemocap":
        path = named[0][1]
        cams = [CameraKeypoints(f"cam{i}", path, p) for i, p in enumerate(read_freemocap(path, keypoint_set))]
        return KeypointInput(cams, kind)
    cams = []
    for name, p in named:
        if kind == "mediapipe":
            parsed = read_mediapipe(p)
        elif kind == "openpose":
            parsed = read_openpose_folder(p, keypoint_set)
        else:
            parsed = read_mmpose(p, keypoint_set)
        cams.append(CameraKeypoints(name or camera_name(p), p, parsed))
    return KeypointInput(cams, kind)


def read_new_frames(cam: CameraKeypoints, layout: str, keypoint_set: str | None, seen: set[str]) -> ParsedFrames:
    """The frames of a camera folder's files not in ``seen`` (their names, updated): a detector writing live.
    Only files whose name carries a frame number are read (the order of files still being written means nothing).
    """
    if not cam.source.is_dir():
        return ParsedFrames(cam.parsed.keypoint_set, {})
    parts = []
    for f in sorted(cam.source.iterdir()):
        if f.name in seen or f.suffix.lower() != ".json" or not f.is_file():
            continue
        n = _number(f)
        if n is None:
            continue
        try:
            doc = _json(f, MAX_FRAME_FILE_BYTES)
        except InputError:
            continue  # still being written: read at the next look
        seen.add(f.name)
        wanted = keypoint_set or cam.parsed.keypoint_set or None
        if layout == "mediapipe":
            parts.append((n, parse_mediapipe(doc, str(f))))
        elif layout in ("openpose", "pose2sim"):
            parts.append((n, parse_openpose(doc, wanted, str(f))))
        else:
            parts.append((n, parse_mmpose(doc, wanted, str(f))))
    return _merge(cam.source, parts)


def read_pose2sim_project(project: Path, keypoint_set: str | None = None) -> KeypointInput:
    """A Pose2Sim project folder (see the module docstring); the frame rate when ``Config.toml`` gives a number."""
    pose = project / "pose"
    if not pose.is_dir():
        raise InputError(f"{project}: a Pose2Sim project without keypoints (no pose/ folder): run Pose2Sim's pose "
                         "estimation first, or give another detector's files")  # fmt: skip
    folders = sorted(f for f in pose.iterdir() if f.is_dir())
    if not folders:
        raise InputError(f"{pose}: no camera folders (<camera>_json/ of OpenPose-style files: run Pose2Sim's pose "
                         "estimation first)")  # fmt: skip
    cams = [CameraKeypoints(camera_name(f), f, read_openpose_folder(f, keypoint_set)) for f in folders]
    calib_dir = project / "calibration"
    calib = None
    if calib_dir.is_dir():
        found = sorted(calib_dir.glob("Calib*.toml")) or sorted(calib_dir.glob("*.toml")) or sorted(
            calib_dir.glob("*.qca.txt"))  # fmt: skip
        calib = found[0] if found else None
    fps = None
    config = project / "Config.toml"
    if config.is_file():
        try:
            doc = tomllib.loads(read_input_bytes(config, "Pose2Sim config", max_bytes=1 << 20).decode())
        except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise InputError(f"{config}: not TOML: {exc}") from None
        rate = doc.get("project", {}).get("frame_rate") if isinstance(doc.get("project"), dict) else None
        fps = float(rate) if isinstance(rate, int | float) and not isinstance(rate, bool) and rate > 0 else None
    return KeypointInput(cams, "pose2sim", calib, fps)


def read_timestamps(specs: list[str]) -> dict[str | None, dict[int, float]]:
    """``--timestamps [CAMERA=]FILE``: per camera (None: every camera without its own), frame -> seconds."""
    out: dict[str | None, dict[int, float]] = {}
    for spec in specs:
        name, path = _named(spec)
        if name in out:
            raise InputError(f"--timestamps: {name or 'the cameras'} given twice")
        data = read_input_bytes(path, "timestamps file", max_bytes=MAX_VIDEO_FILE_BYTES)
        out[name] = parse_timestamps(data.decode("utf-8", errors="replace"), str(path))
    return out


def match_cameras(inputs: list[str], calibrated: list[str]) -> list[int]:
    """For each input camera name, the index of its calibrated camera: the same name, else the one calibrated name
    the input's name contains or is contained in (``cam01`` and ``cam01_img``), else (as many inputs as calibrated
    cameras, no name matching) the calibration's order."""
    out: list[int | None] = []
    for name in inputs:
        if name in calibrated:
            out.append(calibrated.index(name))
            continue
        near = [i for i, c in enumerate(calibrated) if c and (c in name or name in c)]
        out.append(near[0] if len(near) == 1 else None)
    taken = [i for i in out if i is not None]
    if len(set(taken)) != len(taken):
        raise InputError(f"input cameras {inputs} match the calibration's {calibrated} ambiguously: name them "
                         "(NAME=PATH, NAME a camera of the calibration)")  # fmt: skip
    if all(i is not None for i in out):
        return [i for i in out if i is not None]
    if not taken and len(inputs) == len(calibrated):
        return list(range(len(inputs)))
    missing = [n for n, i in zip(inputs, out, strict=True) if i is None]
    raise InputError(f"input camera(s) {missing} are not in the calibration, which has {calibrated}: name them "
                     "(NAME=PATH)")  # fmt: skip
