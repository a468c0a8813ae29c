"""CMU ASF skeletons and AMC motions → :class:`~mocapd.core.motion.SourceMotion`.

ASF describes *bones* (segments): each has a rest direction and length in world axes, a local frame given by
``axis`` Euler angles (``C``) and the degrees of freedom its AMC line carries (``M``). A bone's global rotation
is ``G = G_parent · C · M · C⁻¹`` and it spans from its parent's end to ``start + G · direction · length``.
We convert to the joint tree of SourceMotion: one joint per bone, at the bone's start, whose local rotation is
``C M C⁻¹`` and whose children sit at the bone's rest vector. Units: ``:units length`` (CMU: 0.45, i.e. one
unit = 1/0.45 inch) and ``angle deg|rad``. AMC files are 120 Hz unless the caller says otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mocapd.core.motion import SourceMotion
from mocapd.core.rotations import quat_conjugate, quat_multiply
from mocapd.errors import InputError
from mocapd.io.bvh import MAX_CHANNEL_VALUE
from mocapd.io.input_files import GiB, MiB, read_input_text
from mocapd.io.malformed import malformed_file
from mocapd.io.mocap_units import quat_from_euler

MAX_FILE_BYTES = GiB // 2
"""Largest motion file read (read whole and split into words: ~10 times its size in memory while parsed; an hour
of 120 Hz motion of a 30-bone skeleton is ~250 MiB of text)."""

FloatArray = NDArray[np.float64]
_INCH = 0.0254


@dataclass
class _Bone:
    name: str
    direction: FloatArray = field(default_factory=lambda: np.zeros(3))
    length: float = 0.0
    axis: FloatArray = field(default_factory=lambda: np.zeros(3))
    axis_order: str = "xyz"
    dofs: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class AsfSkeleton:
    """A parsed ASF file."""

    bones: tuple[_Bone, ...]  # index 0 is the root
    parents: tuple[int, ...]
    length_scale: float  # metres per file length unit
    degrees: bool
    root_order: tuple[str, ...]
    root_axis_order: str


def read_asf(path: str | Path) -> AsfSkeleton:
    p = Path(path)
    text = read_input_text(p, "ASF file", max_bytes=16 * MiB)  # a skeleton: a few KB
    return parse_asf(text, p.name)


def parse_asf(text: str, name: str = "asf") -> AsfSkeleton:
    """Parse ASF text; a malformed file is an :class:`~mocapd.errors.InputError`."""
    with malformed_file(f"ASF {name}"):
        return _parse_asf(text, name)


def _parse_asf(text: str, name: str) -> AsfSkeleton:
    section = ""
    length_unit = 1.0
    degrees = True
    root = _Bone("root")
    root_order: tuple[str, ...] = ("tx", "ty", "tz", "rx", "ry", "rz")
    root_axis_order = "xyz"
    bones: list[_Bone] = []
    cur: _Bone | None = None
    hierarchy: list[tuple[str, list[str]]] = []
    in_limits = False
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith(":"):
            parts = line[1:].split()
            section = parts[0].lower()
            continue
        words = line.split()
        key = words[0].lower()
        if section == "units":
            if key == "length":
                length_unit = float(words[1])
            elif key == "angle":
                degrees = words[1].lower().startswith("deg")
        elif section == "root":
            if key == "order":
                root_order = tuple(w.lower() for w in words[1:])
            elif key == "axis":
                root_axis_order = words[1].lower()
            elif key == "orientation":
                root.axis = np.array([float(w) for w in words[1:4]])
        elif section == "bonedata":
            if key == "begin":
                cur = _Bone("")
                in_limits = False
            elif key == "end":
                if cur is None or not cur.name:
                    raise InputError(f"ASF {name}: a bone without a name")
                bones.append(cur)
                cur = None
            elif cur is not None:
                if key == "name":
                    cur.name = words[1]
                elif key == "direction":
                    cur.direction = np.array([float(w) for w in words[1:4]])
                elif key == "length":
                    cur.length = float(words[1])
                elif key == "axis":
                    cur.axis = np.array([float(w) for w in words[1:4]])
                    cur.axis_order = words[4].lower() if len(words) > 4 else "xyz"
                elif key == "dof":
                    cur.dofs = [w.lower() for w in words[1:]]
                    in_limits = False
                elif key == "limits" or in_limits:
                    in_limits = True
        elif section == "hierarchy":
            if key in ("begin", "end"):
                continue
            hierarchy.append((words[0], words[1:]))
    by_name = {b.name.lower(): i + 1 for i, b in enumerate(bones)}
    by_name["root"] = 0
    parent_of: dict[int, int] = {}
    for parent, kids in hierarchy:
        if parent.lower() not in by_name:
            raise InputError(f"ASF {name}: hierarchy names unknown bone {parent!r}")
        for k in kids:
            if k.lower() not in by_name:
                raise InputError(f"ASF {name}: hierarchy names unknown bone {k!r}")
            parent_of[by_name[k.lower()]] = by_name[parent.lower()]
    # Order bones so that parents precede children.
    all_bones = [root, *bones]
    order: list[int] = [0]
    frontier = [0]
    while frontier:
        nxt: list[int] = []
        for i in frontier:
            children = sorted(c for c, p in parent_of.items() if p == i)
            order.extend(children)
            nxt.extend(children)
        frontier = nxt
    remap = {old: new for new, old in enumerate(order)}
    ordered = tuple(all_bones[i] for i in order)
    parents = tuple(-1 if i == 0 else remap[parent_of[i]] for i in order)
    # CMU: length unit 0.45 means lengths are in inches / 0.45.
    if not (np.isfinite(length_unit) and length_unit > 0):
        raise InputError(f"ASF {name}: ':units length {length_unit!r}'; allowed: a positive number")
    for b in ordered:
        if not (np.isfinite(b.direction).all() and np.isfinite(b.length) and b.length >= 0):
            raise InputError(f"ASF {name}: bone {b.name}: non-finite direction or length (or a negative length)")
    scale = _INCH / length_unit
    return AsfSkeleton(ordered, parents, scale, degrees, root_order, root_axis_order)


def _euler_xyz(angles_deg: FloatArray) -> FloatArray:
    """ASF/AMC rotation for angles about x, y, z (degrees): R = Rz Ry Rx (static xyz), shape (..., 3) -> (..., 4)."""
    a = np.asarray(angles_deg, dtype=np.float64)
    return quat_from_euler(a[..., ::-1], "zyx")


def read_amc(path: str | Path, skeleton: AsfSkeleton, fps: float = 120.0) -> SourceMotion:
    p = Path(path)
    text = read_input_text(p, "AMC file", max_bytes=MAX_FILE_BYTES)
    return parse_amc(text, skeleton, p.stem, fps)


def parse_amc(text: str, skeleton: AsfSkeleton, name: str = "amc", fps: float = 120.0) -> SourceMotion:
    """AMC text on a parsed ASF skeleton (see module doc); a malformed file is an :class:`~mocapd.errors.InputError`."""
    with malformed_file(f"AMC {name}"):
        return _parse_amc(text, skeleton, name, fps)


def _parse_amc(text: str, skeleton: AsfSkeleton, name: str, fps: float) -> SourceMotion:
    bones = skeleton.bones
    index = {b.name.lower(): i for i, b in enumerate(bones)}
    frames: list[dict[int, list[float]]] = []
    cur: dict[int, list[float]] | None = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#") or line.startswith(":"):
            continue
        words = line.split()
        if len(words) == 1 and words[0].isdigit():
            cur = {}
            frames.append(cur)
            continue
        if cur is None:
            continue
        j = index.get(words[0].lower())
        if j is None:
            raise InputError(f"AMC {name}: unknown bone {words[0]!r}")
        cur[j] = [float(w) for w in words[1:]]
        if not all(math.isfinite(v) and abs(v) <= MAX_CHANNEL_VALUE for v in cur[j]):
            # refused before any rotation math runs on them (sin/cos of 1e308 degrees is NaN with a warning)
            raise InputError(f"AMC {name}: bone {words[0]!r}: values must be finite and within ±{MAX_CHANNEL_VALUE:g}")
    if not frames:
        raise InputError(f"AMC {name}: no frames")
    n, f = len(bones), len(frames)
    s = skeleton.length_scale
    ang = 1.0 if skeleton.degrees else 180.0 / np.pi
    # Rest translations: a joint sits at its parent bone's end.
    rest = np.zeros((n, 3))
    end_sites = np.zeros((n, 3))
    for j, b in enumerate(bones):
        vec = b.direction * b.length * s
        end_sites[j] = vec
        for k, par in enumerate(skeleton.parents):
            if par == j:
                rest[k] = vec
    has_child = {p for p in skeleton.parents if p >= 0}
    for j in has_child:
        end_sites[j] = 0.0
    trans = np.broadcast_to(rest, (f, n, 3)).copy()
    rot = np.zeros((f, n, 4))
    rot[..., 0] = 1.0
    for j, b in enumerate(bones):
        dofs = list(skeleton.root_order) if j == 0 else b.dofs
        if not dofs:
            continue
        vals = np.array([fr.get(j, [0.0] * len(dofs)) for fr in frames])
        if vals.shape[1] != len(dofs):
            raise InputError(f"AMC {name}: bone {b.name} has {vals.shape[1]} values for dofs {dofs}")
        xyz = np.zeros((f, 3))
        for k, d in enumerate(dofs):
            if d.startswith("t") and j == 0:
                trans[:, 0, "xyz".index(d[1])] = vals[:, k] * s
            elif d.startswith("r"):
                xyz[:, "xyz".index(d[1])] = vals[:, k] * ang
        M = _euler_xyz(xyz)
        C = _euler_xyz(b.axis * ang)
        rot[:, j] = quat_multiply(quat_multiply(C, M), quat_conjugate(C))
    names = tuple(b.name for b in bones)
    return SourceMotion(name, names, skeleton.parents, trans, rot, end_sites, fps)
