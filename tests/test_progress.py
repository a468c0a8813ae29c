"""Progress bars (mocapd.io.progress): drawn on a real pseudo-terminal, never into a pipe or a file."""

from __future__ import annotations

import io
import os
import pty

from mocapd.io.progress import Progress


def _pty_stream() -> tuple[io.TextIOWrapper, int]:
    master, slave = pty.openpty()
    return io.TextIOWrapper(os.fdopen(slave, "wb", buffering=0), encoding="utf-8", write_through=True), master


def _drain(fd: int) -> str:
    chunks = []
    os.set_blocking(fd, False)
    while True:
        try:
            chunk = os.read(fd, 65536)
        except BlockingIOError:
            break
        if not chunk:
            break
        chunks.append(chunk)
    return b"".join(chunks).decode("utf-8", "replace")


def test_bar_draws_on_a_terminal() -> None:
    stream, master = _pty_stream()
    try:
        with Progress(10, "resolve", stream=stream) as bar:
            assert bar.active
            for _ in range(10):
                bar(1)
            bar.label = "resolve done"
        text = _drain(master)
    finally:
        stream.close()
        os.close(master)
    assert "resolve done" in text and "10/10" in text
    assert "\x1b[" in text  # drawn with terminal control sequences


def test_nothing_is_written_when_not_a_terminal() -> None:
    out = io.StringIO()
    with Progress(5, "export", stream=out) as bar:
        assert not bar.active
        bar(3)
        bar.update(4, 8)
    assert out.getvalue() == ""
    assert (bar.done, bar.total) == (4, 8)


def test_disabled_bar_stays_silent_on_a_terminal() -> None:
    stream, master = _pty_stream()
    try:
        with Progress(5, "eval", enabled=False, stream=stream) as bar:
            bar(5)
        assert not bar.active
        assert _drain(master) == ""
    finally:
        stream.close()
        os.close(master)
