"""Session directories on disk: a writer thread with a bounded queue, and a reader that recovers torn tails.

A session directory holds ``manifest.json`` and one append-only stream file per kind of record
(:data:`STREAMS`: ``imu.mcs``, ``keypoints.mcs``, ``poses.mcs``; ``mocapd resolve`` adds ``poses-resolved.mcs``),
framed as :mod:`mocapd.protocols.session_format` describes. ``docs/sessions.md`` has the whole layout.

Durability: :class:`SessionWriter` encodes and writes records on its own thread and flushes every stream to the
OS, then ``fsync``\\s it, every ``flush_interval_s`` (at most 1 s). A crash of the process loses only what was
still queued or buffered, a power cut what was not yet fsynced: in both cases at most the last flush interval.
The manifest is written atomically (temporary file, fsync, rename) at the start and again at a clean close, with
``"closed": true`` and the writer's counters; a session whose manifest still says ``"closed": false`` ended
without a clean close.

A write that fails (the disk full: ``ENOSPC``; the drive gone) stops the recording there, for good, with one log
line: every stream ends at its last complete record, and the closing manifest says ``"cut"`` (the errno, when,
which stream). Space for that manifest is held from the start (the opening manifest's padding,
:data:`RESERVE_BYTES`), so a full disk does not keep the session from closing properly.

Recovery: :func:`open_session` reads every stream with :class:`~mocapd.protocols.session_format.StreamDecoder`;
records failing their CRC are counted and skipped (decoding resynchronises on the next record), and a partial
record at the end of a file (the write the crash interrupted) is reported as the torn tail. Everything before it
is returned.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import queue
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar

from mocapd.errors import InputError
from mocapd.io.input_files import read_input_bytes
from mocapd.protocols.session_format import (
    T_EVENT,
    T_FRAME,
    T_HEADER,
    T_IMU,
    T_KEYPOINTS,
    T_POSE,
    FrameRecord,
    ImuRecord,
    KeypointRecord,
    PoseRecord,
    Record,
    StreamDecoder,
    decode_event,
    decode_frame,
    decode_header,
    decode_imu,
    decode_keypoints,
    decode_pose,
    encode_header,
    encode_record,
)

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
SUFFIX = ".mcs"
STREAMS = ("imu", "keypoints", "poses")
FRAMES = "frames"
"""The optional stream of downscaled camera frames (``[record] frames``)."""
EVENTS = "events"
"""What happened to the rig while recording (a camera recalibrated live); sessions before it have none."""
RESOLVED = "poses-resolved"
MAX_FLUSH_INTERVAL_S = 1.0
RESERVE_BYTES = 256 * 1024
"""The opening manifest is padded with spaces to at least this size (and twice its own): disk space held for the
closing manifest, rewritten in place when a full disk refuses a new file, so a session cut by a full disk still
closes with a manifest that says so."""
_CHUNK = 1 << 20
BLOCK = 1 << 16
"""The writer hands the OS whole 64 KiB blocks as they fill (whatever record boundaries fall inside them) and
the rest at each flush: large writes, and a crash between two of them leaves a partial record at the end."""
_STOP = object()
T = TypeVar("T")
MAX_MANIFEST_BYTES = 64 << 20
"""Largest manifest read (a session's is a few KB to a few MB with a long synthetic truth table)."""


def write_json_atomic(path: Path, data: dict[str, Any], pad_to: int = 0) -> None:
    """Write JSON to ``path`` so that a reader sees the old or the new file, never a partial one (and no
    temporary file is left when the write fails: a full disk). ``pad_to``: spaces after the JSON (which allows
    them) up to that many bytes, really written: disk space held for a later rewrite in place."""
    tmp = path.with_name(path.name + ".tmp")
    text = json.dumps(data, indent=1, default=str).encode()
    try:
        with tmp.open("wb") as fh:
            fh.write(text + b" " * max(0, pad_to - len(text) - 1) + b"\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


@dataclass
class WriterCounters:
    """What the writer did (in the manifest at close, and in the recorder's status)."""

    queued: int = 0
    dropped: int = 0
    """Records refused because the queue was full (the disk could not keep up): never blocks the caller."""
    written: int = 0
    bytes: int = 0
    flushes: int = 0
    write_errors: int = 0
    encode_errors: int = 0
    lost_bytes: int = 0
    """Bytes given up when recording stopped on a write error (written to no file)."""
    not_recorded: int = 0
    """Records given after recording stopped on a write error."""
    max_queue: int = 0


class SessionWriter:
    """Appends records to the streams of one session directory from a writer thread.

    Parameters
    ----------
    directory : path
        The session directory; created (with parents). Existing stream files in it are refused.
    manifest : dict
        JSON-able description of the session (written as ``manifest.json`` with ``"closed": false``).
    streams : sequence of str
        Stream names (files ``<name>.mcs``).
    flush_interval_s : float
        Flush (and fsync) cadence, in (0, 1] seconds.
    fsync : bool
        fsync after each flush (power-cut safety) or only flush to the OS (crash safety).
    queue_size : int
        Records the queue holds before :meth:`put` starts dropping (and counting) them.
    """

    def __init__(
        self,
        directory: str | Path,
        manifest: dict[str, Any],
        *,
        streams: tuple[str, ...] = STREAMS,
        flush_interval_s: float = 0.25,
        fsync: bool = True,
        queue_size: int = 100_000,
    ) -> None:
        if not (0 < flush_interval_s <= MAX_FLUSH_INTERVAL_S):
            raise InputError(f"flush_interval_s must be in (0, {MAX_FLUSH_INTERVAL_S}], got {flush_interval_s!r}")
        self.directory = Path(directory)
        self.manifest = dict(manifest)
        self.streams = streams
        self.flush_interval_s = flush_interval_s
        self.fsync = fsync
        self.counters = WriterCounters()
        self._queue: queue.Queue[object] = queue.Queue(maxsize=queue_size)
        self._files: dict[str, Any] = {}
        self._pending: dict[str, bytearray] = {}
        self._thread: threading.Thread | None = None
        self._closed = False
        #: why recording stopped before the close (a write error: the disk full), else None; in the manifest
        self.cut: dict[str, Any] | None = None

    # ------------------------------------------------------------------------------------------ life cycle
    def open(self) -> None:
        """Create the directory, the manifest and the stream files (with their header records); start the
        writer thread."""
        self.directory.mkdir(parents=True, exist_ok=True)
        for name in self.streams:
            path = self.directory / f"{name}{SUFFIX}"
            if path.exists():
                raise InputError(f"session stream {path} exists already: record into a new directory")
        self.manifest["closed"] = False
        size = len(json.dumps(self.manifest, indent=1, default=str))
        write_json_atomic(self.directory / MANIFEST, self.manifest, pad_to=max(RESERVE_BYTES, 2 * size))
        for name in self.streams:
            self._files[name] = (self.directory / f"{name}{SUFFIX}").open("xb", buffering=0)
            self._pending[name] = bytearray(encode_record(T_HEADER, encode_header(name)))
        self._sync()
        self._thread = threading.Thread(target=self._run, name=f"session-writer:{self.directory.name}", daemon=True)
        self._thread.start()

    def put(self, stream: str, rtype: int, encode: Callable[..., bytes], *args: Any) -> bool:
        """Queue one record (``encode(*args)`` runs on the writer thread); never blocks. False when dropped."""
        if self._closed:
            return False
        if self.cut is not None:
            self.counters.not_recorded += 1
            return False
        try:
            self._queue.put_nowait((stream, rtype, encode, args))
        except queue.Full:
            self.counters.dropped += 1
            return False
        self.counters.queued += 1
        return True

    def close(self, update: dict[str, Any] | None = None) -> None:
        """Write what is queued, flush, fsync, close the files and mark the manifest closed (with ``update``)."""
        if self._closed:
            return
        self._closed = True
        if self._thread is not None:
            self._queue.put(_STOP)
            self._thread.join()
        for fh in self._files.values():
            with contextlib.suppress(OSError):  # closing an unbuffered file writes nothing more
                fh.close()
        self.manifest.update(update or {})
        self.manifest["closed"] = True
        self.manifest["writer"] = asdict(self.counters)
        if self.cut is not None:
            self.manifest["cut"] = self.cut
        path = self.directory / MANIFEST
        try:
            write_json_atomic(path, self.manifest)
        except OSError:  # no room for a new file: over the opening one, in the space its padding holds
            try:
                _overwrite_json(path, self.manifest)
            except OSError as exc:
                log.error("session %s: cannot write the closing manifest: %s (`mocapd session` still reads the "
                          "streams)", self.directory, exc.strerror or exc)  # fmt: skip

    # ------------------------------------------------------------------------------------------ the thread
    def _run(self) -> None:
        next_flush = time.monotonic() + self.flush_interval_s
        while True:
            try:
                item = self._queue.get(timeout=max(0.0, next_flush - time.monotonic()))
            except queue.Empty:
                item = None
            if item is _STOP:
                break
            if item is not None:
                self._write(item)
                self.counters.max_queue = max(self.counters.max_queue, self._queue.qsize())
            if time.monotonic() >= next_flush:
                self._sync()
                next_flush = time.monotonic() + self.flush_interval_s
        while True:  # anything put before the stop marker was already taken; drain what raced with it
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if item is not _STOP:
                self._write(item)
        self._sync()

    def _write(self, item: object) -> None:
        stream: str
        rtype: int
        encode: Callable[..., bytes]
        args: tuple[Any, ...]
        stream, rtype, encode, args = item  # type: ignore[misc]
        try:
            data = encode_record(rtype, encode(*args))
        except (InputError, ValueError, struct.error) as exc:  # a value the format cannot hold: counted, skipped
            self.counters.encode_errors += 1
            log.warning("session %s: record not encodable for %s: %s", self.directory, stream, exc)
            return
        if self.cut is not None:
            self.counters.not_recorded += 1
            return
        pending = self._pending[stream]
        pending += data
        try:
            if len(pending) >= BLOCK:
                _write_all(self._files[stream], pending, len(pending) - len(pending) % BLOCK)
        except OSError as exc:
            self._stop_recording(stream, exc)
            return
        self.counters.written += 1
        self.counters.bytes += len(data)

    def _sync(self) -> None:
        if self.cut is not None:
            return
        for name, fh in self._files.items():
            try:
                pending = self._pending[name]
                _write_all(fh, pending, len(pending))
                if self.fsync:
                    os.fsync(fh.fileno())
            except OSError as exc:
                self._stop_recording(name, exc)
                return
        self.counters.flushes += 1

    def _stop_recording(self, stream: str, exc: OSError) -> None:
        """A write failed (the disk is full, the drive went away): stop recording here, for good.

        Writing on after a failed write would leave a hole of unknown size inside a stream, records after it
        stamped as if nothing was missing; stopping leaves every stream ending at its last complete record (a
        partial one at the end is the reader's torn tail). One log line says so; the manifest written at the
        close records it (``cut``), and :meth:`Session.recovery_lines` tells it. The live output is not touched.
        """
        self.counters.write_errors += 1
        name = errno.errorcode.get(exc.errno or 0, "error")
        self.cut = {"errno": name, "error": exc.strerror or str(exc), "stream": f"{stream}{SUFFIX}",
                    "at_utc": datetime.now(UTC).isoformat(), "at_monotonic_ns": time.monotonic_ns(),
                    "records_written": self.counters.written}  # fmt: skip
        for pending in self._pending.values():
            self.counters.lost_bytes += len(pending)
            pending.clear()
        log.error("session %s: recording stopped: cannot write %s%s (%s: %s); the live output goes on, the session "
                  "keeps the %d records written before", self.directory, stream, SUFFIX, name,
                  exc.strerror or exc, self.counters.written)  # fmt: skip


def _overwrite_json(path: Path, data: dict[str, Any]) -> None:
    """Rewrite ``path`` in place with ``data`` as JSON, padded with spaces over the old bytes: no new disk space
    where the old file is at least as long (not atomic: only for when a full disk leaves no other way)."""
    text = json.dumps(data, indent=1, default=str).encode()
    with path.open("r+b") as fh:
        old = fh.seek(0, os.SEEK_END)
        fh.seek(0)
        fh.write(text + b" " * max(0, old - len(text) - 1) + b"\n")
        fh.flush()
        os.fsync(fh.fileno())


def _write_all(fh: Any, pending: bytearray, n: int) -> None:
    """Write the first ``n`` bytes of ``pending`` (all of them, across short writes) and drop them from it."""
    view = memoryview(pending)
    done = 0
    try:
        while done < n:
            done += fh.write(view[done:n])
    finally:
        view.release()
        del pending[:done]


# ---------------------------------------------------------------------------------------------- reading
@dataclass
class StreamReport:
    """What reading one stream found."""

    name: str
    records: int = 0
    corrupt: int = 0
    skipped_bytes: int = 0
    torn_tail_bytes: int = 0
    missing: bool = False
    undecodable: int = 0
    """Records with an intact CRC whose payload did not decode (not written by mocapd): counted and skipped."""

    @property
    def damaged(self) -> bool:
        return self.corrupt > 0 or self.torn_tail_bytes > 0 or self.undecodable > 0

    @property
    def empty(self) -> bool:
        """Present but without a single intact record (not even its header): a zero-length or wiped file."""
        return not self.missing and self.records == 0


def read_stream(path: Path) -> tuple[list[Record], StreamReport]:
    """Every intact record of one stream file (header first) and what was recovered."""
    report = StreamReport(path.name.removesuffix(SUFFIX))
    if not path.exists():
        report.missing = True
        return [], report
    if not path.is_file():  # a directory (or a pipe, which would block) of that name
        raise InputError(f"{path}: not a regular file, not a session stream")
    dec = StreamDecoder()
    records: list[Record] = []
    try:
        with path.open("rb") as fh:
            while chunk := fh.read(_CHUNK):
                dec.receive_data(chunk)
                records.extend(dec.records_received())
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
    report.torn_tail_bytes = dec.finish()
    records.extend(dec.records_received())
    c = dec.counters
    report.records, report.corrupt, report.skipped_bytes = c.records, c.corrupt, c.skipped_bytes
    if records and records[0].rtype == T_HEADER:
        decode_header(records[0].payload)
    return records, report


class Session:
    """An opened session directory: its manifest, and its streams decoded on demand."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        where = self.path / MANIFEST
        if self.path.is_file():
            hint = (f": a pose stream written by `mocapd resolve SESSION -o {self.path}`? Give its session and "
                    f"`--poses {self.path}`" if self.path.suffix == SUFFIX else "")  # fmt: skip
            raise InputError(f"{self.path} is a file, not a session directory{hint}")
        if not where.exists():
            raise InputError(f"{self.path} is not a session directory (no {MANIFEST})")
        try:  # a regular file of sane size: a FIFO or a link to /dev/zero is refused, not waited on or read
            manifest = json.loads(read_input_bytes(where, "session manifest", max_bytes=MAX_MANIFEST_BYTES))
        except UnicodeDecodeError as exc:
            raise InputError(f"{where}: damaged: byte {exc.start} is not UTF-8 (a manifest is JSON text)") from None
        except json.JSONDecodeError as exc:
            raise InputError(f"{where}: not JSON (damaged?): {exc}") from None
        except (OSError, RecursionError) as exc:
            raise InputError(f"{where}: cannot read: {exc}") from None
        if not isinstance(manifest, dict) or manifest.get("format") != "mocapd-session":
            raise InputError(f"{where}: not a mocapd session manifest")
        streams = manifest.get("streams", [])
        if not isinstance(streams, list) or not all(isinstance(x, str) and x.isidentifier() for x in streams):
            raise InputError(f"{where}: damaged: 'streams' is not a list of stream names")
        self.manifest: dict[str, Any] = manifest
        self.reports: dict[str, StreamReport] = {}

    @property
    def closed_cleanly(self) -> bool:
        return bool(self.manifest.get("closed"))

    def _records(self, stream: str, rtype: int, path: Path | None = None) -> Iterator[Record]:
        records, report = read_stream(path if path is not None else self.path / f"{stream}{SUFFIX}")
        self.reports[stream] = report
        return (r for r in records if r.rtype == rtype)

    def has_stream(self, stream: str) -> bool:
        return (self.path / f"{stream}{SUFFIX}").exists()

    def _decoded(self, stream: str, rtype: int, decode: Callable[[bytes], T], path: Path | None = None) -> list[T]:
        """Every record of ``rtype`` in ``stream``, decoded; a payload that does not decode (its CRC intact: a
        record written by something else, or a CRC collision) is counted in the stream's report and skipped, as a
        corrupt record is."""
        out: list[T] = []
        records = self._records(stream, rtype, path)
        report = self.reports[stream]
        for r in records:
            try:
                out.append(decode(r.payload))
            except InputError:
                report.undecodable += 1
        return out

    def poses(self, stream: str = "poses") -> list[PoseRecord]:
        """The recorded frames of a pose stream (``poses`` or ``poses-resolved``), in order."""
        return self._decoded(stream, T_POSE, decode_pose)

    def keypoints(self) -> list[KeypointRecord]:
        return self._decoded("keypoints", T_KEYPOINTS, decode_keypoints)

    def frames(self) -> list[FrameRecord]:
        """The recorded camera frames (none when the session was recorded without them)."""
        if not self.has_stream(FRAMES):
            return []
        return self._decoded(FRAMES, T_FRAME, decode_frame)

    def events(self) -> list[dict[str, object]]:
        """The recorded events (:data:`EVENTS`; none when the session has no such stream), in order."""
        if not self.has_stream(EVENTS):
            return []
        return self._decoded(EVENTS, T_EVENT, decode_event)

    def imu(self) -> list[ImuRecord]:
        return self._decoded("imu", T_IMU, decode_imu)

    def check(self) -> dict[str, StreamReport]:
        """Read every stream file present, and those the manifest lists, and report what was recovered (a listed
        stream without its file is reported ``missing``)."""
        listed = set(self.manifest.get("streams", []))  # sessions from before the manifest listed them: none
        names = {p.name.removesuffix(SUFFIX) for p in self.path.glob(f"*{SUFFIX}")} | listed
        for name in sorted(names):
            self.reports[name] = read_stream(self.path / f"{name}{SUFFIX}")[1]
        return dict(self.reports)

    def require_stream(self, stream: str) -> None:
        """:class:`~mocapd.errors.InputError` naming the stream when its file is missing or holds no intact
        record (a re-solve without the recorded keypoints or IMU samples would be a different, silent answer)."""
        where = self.path / f"{stream}{SUFFIX}"
        if not where.exists():
            raise InputError(f"{where}: missing: the session's {stream} stream is needed here")
        report = self.reports.get(stream) or read_stream(where)[1]
        if report.empty:
            raise InputError(f"{where}: empty: no intact record, not even its header")

    def require_poses(self, stream: str = "poses") -> list[PoseRecord]:
        """The frames of a pose stream, or :class:`~mocapd.errors.InputError` naming it when it is missing, empty
        or holds no pose (what replay and export need)."""
        where = self.path / f"{stream}{SUFFIX}"
        if not where.exists():
            raise InputError(f"{where}: missing: the session has no {stream} stream")
        frames = self.poses(stream)
        if not frames:
            report = self.reports[stream]
            what = "empty (zero length)" if where.stat().st_size == 0 else f"no intact pose in {report.records} records"
            hint = " (an imported IMU session: run `mocapd resolve` first)" if "imported" in self.manifest else ""
            raise InputError(f"{where}: {what}: nothing to read{hint}")
        return frames

    def require_poses_file(self, path: str | Path) -> list[PoseRecord]:
        """The frames of a pose stream file outside the session (``mocapd resolve SESSION -o FILE``), on this
        session's rig; :class:`~mocapd.errors.InputError` naming it when it is missing or holds no pose."""
        where = Path(path)
        if not where.is_file():
            raise InputError(f"{where}: no such pose stream file (`mocapd resolve {self.path} -o {where}` writes one)")
        frames = self._decoded(where.name.removesuffix(SUFFIX), T_POSE, decode_pose, where)
        if not frames:
            raise InputError(f"{where}: no intact pose: nothing to read (not a pose stream of `mocapd resolve -o`?)")
        return frames

    @property
    def cut(self) -> dict[str, Any] | None:
        """Why recording stopped before the session was closed (a write error, e.g. ``ENOSPC``), else None."""
        cut = self.manifest.get("cut")
        return cut if isinstance(cut, dict) else None

    def recovery_lines(self) -> list[str]:
        """Human-readable notes on damaged, missing or empty streams, a recording cut short and an unclean end."""
        lines = [] if self.closed_cleanly else [f"{self.path}: not closed cleanly (the recorder was interrupted)"]
        if (cut := self.cut) is not None:
            why = "the disk was full" if cut.get("errno") == "ENOSPC" else "a write failed"
            lines.append(f"{self.path}: cut by {cut.get('errno', '?')}: recording stopped at {cut.get('at_utc', '?')} "
                         f"because {why} ({cut.get('error', '?')}, writing {cut.get('stream', '?')}); the session "
                         "holds what was written before")  # fmt: skip
        for r in self.reports.values():
            if r.missing:
                lines.append(f"{self.path}/{r.name}{SUFFIX}: missing (the manifest lists this stream)")
            elif r.empty:
                lines.append(f"{self.path}/{r.name}{SUFFIX}: empty: no intact record, not even its header")
            elif r.damaged:
                lines.append(
                    f"{self.path}/{r.name}{SUFFIX}: recovered {r.records} records; {r.corrupt} corrupt "
                    f"({r.skipped_bytes} bytes skipped), torn tail of {r.torn_tail_bytes} bytes dropped"
                    + (f", {r.undecodable} intact records that do not decode skipped" if r.undecodable else "")
                )
        return lines


def open_session(path: str | Path) -> Session:
    """Open a session directory (reads the manifest; streams are read on demand)."""
    return Session(path)


def write_pose_stream(directory: Path, stream: str, payloads: list[bytes]) -> Path:
    """Write a whole pose stream (e.g. ``poses-resolved``) in one go: temporary file, fsync, rename (a write that
    fails or is interrupted by a stop signal leaves the old stream, if any, and no temporary file)."""
    path = directory / f"{stream}{SUFFIX}"
    tmp = path.with_name(path.name + ".tmp")
    try:
        with tmp.open("wb") as fh:
            fh.write(encode_record(T_HEADER, encode_header(stream)))
            for p in payloads:
                fh.write(encode_record(T_POSE, p))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        os.fsync(fd)
        os.close(fd)
    return path


__all__ = [
    "EVENTS",
    "FRAMES",
    "MANIFEST",
    "RESOLVED",
    "STREAMS",
    "T_IMU",
    "T_KEYPOINTS",
    "T_POSE",
    "Session",
    "SessionWriter",
    "StreamReport",
    "open_session",
    "read_stream",
    "write_json_atomic",
    "write_pose_stream",
]
