"""File arguments as a door: a file named on the command line (or in a config) is read only if it is a regular
file of bounded size, and is read with bounded memory.

What this keeps out (issue 34): a FIFO, which makes ``open()`` wait for a writer forever; a character device such
as ``/dev/zero`` (or a symlink to one), which a whole-file read turns into an allocation that grows until the
machine runs out of memory; a directory; a file larger than the reader's format can sensibly be (a 50 GiB "MVNX
file" is damage or an attack, not a recording). The file is opened first, without blocking (``O_NONBLOCK``: a
FIFO opens at once instead of waiting for a writer) and without following into a terminal (``O_NOCTTY``), and the
checks are made on the open descriptor (``fstat``), so a file swapped between a check and the read cannot slip
through; then the read is bounded by the same size limit, in case the file grows while it is read.

Each reader says what its files are (``what``: ``"MT Manager export"``) and how large one may be, and passes the
exception class its callers expect (:class:`~mocapd.errors.InputError`, ``CalibrationError``, ...). Messages are
one line naming the file::

    MT Manager export /tmp/x.txt: not a regular file (a character device); give the export file itself
"""

from __future__ import annotations

import contextlib
import io
import os
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO, TextIO

from mocapd.errors import InputError, MocapdError

MiB = 1 << 20
GiB = 1 << 30

_KINDS = {
    stat.S_IFDIR: "a directory",
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFIFO: "a FIFO",
    stat.S_IFSOCK: "a socket",
}


def file_kind(mode: int) -> str:
    """What a ``st_mode`` is, in words (``"a FIFO (named pipe)"``, ``"a regular file"``)."""
    if stat.S_ISREG(mode):
        return "a regular file"
    return _KINDS.get(stat.S_IFMT(mode), "not a regular file")


def _size(n: int) -> str:
    return f"{n / GiB:g} GiB" if n >= GiB else f"{n / MiB:g} MiB" if n >= MiB else f"{n} bytes"


@contextlib.contextmanager
def open_input(
    path: str | Path, what: str, *, max_bytes: int, error: type[MocapdError] = InputError
) -> Iterator[BinaryIO]:
    """Open ``path`` for reading as a binary file, checked (see the module docstring).

    Parameters
    ----------
    path : path
    what : str
        What the file should be, for messages (``"MVNX file"``).
    max_bytes : int
        Largest size accepted.
    error : MocapdError subclass
        What to raise.

    Raises
    ------
    error
        Missing, unreadable, not a regular file, or larger than ``max_bytes``.
    """
    p = Path(path)
    fd = checked_fd(p, what, max_bytes=max_bytes, error=error)
    try:
        raw = os.fdopen(fd, "rb", buffering=0)
    except BaseException:
        os.close(fd)
        raise
    with io.BufferedReader(_Bounded(raw, max_bytes, f"{what} {p}", error)) as fh:
        yield fh


def checked_fd(path: str | Path, what: str, *, max_bytes: int, error: type[MocapdError] = InputError) -> int:
    """A descriptor (blocking, close-on-exec; the caller closes it) of ``path`` once it is known to be a regular
    file of at most ``max_bytes``: the checks of :func:`open_input`, for readers that take a descriptor or a name
    (:mod:`mocapd.io.media_files` hands decoders ``/proc/self/fd/N``, the file checked)."""
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except FileNotFoundError:
        raise error(f"{what} {p}: no such file") from None
    except IsADirectoryError:
        raise error(f"{what} {p}: a directory, not a file") from None
    except OSError as exc:
        raise error(f"{what} {p}: cannot open: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{what} {p}: not a regular file ({file_kind(st.st_mode)}); give the file itself")
        if st.st_size > max_bytes:
            raise error(f"{what} {p}: {_size(st.st_size)}, larger than the {_size(max_bytes)} a {what} may be")
        os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd


def read_input_bytes(path: str | Path, what: str, *, max_bytes: int, error: type[MocapdError] = InputError) -> bytes:
    """The whole of a checked input file (:func:`open_input`), at most ``max_bytes``."""
    with open_input(path, what, max_bytes=max_bytes, error=error) as fh:
        try:
            return fh.read()
        except OSError as exc:
            raise error(f"{what} {path}: cannot read: {exc.strerror or exc}") from None


def read_input_text(
    path: str | Path,
    what: str,
    *,
    max_bytes: int,
    encoding: str = "utf-8",
    errors: str = "replace",
    error: type[MocapdError] = InputError,
) -> str:
    """The text of a checked input file (:func:`open_input`): ``encoding`` with ``errors``, as ``read_text``."""
    return read_input_bytes(path, what, max_bytes=max_bytes, error=error).decode(encoding, errors)


@contextlib.contextmanager
def open_input_text(
    path: str | Path,
    what: str,
    *,
    max_bytes: int,
    encoding: str = "utf-8",
    errors: str = "replace",
    error: type[MocapdError] = InputError,
) -> Iterator[TextIO]:
    """A checked input file (:func:`open_input`) as text, to be read line by line (bounded memory)."""
    with open_input(path, what, max_bytes=max_bytes, error=error) as fh:
        yield io.TextIOWrapper(fh, encoding=encoding, errors=errors, newline=None)


class _Bounded(io.RawIOBase):
    """A raw file that raises ``error`` once more than ``limit`` bytes were read (a file that grows while it is
    read, or one whose size ``fstat`` did not tell)."""

    def __init__(self, raw: BinaryIO, limit: int, name: str, error: type[MocapdError]) -> None:
        super().__init__()
        self._raw = raw
        self._left = limit
        self._limit = limit
        self._name = name
        self._error = error

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: bytearray | memoryview) -> int:  # type: ignore[override]
        n = self._raw.readinto(buffer)  # type: ignore[attr-defined]
        if not n:
            return 0
        self._left -= n
        if self._left < 0:
            raise self._error(f"{self._name}: grew past {_size(self._limit)} while being read")
        return int(n)

    def fileno(self) -> int:
        return self._raw.fileno()

    def close(self) -> None:
        if not self.closed:
            self._raw.close()
        super().close()
