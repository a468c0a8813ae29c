"""The guided IMU calibration of a running daemon's suit (docs/imu.md, "Calibrating a suit live").

``POST /imu/calibrate?suit=NAME&pose=a-pose`` (``mocapd calibrate imu --live``), or the WebSocket request
``calibrate_imu``, starts :class:`mocapd.core.calibration_routine.CalibrationRoutine` for one suit of the rig: the
wearer stands, walks a few steps, bends the elbows; the daemon feeds it the suit's samples as they arrive (from the
IMU buffers, once a second), says each step on its console (a warning line, so it shows without ``--verbose``) and in
``/status`` (``imu_calibration_routine``: the step, what to do, progress, what it said), and when the routine is
done writes the suit's calibration file and fuses the suit with it from the next tick on (the sensors and their bones
stay the suit's; only their mountings, the heading and the posture found change). ``cancel=1`` stops a routine.

A suit of SlimeVR trackers is refused: each tracker's own heading comes from a calibration with ``--mount-yaw``
(``mocapd calibrate imu``), which a live routine does not redo.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mocapd.core.calibration_routine import CalibrationRoutine, RoutineOptions
from mocapd.core.imu_calibration import ImuCalibration
from mocapd.core.skeleton import Skeleton
from mocapd.errors import InputError, MocapdError, OutputError
from mocapd.io.output_files import write_text_atomic
from mocapd.pipeline.imu_ingest import ImuIngest
from mocapd.pipeline.scheduler import FixedLatencyScheduler, Suit
from mocapd.protocols.ws_stream import ROUTINE_POSES

log = logging.getLogger(__name__)


@dataclass
class _Run:
    routine: CalibrationRoutine
    source: str
    said: int = 0  # how many of the routine's words are on the console already
    seen_ns: dict[str, int] = field(default_factory=dict)  # per sensor, the newest sample fed


class LiveCalibrations:
    """The routines running (or just done) per suit, fed from the IMU buffers; see the module docstring.

    Parameters
    ----------
    calibration_dir : Path
        Where the suits' ``<person>.imu.json`` files are (``[imu] calibration_dir``).
    skeleton : Skeleton
        The rig's (a suit's mount sites are on it).
    install : callable
        Called with the suit rebuilt from a finished routine's calibration, to fuse it from then on.
    """

    def __init__(self, calibration_dir: Path, skeleton: Skeleton, install: Callable[[Suit], None]) -> None:
        self.calibration_dir = calibration_dir
        self.skeleton = skeleton
        self.install = install
        self.runs: dict[str, _Run] = {}

    def start(
        self, suits: list[Suit], suit: str | None, pose: str | None, source: str, now_ns: int, *, cancel: bool = False
    ) -> dict[str, Any]:
        """Start (or with ``cancel`` stop) the routine for ``suit`` (None: the rig's only suit); returns its state.

        Raises
        ------
        InputError
            No such suit (or several and none named), a bad pose, a routine already running, SlimeVR trackers.
        """
        names = ", ".join(s.id for s in suits) or "none: calibrate one first with `mocapd calibrate imu`"
        if suit is None and len(suits) != 1:
            raise InputError(f"name the suit to calibrate (suits: {names})")
        chosen = next((s for s in suits if suit in (None, s.id)), None)
        if chosen is None:
            raise InputError(f"no suit {suit!r} to calibrate (suits: {names})")
        running = self.runs.get(chosen.id)
        active = running is not None and running.routine.step not in ("done", "failed")
        if cancel:
            if not active:
                raise InputError(f"no calibration of suit {chosen.id} is running")
            assert running is not None
            running.routine.cancel(now_ns / 1e9, f"cancelled by {source}")
            self._say(chosen.id, running)
            return {"suit": chosen.id, **running.routine.status(now_ns / 1e9)}
        if active and running is not None:
            raise InputError(f"suit {chosen.id} is being calibrated already (step {running.routine.step}); cancel it "
                             "first (cancel=1)")  # fmt: skip
        if any("/" in sid for sid in chosen.calibration.bones):
            raise InputError(f"suit {chosen.id} has SlimeVR trackers, whose own headings a live calibration does not "
                             "redo: stop the daemon and run `mocapd calibrate imu --mount-yaw ...`")  # fmt: skip
        hint = pose or "n-pose"
        if hint not in ROUTINE_POSES:
            raise InputError(f"pose {hint!r}: one of {', '.join(ROUTINE_POSES)}")
        old = chosen.calibration
        options = RoutineOptions(pose=hint, world_heading=old.world_heading)
        run = _Run(CalibrationRoutine(old.person, dict(old.bones), options), source)
        run.seen_ns = dict.fromkeys(old.bones, now_ns)  # from now on: the wearer hears the first step now
        run.routine.start(now_ns / 1e9)
        self.runs[chosen.id] = run
        log.warning("imu calibration of suit %s asked by %s", chosen.id, source)
        self._say(chosen.id, run)
        return {"suit": chosen.id, **run.routine.status(now_ns / 1e9)}

    def poll(self, ingest: ImuIngest, now_ns: int) -> None:
        """Feed every running routine its suit's new samples; install and write what a finished one calibrated."""
        for suit_id, run in self.runs.items():
            routine = run.routine
            if routine.step in ("done", "failed"):
                continue
            new: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
            for sid in routine.bones:
                stream = ingest.streams.get(sid)
                if stream is None or not len(stream.buffer):
                    continue
                times = stream.buffer.times()
                k = int(np.searchsorted(times, run.seen_ns.get(sid, -1), side="right"))
                if k >= len(times):
                    continue
                rows = stream.buffer.rows()[k:]
                ok = np.all(np.isfinite(rows[:, 0:7]), axis=1)
                new[sid] = (times[k:][ok] / 1e9, rows[ok, 0:4], rows[ok, 4:7])
                run.seen_ns[sid] = int(times[-1])
            try:
                routine.feed(now_ns / 1e9, new)
            except MocapdError as exc:  # samples the routine cannot use: it fails saying why, the daemon runs on
                routine.cancel(now_ns / 1e9, str(exc))
            self._say(suit_id, run)
            if routine.step == "done" and routine.calibration is not None:
                self._finish(suit_id, routine.calibration)

    def _finish(self, suit_id: str, calib: ImuCalibration) -> None:
        suit = Suit.from_calibration(suit_id, calib, self.skeleton)
        path = self.calibration_dir / f"{calib.person}.imu.json"
        try:
            write_text_atomic(path, json.dumps(calib.to_json_dict(), indent=2) + "\n")
            where, written = f"wrote {path}", str(path)
        except (OSError, OutputError) as exc:  # the pose still uses it; the file keeps the old one (a read-only
            # calibration_dir: under the systemd unit's ProtectSystem=strict, one outside its StateDirectory)
            where, written = f"could not write {path} ({exc}): the daemon uses it until it stops", None
        self.install(suit)
        log.warning("imu calibration of suit %s done: %s; the suit is fused with it from now on", suit_id, where)
        self.runs[suit_id].routine.report["file"] = written

    def _say(self, suit_id: str, run: _Run) -> None:
        """The routine's new words on the console."""
        for _, text in run.routine.said[run.said :]:
            log.warning("imu calibration (suit %s): %s", suit_id, text)
        run.said = len(run.routine.said)

    def status(self, now_ns: int) -> dict[str, Any]:
        """Per suit, the routine's state (``imu_calibration_routine`` in /status)."""
        return {k: {**r.routine.status(now_ns / 1e9), "asked_by": r.source} for k, r in self.runs.items()}


def install_suit(scheduler: FixedLatencyScheduler, suits: list[Suit], suit: Suit) -> None:
    """Fuse ``suit`` (same id, sensors and bones as the one it replaces, a new calibration) from the next tick on.

    The scheduler keeps each suit and its mountings (``_q_ib``, the array its tick reads); both are replaced under
    its lock, so a tick sees the old suit or the new one, never half of each.
    """
    old = scheduler.suits[suit.id]
    if old.sensors != suit.sensors:
        raise InputError(f"suit {suit.id}: a live calibration must keep its sensors")
    with scheduler.lock:
        scheduler.suits[suit.id] = suit
        scheduler._q_ib[suit.id] = np.array([suit.calibration.q_ib[sid] for sid in suit.sensors])
    for i, s in enumerate(suits):
        if s.id == suit.id:
            suits[i] = suit
