"""Output paths as a door: every file a command writes is checked before the work starts and written atomically.

The rules (issue 34; every output of ``export``, ``calibrate`` and ``import`` goes through here, and so should any
new writer, e.g. an FBX export):

- **Checked first.** :func:`check_output_file` runs before any work: the folder must exist and be a folder, and a
  file must be creatable in it (tried: a read-only file system, ``/proc`` or a folder without write permission is
  found here, not after a minute of resampling); the path must not be a directory, nor anything but a regular file
  if it exists (``/dev/full``, a FIFO: mocapd never writes into devices or pipes, ``--force`` or not); it must not
  be one of the command's inputs (``calibrate convert X X``), and two outputs of one command must not be the same
  file (``export --bvh F --csv F``: :func:`check_distinct`).
- **Existing files.** An existing output is refused unless the command was given ``--force`` (the message says
  so); a command whose purpose is to replace a file (``calibrate imu`` renewing a person's calibration) says it
  replaced one.
- **Atomic.** :func:`atomic_path` / :func:`atomic_file` write a temporary file beside the output (``.<name>.*.part``)
  and rename it over the output only when it is complete and fsynced: a failed or interrupted write (a full disk,
  a crash, Ctrl-C) leaves the old file or none, never half of one. :func:`atomic_directory` does the same for a
  directory (a session being imported).

Every failure is an :class:`~mocapd.errors.OutputError` with one line naming the path; commands print it as
``error: ...`` and exit 2.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO, Any

from mocapd.errors import OutputError
from mocapd.io.input_files import file_kind

MAX_NAME_BYTES = 255
"""Longest file name on Linux file systems (NAME_MAX)."""


def _short(name: str) -> str:
    """The first 100 bytes of a file name, cut on a character boundary: a temporary file's name beside it, which
    must stay under :data:`MAX_NAME_BYTES` with its suffix (100 characters of a 4-byte script are 400 bytes)."""
    return name.encode()[:100].decode("utf-8", "ignore")


def _stat(path: Path) -> os.stat_result | None:
    try:
        return os.stat(path)
    except FileNotFoundError:
        return None
    except OSError as exc:  # ENAMETOOLONG, ENOTDIR (a file used as a folder), ELOOP, EACCES
        raise OutputError(f"{path}: cannot be written: {exc.strerror or exc}") from None


def _folder(path: Path, *, create: bool) -> Path:
    """The folder ``path`` is written into: it must exist and be a folder (``create``: the nearest existing
    ancestor must be one; the rest is made when the file is written)."""
    parent = path.parent
    probe = parent
    while create and _stat(probe) is None and probe != probe.parent:
        probe = probe.parent
    st = _stat(probe)
    if st is None:
        raise OutputError(f"{path}: the folder {parent} does not exist")
    if not stat.S_ISDIR(st.st_mode):
        raise OutputError(f"{path}: {probe} is not a folder ({file_kind(st.st_mode)})")
    _try_create(probe, path)  # the folder, or the ancestor the missing folders will be made in
    return parent


def _try_create(folder: Path, path: Path) -> None:
    """Create and remove a file in ``folder``: the one sure test that the output can be written there."""
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{_short(path.name)}.", suffix=".part")
    except OSError as exc:
        raise OutputError(f"{path}: cannot create a file in {folder}: {exc.strerror or exc}") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(tmp)


def check_output_file(
    path: str | Path,
    *,
    inputs: Sequence[str | Path] = (),
    overwrite: bool = False,
    force_flag: str = "--force",
    create_folder: bool = False,
) -> Path:
    """Check an output file before the work that produces it (see the module docstring).

    Parameters
    ----------
    path : path
    inputs : paths
        The command's input files: the output must be none of them (not even with ``overwrite``).
    overwrite : bool
        An existing regular file may be replaced (the command's ``--force``).
    force_flag : str
        The option that allows it, named in the refusal.
    create_folder : bool
        The output's folder may be missing (it is created when the file is written).

    Returns
    -------
    Path

    Raises
    ------
    OutputError
        One line naming the path and why it cannot be written.
    """
    p = Path(path)
    if not p.name or p.name in (".", ".."):
        raise OutputError(f"{p}: not a file name")
    if len(os.fsencode(p.name)) > MAX_NAME_BYTES:
        raise OutputError(f"{p}: a file name longer than {MAX_NAME_BYTES} bytes")
    _folder(p, create=create_folder)
    st = _stat(p)
    if st is None:
        return p
    if stat.S_ISDIR(st.st_mode):
        raise OutputError(f"{p}: a directory; give a file name")
    if not stat.S_ISREG(st.st_mode):
        raise OutputError(f"{p}: not a regular file ({file_kind(st.st_mode)}); mocapd writes regular files only")
    for given in inputs:
        if _same(p, Path(given)):
            raise OutputError(f"{p}: is an input of this command ({given}); write to another file")
    if not overwrite:
        raise OutputError(f"{p}: exists already; give {force_flag} to replace it, or another name")
    return p


def _same(a: Path, b: Path) -> bool:
    """``a`` and ``b`` are one file (hard links and symlinks included)."""
    with contextlib.suppress(OSError):
        return os.path.samefile(a, b)
    return False


def check_distinct(outputs: Sequence[tuple[str, str | Path]]) -> None:
    """Two outputs of one command must not be the same file: ``[("--bvh", p), ("--csv", q)]``."""
    seen: dict[str, str] = {}
    for option, path in outputs:
        key = os.path.realpath(path)
        if key in seen:
            raise OutputError(f"{path}: given to both {seen[key]} and {option}; each output needs its own file")
        seen[key] = option


def check_output_dir(path: str | Path, *, what: str = "directory") -> Path:
    """A directory a command creates and fills (an imported session): it must not exist, or be an empty
    directory; its folder must exist and be writable."""
    p = Path(path)
    if not p.name or p.name in (".", ".."):
        raise OutputError(f"{p}: not a directory name")
    _folder(p, create=False)
    st = _stat(p)
    if st is None:
        return p
    if not stat.S_ISDIR(st.st_mode):
        raise OutputError(f"{p}: exists and is {file_kind(st.st_mode)}; give the name of a new {what}")
    try:
        empty = next(os.scandir(p), None) is None
    except OSError as exc:
        raise OutputError(f"{p}: cannot be read: {exc.strerror or exc}") from None
    if not empty:
        raise OutputError(f"{p}: exists and is not empty; give the name of a new {what}")
    return p


def _mode_for(path: Path) -> int:
    """The new file's permissions: the replaced file's, else the ones ``open()`` would give (0666 less umask)."""
    with contextlib.suppress(OSError):
        return stat.S_IMODE(os.stat(path).st_mode)
    return 0o666 & ~_umask()


def _sync_folder(folder: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` (same suffix, for writers that choose the format by it) that is renamed
    to ``path`` when the block ends without an exception; removed otherwise. OSError becomes OutputError."""
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)  # checked before (check_output_file(create_folder=True))
        fd, name = tempfile.mkstemp(dir=p.parent, prefix=f".{_short(p.name)}.", suffix=f".part{p.suffix}")
    except OSError as exc:
        raise OutputError(f"cannot write {p}: {exc.strerror or exc}") from None
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, _mode_for(p))
        os.replace(tmp, p)
        _sync_folder(p.parent)
    except OSError as exc:
        raise OutputError(f"cannot write {p}: {exc.strerror or exc}") from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


@contextlib.contextmanager
def atomic_file(path: str | Path, mode: str = "w", **kwargs: Any) -> Iterator[IO[Any]]:
    """``open(path, mode, **kwargs)`` for writing, atomically (:func:`atomic_path`)."""
    with atomic_path(path) as tmp, open(tmp, mode, **kwargs) as fh:
        yield fh


def write_text_atomic(path: str | Path, text: str, encoding: str = "utf-8") -> None:
    with atomic_file(path, "w", encoding=encoding) as fh:
        fh.write(text)


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    with atomic_file(path, "wb") as fh:
        fh.write(data)


@contextlib.contextmanager
def atomic_directory(path: str | Path) -> Iterator[Path]:
    """A temporary directory beside ``path``, renamed to ``path`` (absent or an empty directory) when the block
    ends without an exception; removed with its contents otherwise."""
    p = Path(path)
    try:
        tmp = Path(tempfile.mkdtemp(dir=p.parent, prefix=f".{_short(p.name)}.", suffix=".part"))
    except OSError as exc:
        raise OutputError(f"cannot create {p}: {exc.strerror or exc}") from None
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())
        os.rename(tmp, p)  # onto an empty directory too (rename(2)); a non-empty one: ENOTEMPTY
        _sync_folder(p.parent)
    except OSError as exc:
        raise OutputError(f"cannot create {p}: {exc.strerror or exc}") from None
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _umask() -> int:
    """The process's umask (read by setting and restoring it: commands are single-threaded here)."""
    umask = os.umask(0)
    os.umask(umask)
    return umask
