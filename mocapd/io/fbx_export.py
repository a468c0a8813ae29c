"""FBX export of recorded subjects through Blender's own FBX exporter, run as a child process.

Why Blender: FBX is a closed binary format whose only complete writers are Autodesk's SDK (not redistributable)
and Blender's exporter (GPL, well kept, used by every Blender-to-engine pipeline). mocapd does not link either: it
writes a job (JSON + ``.npz`` of the resampled tracks) to a temporary directory and runs
``mocapd/io/_blender_fbx.py`` in Blender, which builds the armatures and calls ``export_scene.fbx``.

Which Blender (the first found): ``--blender PATH`` (a ``blender`` executable, or a Python that has the ``bpy``
module); ``$MOCAPD_BLENDER`` (the same); ``.venv-bpy/bin/python`` of a source checkout (made by
``setup/steps/40-bpy.sh``) or of the current directory; ``blender`` on ``PATH``. None: :class:`ToolError` with the
install command (:data:`INSTALL`).

The child process: its output is collected and shown only when it fails; it runs at most ``timeout_s`` (then it
is terminated: SIGTERM, SIGKILL 5 s later), and any exception in mocapd while it runs (Ctrl-C included)
terminates it before the exception goes on, so it never outlives the export. The FBX is written beside the output
under a temporary name and renamed into place, so a failed or interrupted export leaves no partial file.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mocapd.core.rotations import quat_from_rotvec
from mocapd.core.skeleton import BONE_NAMES, N_BONES, PARENTS, Skeleton
from mocapd.errors import InputError, ToolError
from mocapd.io import lifecycle
from mocapd.io.output_files import check_output_file
from mocapd.io.session_export import SubjectTrack
from mocapd.protocols.fingers import EXTENDED_BONE_NAMES, EXTENDED_PARENTS, extended_offsets, leaf_ends, tail_child
from mocapd.protocols.gltf_writer import END_FRACTION, rest_positions

SCRIPT = Path(__file__).with_name("_blender_fbx.py")
INSTALL = "python3.11 -m venv .venv-bpy && .venv-bpy/bin/python -m pip install bpy==4.5.15"
"""Blender as a Python module (Blender 4.5 LTS), where mocapd looks for it; or install Blender itself."""
UNITS = ("cm", "m")
UP_AXES = ("y", "z")
TIMEOUT_S = 1800.0
_CHECKOUT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Blender:
    """How to run a script in Blender: a ``blender`` executable or a Python with ``bpy``."""

    path: Path
    is_python: bool

    def command(self, script: Path, *args: str) -> list[str]:
        if self.is_python:
            return [str(self.path), str(script), *args]
        return [str(self.path), "--background", "--factory-startup", "--python-exit-code", "1",
                "--python", str(script), "--", *args]  # fmt: skip


def _as_blender(path: Path) -> Blender:
    return Blender(path, is_python="python" in path.name)


def find_blender(explicit: str | Path | None = None) -> Blender:
    """The Blender to run (module docstring); :class:`ToolError` in one line when there is none."""
    if explicit is not None:
        p = Path(explicit)
        if not (p.is_file() and os.access(p, os.X_OK)):
            raise ToolError(f"--blender {p}: no such executable (a blender binary or a Python with bpy); "
                            f"install Blender as a module with: {INSTALL}")  # fmt: skip
        return _as_blender(p)
    env = os.environ.get("MOCAPD_BLENDER")
    if env:
        p = Path(env)
        if not (p.is_file() and os.access(p, os.X_OK)):
            raise ToolError(f"MOCAPD_BLENDER={env}: no such executable; install Blender as a module with: {INSTALL}")
        return _as_blender(p)
    for venv in (_CHECKOUT / ".venv-bpy", Path.cwd() / ".venv-bpy"):
        py = venv / "bin" / "python"
        if py.is_file() and os.access(py, os.X_OK):
            return Blender(py, is_python=True)
    found = shutil.which("blender")
    if found:
        return Blender(Path(found), is_python=False)
    raise ToolError(f"FBX export needs Blender (4.2 or newer), found none: install it as a Python module with "
                    f"`{INSTALL}`, or put `blender` on PATH, or pass --blender PATH")  # fmt: skip


def node_names(subjects: list[str]) -> list[str]:
    """FBX node names of the subjects' armatures: letters, digits and ``_`` (``suit:suit0`` → ``suit_suit0``; FBX
    and Maya give ``:`` a meaning), distinct."""
    out: list[str] = []
    for s in subjects:
        base = re.sub(r"[^A-Za-z0-9_]", "_", s) or "subject"
        name, k = base, 2
        while name in out:
            name, k = f"{base}_{k}", k + 1
        out.append(name)
    return out


def export_fbx(
    path: str | Path,
    tracks: list[tuple[SubjectTrack, Skeleton]],
    *,
    rate_hz: float,
    units: str = "cm",
    up: str = "y",
    take: str = "take",
    blender: Blender | None = None,
    timeout_s: float = TIMEOUT_S,
) -> dict[str, Any]:
    """Write resampled tracks (each on a ``rate_hz`` grid) with their skeletons as one FBX take.

    Returns what Blender reported (frames, armature names, Blender's version) and each subject's node name.
    """
    if units not in UNITS or up not in UP_AXES:
        raise InputError(f"FBX units {units!r} / up axis {up!r}: allowed {UNITS} and {UP_AXES}")
    if not tracks:
        raise InputError("no subject to export")
    out = check_output_file(path, overwrite=True).resolve()  # replacing a file is the caller's choice (--force)
    blender = blender or find_blender()
    t0 = min(int(t.t_ns[0]) for t, _ in tracks)
    names = node_names([t.subject for t, _ in tracks])
    with tempfile.TemporaryDirectory(prefix="mocapd-fbx-") as tmp:
        arrays: dict[str, Any] = {}  # name -> array (typed Any: np.savez also takes allow_pickle=)
        subjects: list[dict[str, Any]] = []
        for k, ((track, skeleton), name) in enumerate(zip(tracks, names, strict=True)):
            n = int(track.thetas.shape[0])
            arrays[f"offsets_{k}"] = np.asarray(skeleton.offsets, dtype=np.float64)
            arrays[f"root_{k}"] = track.thetas[:, 0:3].astype(np.float64)
            arrays[f"quat_{k}"] = quat_from_rotvec(track.thetas[:, 3:].reshape(n, N_BONES, 3))
            first = round((int(track.t_ns[0]) - t0) * rate_hz / 1e9)
            subject: dict[str, Any] = {"name": name, "subject": track.subject, "root_height": skeleton.root_height,
                                       "first_frame": first}  # fmt: skip
            if track.hands is not None and track.hand_skeleton is not None:  # the finger bones join the body's
                subject.update(_finger_job(arrays, k, track, skeleton))
            subjects.append(subject)
        np.savez(Path(tmp) / "tracks.npz", **arrays)
        job = {"arrays": str(Path(tmp) / "tracks.npz"), "output": str(out), "rate_hz": rate_hz, "units": units,
               "up": up, "take": take, "bones": list(BONE_NAMES), "parents": list(PARENTS),
               "subjects": subjects}  # fmt: skip
        job_path = Path(tmp) / "job.json"
        job_path.write_text(json.dumps(job), encoding="utf-8")
        report = _run(blender.command(SCRIPT, str(job_path)), timeout_s)
    report["nodes"] = dict(zip((t.subject for t, _ in tracks), names, strict=True))
    return report


def _finger_job(arrays: dict[str, Any], k: int, track: SubjectTrack, skeleton: Skeleton) -> dict[str, Any]:
    """A subject with fingers: the 51 bones' offsets, rotations and rest tails in the arrays (replacing the body's),
    their names and parents for the job (:mod:`mocapd.protocols.fingers`)."""
    assert track.hands is not None and track.hand_skeleton is not None
    n = int(track.thetas.shape[0])
    offsets = extended_offsets(skeleton.offsets, track.hand_skeleton)
    arrays[f"offsets_{k}"] = offsets
    arrays[f"quat_{k}"] = np.concatenate([arrays[f"quat_{k}"], track.hands.reshape(n, -1, 4)], axis=1)
    heads = rest_positions(offsets, skeleton.root_height, EXTENDED_PARENTS)
    ends = leaf_ends(skeleton.offsets, track.hand_skeleton, END_FRACTION)
    tails = np.empty_like(heads)
    for b in range(len(EXTENDED_PARENTS)):
        c = tail_child(EXTENDED_PARENTS, b)
        tails[b] = heads[c] if c is not None else heads[b] + ends[b]
    arrays[f"tails_{k}"] = tails
    return {"bones": list(EXTENDED_BONE_NAMES), "parents": list(EXTENDED_PARENTS)}


def _run(command: list[str], timeout_s: float) -> dict[str, Any]:
    """Run Blender; its ``MOCAPD-FBX`` report, or :class:`ToolError` with the end of its output."""
    # Blender ends with mocapd however mocapd ends, SIGKILL included (lifecycle.guarded_command); a stop, a time-out
    # or an error stops it here.
    proc = subprocess.Popen(lifecycle.guarded_command(command), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, text=True, errors="replace")  # fmt: skip
    try:
        output, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        _stop(proc)
        raise ToolError(f"Blender did not finish the FBX export within {timeout_s:g} s (stopped)") from None
    except BaseException:  # Ctrl-C or anything else: Blender must not outlive the export
        _stop(proc)
        raise
    lines = [ln for ln in output.splitlines() if ln.startswith("MOCAPD-FBX ")]
    if proc.returncode != 0 or not lines:
        tail = " | ".join(ln for ln in output.splitlines()[-6:] if ln.strip())
        raise ToolError(f"Blender's FBX export failed (exit {proc.returncode}): {tail}")
    report: dict[str, Any] = json.loads(lines[-1].removeprefix("MOCAPD-FBX "))
    return report


def _stop(proc: subprocess.Popen[str]) -> None:
    proc.terminate()
    try:
        proc.wait(5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
