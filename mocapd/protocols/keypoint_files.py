"""The 2D keypoint files other detectors write, parsed from their decoded JSON (sans-I/O: no file is opened here).

OpenPose (``--write_json``, also Pose2Sim's ``pose/<camera>_json/`` folders and RTMLib's OpenPose-style output):
one file per frame, ``{"people": [{"pose_keypoints_2d": [x0, y0, c0, x1, ...]}, ...]}``, pixels of the image and
a confidence per point; a point not seen is ``0, 0, 0``. BODY_25 (75 numbers), COCO-18 (54) and, as Pose2Sim
writes them, COCO-17 (51), Halpe-26 (78), COCO-WholeBody (399) and BlazePose (99).

MMPose / RTMPose / RTMW, any of:

* a list of instances ``[{"keypoints": [[x, y], ...], "keypoint_scores": [...]}, ...]`` (one image:
  ``MMPoseInferencer(..., pred_out_dir=...)`` writes one such file per image or video frame);
* a list of frames ``[{"frame_id": 0, "instances": [...]}, ...]`` (the inferencer's predictions of a video);
* ``{"meta_info": {...}, "instance_info": [{"frame_id": 1, "instances": [...]}, ...]}``
  (``demo/topdown_demo_with_mmdet.py --save-predictions``; ``meta_info.dataset_name`` names the keypoint set);
* COCO results ``[{"image_id": 3, "keypoints": [x, y, s, ...], "score": 0.9}, ...]`` (``tools/test.py``),
  one frame per image id.

MediaPipe Pose (BlazePose's 33 landmarks, ``x``, ``y`` as fractions of the image, ``visibility``), as its results
are written out: one frame file holding ``{"landmark": [...]}`` (``MessageToDict`` of the legacy solution's
``pose_landmarks``), ``{"pose_landmarks": [[...], ...]}`` (the Tasks API's result, one list per person) or a list
of people; or one file of a video's frames, a list of such frames (or ``{"frames": [...]}``), frame ``i`` the
``i``-th (or its ``frame``/``frame_id``).

Each parser returns :class:`ParsedFrames`: per frame number, the people's keypoints and confidences in the file's
own keypoint set (:mod:`mocapd.core.keypoint_sets`), which it names when the file says or the count tells.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.keypoint_sets import SETS, set_for_count
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

MAX_PEOPLE = 1000
"""Most people one frame may hold (the session format's count is 16-bit; no detector reports more)."""

OPENPOSE_SETS = ("body25", "coco18", "coco17", "halpe26", "wholebody133", "blazepose33")
"""The sets an OpenPose-layout file may hold (told apart by their length)."""
MMPOSE_SETS = ("coco17", "halpe26", "wholebody133")
MMPOSE_DATASETS = {"coco": "coco17", "halpe26": "halpe26", "halpe": "halpe26", "coco_wholebody": "wholebody133",
                   "body8": "coco17", "body8_halpe26": "halpe26"}  # fmt: skip
"""MMPose's ``meta_info.dataset_name`` -> keypoint set."""


@dataclass
class ParsedFrames:
    """The detections of one camera.

    Attributes
    ----------
    keypoint_set : str
        The name in :data:`mocapd.core.keypoint_sets.SETS`.
    frames : dict frame number -> (keypoints (n_people, n_kp, 2), confidences (n_people, n_kp))
    """

    keypoint_set: str
    frames: dict[int, tuple[FloatArray, FloatArray]] = field(default_factory=dict)
    normalized: bool = False
    """The keypoints are fractions of the image's width and height (MediaPipe's), not pixels: scaled by the
    camera's image size once the calibration names it (:func:`to_pixels`)."""


def _triplets(values: object, what: str) -> FloatArray:
    """A flat ``[x, y, c, ...]`` list as an (n, 3) array of finite numbers (an unseen point may be null/NaN)."""
    if not isinstance(values, list) or len(values) % 3:
        raise InputError(f"{what}: expected a list of x, y, confidence triplets, got {_kind(values)}")
    return _numbers(values, what).reshape(-1, 3)


def _numbers(values: Sequence[object], what: str) -> FloatArray:
    out = np.empty(len(values))
    for i, v in enumerate(values):
        if v is None:
            out[i] = math.nan
        elif isinstance(v, int | float) and not isinstance(v, bool):
            out[i] = float(v)
        else:
            raise InputError(f"{what}: value {i} is {_kind(v)}, not a number")
    return out


def _kind(v: object) -> str:
    return f"a {type(v).__name__}" if not isinstance(v, list) else f"a list of {len(v)}"


def _stack(people: list[FloatArray], n_kp: int) -> tuple[FloatArray, FloatArray]:
    if len(people) > MAX_PEOPLE:
        raise InputError(f"{len(people)} people in one frame; at most {MAX_PEOPLE}")
    arr = np.stack(people) if people else np.zeros((0, n_kp, 3))
    conf = np.where(np.isfinite(arr[..., 2]), arr[..., 2], 0.0)
    # OpenPose marks an unseen point 0, 0, 0; a point at the image's corner with a confidence is a real one.
    return arr[..., :2].copy(), conf


def parse_openpose(doc: object, keypoint_set: str | None = None, what: str = "OpenPose JSON") -> ParsedFrames:
    """One OpenPose frame file: the people's ``pose_keypoints_2d`` (frame number 0; the reader numbers the
    files). ``keypoint_set`` names the set; else it is told by the length (:data:`OPENPOSE_SETS`)."""
    if not isinstance(doc, dict) or not isinstance(doc.get("people"), list):
        raise InputError(f"{what}: not an OpenPose keypoint file (no 'people' list)")
    people = []
    for i, person in enumerate(doc["people"]):
        if not isinstance(person, dict):
            raise InputError(f"{what}: people[{i}] is {_kind(person)}, not an object")
        values = person.get("pose_keypoints_2d")
        if values is None or values == []:
            continue  # a person without body points (a face or hand only): nothing for the body solver
        people.append(_triplets(values, f"{what}: people[{i}].pose_keypoints_2d"))
    n_kp = {len(p) for p in people}
    if len(n_kp) > 1:
        raise InputError(f"{what}: people with different numbers of keypoints {sorted(n_kp)}")
    name = keypoint_set or (set_for_count(n_kp.pop(), OPENPOSE_SETS) if n_kp else None)
    if name is None:
        return ParsedFrames("", {0: (np.zeros((0, 0, 2)), np.zeros((0, 0)))})
    _check_count(name, people, what)
    return ParsedFrames(name, {0: _stack(people, len(SETS[name]))})


def _check_count(name: str, people: list[FloatArray], what: str) -> None:
    want = len(SETS[name])
    for p in people:
        if len(p) != want:
            raise InputError(f"{what}: {len(p)} keypoints per person, {name} has {want}")


def _instance(inst: object, what: str) -> FloatArray:
    """One MMPose instance (or COCO result) as (n_kp, 3): x, y, score."""
    if not isinstance(inst, dict) or "keypoints" not in inst:
        raise InputError(f"{what}: not an instance with 'keypoints'")
    kps = inst["keypoints"]
    if isinstance(kps, list) and kps and isinstance(kps[0], list):  # [[x, y], ...] with keypoint_scores
        if len(kps) == 1 and kps[0] and isinstance(kps[0][0], list):
            kps = kps[0]  # some versions keep a batch axis of one
        xy = np.array([_numbers(p, f"{what}.keypoints") for p in kps], dtype=np.float64).reshape(len(kps), -1)
        if xy.shape[1] < 2:
            raise InputError(f"{what}.keypoints: expected [x, y] pairs")
        scores = inst.get("keypoint_scores")
        if isinstance(scores, list) and len(scores) == 1 and isinstance(scores[0], list):
            scores = scores[0]
        if not isinstance(scores, list) or len(scores) != len(kps):
            if xy.shape[1] >= 3:  # [x, y, score] triplets
                return xy[:, :3]
            raise InputError(f"{what}: keypoint_scores missing or not one per keypoint ({len(kps)})")
        return np.column_stack([xy[:, :2], _numbers(scores, f"{what}.keypoint_scores")])
    return _triplets(kps, f"{what}.keypoints")


def _mmpose_set(n_kp: int, meta: object, keypoint_set: str | None) -> str:
    if keypoint_set is not None:
        return keypoint_set
    if isinstance(meta, dict):
        named = MMPOSE_DATASETS.get(str(meta.get("dataset_name", "")).lower())
        if named is not None and len(SETS[named]) == n_kp:
            return named
    return set_for_count(n_kp, MMPOSE_SETS)


def parse_mmpose(doc: object, keypoint_set: str | None = None, what: str = "MMPose JSON") -> ParsedFrames:
    """An MMPose / RTMPose prediction file in any of the layouts of the module docstring; frame numbers as the
    file gives them (0 for a single image's instances)."""
    meta: object = None
    if isinstance(doc, dict) and "instance_info" in doc:
        meta, doc = doc.get("meta_info"), doc["instance_info"]
    if isinstance(doc, dict) and "instances" in doc:
        doc = [doc]
    if not isinstance(doc, list):
        raise InputError(f"{what}: not an MMPose prediction file (a list of instances or frames, or instance_info)")
    frames: dict[int, list[FloatArray]] = {}
    for i, item in enumerate(doc):
        if not isinstance(item, dict):
            raise InputError(f"{what}: item {i} is {_kind(item)}, not an object")
        if "instances" in item:  # a frame
            fid = item.get("frame_id", i)
            insts = item["instances"]
            if not isinstance(insts, list):
                raise InputError(f"{what}: frame {i}: 'instances' is {_kind(insts)}, not a list")
        elif "image_id" in item:  # a COCO result: one person of image image_id
            fid, insts = item["image_id"], [item]
        else:  # an instance of the one image
            fid, insts = 0, [item]
        if isinstance(fid, bool) or not isinstance(fid, int):
            raise InputError(f"{what}: item {i}: frame id {fid!r} is not an integer")
        people = frames.setdefault(fid, [])
        people += [_instance(inst, f"{what}: frame {fid} instance {j}") for j, inst in enumerate(insts)]
    counts = {len(p) for ps in frames.values() for p in ps}
    if len(counts) > 1:
        raise InputError(f"{what}: instances with different numbers of keypoints {sorted(counts)}")
    if not counts:
        return ParsedFrames(keypoint_set or "", {f: (np.zeros((0, 0, 2)), np.zeros((0, 0))) for f in frames})
    name = _mmpose_set(counts.pop(), meta, keypoint_set)
    for ps in frames.values():
        _check_count(name, ps, what)
    return ParsedFrames(name, {f: _stack(ps, len(SETS[name])) for f, ps in sorted(frames.items())})


def parse_landmark_array(arr: FloatArray, keypoint_set: str = "blazepose33", what: str = "landmarks") -> list[
    ParsedFrames]:  # fmt: skip
    """FreeMoCap's 2D data (``mediapipe2dData_numCams_numFrames_numTrackedPoints_pixelXY.npy``): one person per
    camera and frame, pixels; the first points are the set's (BlazePose's 33 body landmarks come first, then
    hands and face, which are left out). A third channel is the confidence (visibility); without one a point is
    seen (confidence 1) where it is finite.

    Parameters
    ----------
    arr : array, shape (n_cams, n_frames, n_points, 2 or 3)

    Returns
    -------
    list of ParsedFrames, one per camera
    """
    n_set = len(SETS[keypoint_set])
    if arr.ndim != 4 or arr.shape[3] not in (2, 3) or arr.shape[2] < n_set:
        raise InputError(f"{what}: expected (cameras, frames, points >= {n_set}, 2 or 3), got {arr.shape}")
    out = []
    for cam in arr:
        pts = np.asarray(cam[:, :n_set], dtype=np.float64)
        xy = pts[..., :2]
        seen = np.all(np.isfinite(xy), axis=-1)
        conf = np.where(seen, pts[..., 2] if pts.shape[-1] == 3 else 1.0, 0.0)
        conf = np.where(np.isfinite(conf), conf, 0.0)
        frames = {f: (np.where(seen[f, :, None], xy[f], 0.0)[None], conf[f][None]) for f in range(len(pts))}
        out.append(ParsedFrames(keypoint_set, frames))
    return out


def parse_timestamps(text: str, what: str = "timestamps") -> dict[int, float]:
    """Frame times of a text file: one time (seconds) per line, the line's place being the frame (counted from 0,
    blank lines and ``#`` comments left out), or two columns ``frame time_s`` (comma, tab or space between them);
    a first line that is not numbers is a header. Times must increase with the frame.

    Returns
    -------
    dict frame -> seconds
    """
    out: dict[int, float] = {}
    rows = [line.split("#", 1)[0].replace(",", " ").replace(";", " ").split() for line in text.splitlines()]
    rows = [r for r in rows if r]
    if rows and not _numeric(rows[0]):
        rows = rows[1:]  # a header
    for i, r in enumerate(rows):
        if not _numeric(r) or len(r) not in (1, 2):
            raise InputError(f"{what}: line {i + 1}: expected 'time_s' or 'frame time_s', got {' '.join(r)[:60]!r}")
        frame = i if len(r) == 1 else int(float(r[0]))
        if len(r) == 2 and float(r[0]) != frame:
            raise InputError(f"{what}: line {i + 1}: frame {r[0]!r} is not a whole number")
        t = float(r[-1])
        if frame in out:
            raise InputError(f"{what}: line {i + 1}: frame {frame} twice")
        if not math.isfinite(t):
            raise InputError(f"{what}: line {i + 1}: time not finite")
        out[frame] = t
    if not out:
        raise InputError(f"{what}: no times")
    frames = sorted(out)
    if any(out[b] <= out[a] for a, b in itertools.pairwise(frames)):
        raise InputError(f"{what}: times must increase with the frame number")
    return out


def _numeric(row: list[str]) -> bool:
    try:
        [float(v) for v in row]
    except ValueError:
        return False
    return True


def _landmarks(person: object, what: str) -> FloatArray:
    """One MediaPipe person: 33 landmarks (dicts of x, y and visibility or presence) as (33, 3)."""
    if isinstance(person, dict) and "landmark" in person:
        person = person["landmark"]
    if not isinstance(person, list) or len(person) != 33:
        raise InputError(f"{what}: expected BlazePose's 33 landmarks, got {_kind(person)}")
    out = np.empty((33, 3))
    for i, lm in enumerate(person):
        if not isinstance(lm, dict):
            raise InputError(f"{what}: landmark {i} is {_kind(lm)}, not an object")
        conf = lm.get("visibility", lm.get("presence", 1.0))
        out[i] = _numbers([lm.get("x"), lm.get("y"), conf], f"{what}: landmark {i}")
    return out


def _mediapipe_people(frame: object, what: str) -> list[FloatArray]:
    if isinstance(frame, dict):
        if "landmark" in frame:
            return [_landmarks(frame, what)]
        people = frame.get("pose_landmarks", frame.get("people", []))
    else:
        people = frame
    if isinstance(people, dict):  # MessageToDict of one person under pose_landmarks
        people = [people]
    if not isinstance(people, list):
        raise InputError(f"{what}: not MediaPipe pose landmarks")
    if len(people) == 33 and all(isinstance(p, dict) and "x" in p for p in people):
        people = [people]  # one person's landmarks, not a list of people
    return [_landmarks(p, f"{what}: person {j}") for j, p in enumerate(people)]


def parse_mediapipe(doc: object, what: str = "MediaPipe JSON") -> ParsedFrames:
    """MediaPipe Pose landmarks (module docstring): one frame (frame 0) or a video's frames; ``normalized``."""
    if isinstance(doc, dict) and isinstance(doc.get("frames"), list):
        doc = doc["frames"]
    frames_in: list[tuple[int, object]]
    one_frame = isinstance(doc, dict) or (
        isinstance(doc, list) and (not doc or (isinstance(doc[0], dict) and "x" in doc[0]) or (
            isinstance(doc[0], list) and doc[0] and isinstance(doc[0][0], dict) and "x" in doc[0][0]))
    )  # fmt: skip
    if one_frame:
        frames_in = [(0, doc)]
    elif isinstance(doc, list):
        frames_in = []
        for i, fr in enumerate(doc):
            fid = fr.get("frame", fr.get("frame_id", i)) if isinstance(fr, dict) else i
            if isinstance(fid, bool) or not isinstance(fid, int):
                raise InputError(f"{what}: frame {i}: frame number {fid!r} is not an integer")
            frames_in.append((fid, fr))
    else:
        raise InputError(f"{what}: not MediaPipe pose landmarks")
    out = ParsedFrames("blazepose33", normalized=True)
    for fid, fr in frames_in:
        out.frames[fid] = _stack(_mediapipe_people(fr, f"{what}: frame {fid}"), 33)
    return out


def to_pixels(keypoints: FloatArray, width: int, height: int) -> FloatArray:
    """Normalised keypoints (fractions of the image, shape (..., 2)) as pixels of a ``width`` x ``height`` image."""
    out: FloatArray = np.asarray(keypoints, dtype=np.float64) * np.array([width, height], dtype=np.float64)
    return out
