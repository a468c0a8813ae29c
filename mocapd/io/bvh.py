"""BVH motion files → :class:`~mocapd.core.motion.SourceMotion`.

Handles the variants in the shared data: any rotation channel order per joint (CMU's ZYX on the legs and ZXY on
the arms in the same file), position channels on every joint (Bandai: they replace the OFFSET, as in
MotionBuilder exports), tabs or spaces, end sites with or without length, and any length unit (detected from the
leg length unless given: cm for Bandai, CMU's 1/0.45-inch units for CMU BVH).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocapd.core.motion import SourceMotion
from mocapd.core.naming import match_roles
from mocapd.errors import InputError
from mocapd.io.input_files import GiB, read_input_text
from mocapd.io.malformed import malformed_file
from mocapd.io.mocap_units import CANDIDATE_UNITS, detect_unit, quat_from_euler

MAX_FILE_BYTES = GiB // 2
"""Largest motion file read (read whole and split into words: ~10 times its size in memory while parsed; an hour
of 120 Hz motion of a 30-bone skeleton is ~250 MiB of text)."""

_LEG_NAMES = (("upleg", "hip", "upperleg", "thigh", "femur"), ("leg", "knee", "lowerleg", "shin", "tibia"))


def read_bvh(path: str | Path, unit: str | None = None) -> SourceMotion:
    """Read a BVH file.

    Parameters
    ----------
    path : file path
    unit : one of ``CANDIDATE_UNITS`` (m, cm, mm, inch, cmu) or None to detect it from the leg length.
    """
    p = Path(path)
    text = read_input_text(p, "BVH file", max_bytes=MAX_FILE_BYTES)
    return parse_bvh(text, p.stem, unit)


def parse_bvh(text: str, name: str = "bvh", unit: str | None = None) -> SourceMotion:
    """Parse BVH text (see :func:`read_bvh`); a malformed file is an :class:`~mocapd.errors.InputError`."""
    with malformed_file(f"BVH {name}"):
        return _parse_bvh(text, name, unit)


def _parse_bvh(text: str, name: str, unit: str | None) -> SourceMotion:
    tokens = text.split()
    pos = 0

    def take() -> str:
        nonlocal pos
        if pos >= len(tokens):
            raise InputError(f"BVH {name}: unexpected end of file in the hierarchy")
        pos += 1
        return tokens[pos - 1]

    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[list[str]] = []
    end_sites: list[list[float]] = []
    stack: list[int] = []
    if take().upper() != "HIERARCHY":
        raise InputError(f"BVH {name}: missing HIERARCHY")
    while True:
        tok = take()
        up = tok.upper()
        if up in ("ROOT", "JOINT"):
            names.append(take())
            parents.append(stack[-1] if stack else -1)
            offsets.append([0.0, 0.0, 0.0])
            channels.append([])
            end_sites.append([0.0, 0.0, 0.0])
            if take() != "{":
                raise InputError(f"BVH {name}: expected '{{' after joint {names[-1]}")
            stack.append(len(names) - 1)
        elif up == "END":
            take()  # "Site"
            if take() != "{" or take().upper() != "OFFSET":
                raise InputError(f"BVH {name}: malformed End Site")
            end_sites[stack[-1]] = [float(take()) for _ in range(3)]
            if take() != "}":
                raise InputError(f"BVH {name}: malformed End Site")
        elif up == "OFFSET":
            offsets[stack[-1]] = [float(take()) for _ in range(3)]
        elif up == "CHANNELS":
            channels[stack[-1]] = [take().lower() for _ in range(int(take()))]
        elif tok == "}":
            stack.pop()
        elif up == "MOTION":
            break
        else:
            raise InputError(f"BVH {name}: unexpected token {tok!r} in the hierarchy")
    if take().rstrip(":").upper() != "FRAMES":
        raise InputError(f"BVH {name}: missing 'Frames:'")
    n_frames = int(take())
    if n_frames < 0:  # a negative count slices frames off the end of the data: refuse it instead
        raise InputError(f"BVH {name}: Frames: {n_frames}; allowed: a count >= 0")
    if take().upper() != "FRAME" or take().rstrip(":").upper() != "TIME":
        raise InputError(f"BVH {name}: missing 'Frame Time:'")
    frame_time = float(take())
    n_ch = sum(len(c) for c in channels)
    values = np.array(tokens[pos : pos + n_frames * n_ch], dtype=np.float64)
    if not np.isfinite(values).all() or (values.size and np.abs(values).max() > MAX_CHANNEL_VALUE):
        # refused before any rotation math runs on them (sin/cos of 1e308 degrees is NaN with a warning)
        raise InputError(f"BVH {name}: channel values must be finite and within ±{MAX_CHANNEL_VALUE:g}")
    if values.size < n_frames * n_ch or n_frames < 1:
        n_frames = values.size // max(n_ch, 1)  # a truncated last frame: keep the complete ones
        if n_frames < 1:
            raise InputError(f"BVH {name}: no complete motion frame")
        values = values[: n_frames * n_ch]
    data = values.reshape(n_frames, n_ch)

    n = len(names)
    off = np.array(offsets)
    if not (np.isfinite(off).all() and np.isfinite(np.array(end_sites, dtype=np.float64)).all()):
        # position channels may replace a joint's OFFSET, but the offsets also size the skeleton (unit detection)
        raise InputError(f"BVH {name}: non-finite OFFSET in the hierarchy")
    trans = np.broadcast_to(off, (n_frames, n, 3)).copy()
    rot = np.zeros((n_frames, n, 4))
    rot[..., 0] = 1.0
    col = 0
    for j, ch in enumerate(channels):
        block = data[:, col : col + len(ch)]
        col += len(ch)
        pos_idx = [k for k, c in enumerate(ch) if c.endswith("position")]
        rot_idx = [k for k, c in enumerate(ch) if c.endswith("rotation")]
        if pos_idx:
            for k in pos_idx:
                trans[:, j, "xyz".index(ch[k][0])] = block[:, k]
        if rot_idx:
            order = "".join(ch[k][0] for k in rot_idx)
            rot[:, j] = quat_from_euler(block[:, rot_idx], order)

    scale = CANDIDATE_UNITS[unit] if unit is not None else detect_unit(_leg_length(names, off, parents))[1]
    if unit is not None and unit not in CANDIDATE_UNITS:
        raise InputError(f"BVH {name}: unknown unit {unit!r}; allowed: {sorted(CANDIDATE_UNITS)}")
    return SourceMotion(
        name=name,
        joint_names=tuple(names),
        parents=tuple(parents),
        translations=trans * scale,
        rotations=rot,
        end_sites=np.array(end_sites) * scale,
        fps=_rate(frame_time),
    )


def _leg_length(names: list[str], offsets: np.ndarray, parents: list[int]) -> float:
    """Hip-to-ankle length in file units: along the left leg of the file's naming convention, else the lengths of
    the two joints below the first left thigh-like joint."""
    try:
        roles = match_roles(names).joints
    except InputError:
        roles = {}
    if "lhip" in roles:
        j, total = roles["lankle"], 0.0
        while j not in (roles["lhip"], -1):
            total += float(np.linalg.norm(offsets[j]))
            j = parents[j]
        if j >= 0:
            return total
    low = [n.lower() for n in names]
    for i, n in enumerate(low):
        left = n.startswith("l") or "left" in n or n.endswith("_l")
        if left and any(k in n for k in _LEG_NAMES[0]) and "hipjoint" not in n:
            kids = [c for c, p in enumerate(parents) if p == i]
            grand = [c for c, p in enumerate(parents) if kids and p == kids[0]]
            if kids and grand:
                return float(np.linalg.norm(offsets[kids[0]]) + np.linalg.norm(offsets[grand[0]]))
    return float("nan")


MAX_CHANNEL_VALUE = 1e7
"""Largest magnitude of a motion channel value (cm, mm or degrees): far beyond any capture, finite for the math."""
MIN_FRAME_TIME_S = 1e-4
"""10 kHz: faster than any motion capture (a frame time of 1e-300 s is damage, not a 1e300 Hz recording)."""
MAX_FRAME_TIME_S = 60.0


def _rate(frame_time: float) -> float:
    """Frame rate from a frame time, snapped to an integer rate when the file rounded it (.0083333 -> 120)."""
    if not (np.isfinite(frame_time) and MIN_FRAME_TIME_S <= frame_time <= MAX_FRAME_TIME_S):
        raise InputError(
            f"BVH frame time must be in [{MIN_FRAME_TIME_S:g}, {MAX_FRAME_TIME_S:g}] s, got {frame_time!r}"
        )
    r = 1.0 / frame_time
    return float(round(r)) if abs(r - round(r)) < 1e-3 * r else r
