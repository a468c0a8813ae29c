"""The running daemon's cameras written to its calibration file (issue 43, "cameras that stay calibrated"):
``POST /calibration/save`` (``mocapd calibrate save``), after the camera watch applied a re-estimate (or any time).

The file is ``[calibration] save_to``, or the calibration file itself when that is empty. It is written as mocapd's
calibration TOML (any ``.toml`` is read as mocapd's when it says ``format = "mocapd-calibration"``, whatever
``world_up`` says, so the next start reads what was saved), atomically: a temporary file beside it, flushed and
fsynced, renamed over it, the folder synced (:func:`mocapd.io.output_files.atomic_path`). The old file, if any, is
first copied beside it as ``NAME.YYYYmmddTHHMMSS.bak`` (the same way), so a save can be undone by hand. Cameras in
the old file that the rig does not use are kept as they were; the rig's replace theirs (intrinsics, image size and
distortion as the daemon has them: a live change keeps them).
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass
from pathlib import Path

from mocapd.core.camera import Camera
from mocapd.errors import CalibrationError, InputError, OutputError
from mocapd.io.calibration_files import (
    CalibrationSet,
    CameraCalibration,
    WorldUp,
    read_any,
    write_mocapd_toml,
)
from mocapd.io.output_files import write_bytes_atomic


@dataclass(frozen=True)
class Saved:
    """What a save wrote."""

    file: Path
    backup: Path | None  # the old file's copy (None: there was none)
    cameras: tuple[str, ...]  # the rig's cameras written
    kept: tuple[str, ...]  # cameras of the old file the rig does not use, written back unchanged


def backup_path(target: Path, now: datetime.datetime) -> Path:
    """``calib.toml`` -> ``calib.toml.20261129T075500.bak`` beside it (a second save in the same second: ``_2``...).

    The names list in the order they were made (``_`` sorts after the ``.`` of ``.bak``; up to nine in one second).
    """
    stamp = now.strftime("%Y%m%dT%H%M%S")
    path = target.with_name(f"{target.name}.{stamp}.bak")
    n = 2
    while path.exists():
        path = target.with_name(f"{target.name}.{stamp}_{n}.bak")
        n += 1
    return path


def save_cameras(
    cameras: list[Camera],
    target: Path,
    *,
    source: str,
    world_up: WorldUp | None = None,
    now: datetime.datetime | None = None,
) -> Saved:
    """Write ``cameras`` (the rig as it runs now) to ``target`` (see the module docstring).

    Raises
    ------
    InputError
        ``target`` is not a ``.toml`` file (mocapd's calibration TOML is what is written: over a ``.qca.txt`` or a
        YAML the next start would not read it), or the old file there cannot be read (it is left alone).
    OutputError
        The backup or the file cannot be written (the old file is left as it was).
    """
    if target.suffix.lower() != ".toml":
        raise InputError(f"cannot save the cameras to {target}: mocapd writes its calibration TOML, which needs a "
                         f".toml name; set [calibration] save_to to one")  # fmt: skip
    rig = [CameraCalibration(c.name, (c.width, c.height), c.K, c.dist, c.R, c.t) for c in cameras]
    names = {c.name for c in rig}
    kept: list[CameraCalibration] = []
    backup = None
    if target.exists():
        try:
            old = read_any(target, world_up=world_up)  # as the daemon read it at start
        except CalibrationError as exc:
            raise InputError(f"cannot save the cameras to {target}: the file there is not a calibration this daemon "
                             f"reads ({exc}); left alone") from None  # fmt: skip
        kept = [c for c in old.cameras if c.name not in names]
        backup = backup_path(target, now or datetime.datetime.now())
        try:
            data = target.read_bytes()
        except OSError as exc:
            raise OutputError(f"cannot back up {target}: {exc.strerror or exc}") from None
        write_bytes_atomic(backup, data)
    write_mocapd_toml(CalibrationSet(tuple(rig + kept), source=source), target)
    return Saved(target, backup, tuple(c.name for c in rig), tuple(c.name for c in kept))
