"""Progress bars for long commands (``resolve``, ``export``, ``eval``, ``model fetch``), on a terminal only.

A thin wrapper over :mod:`rich.progress`: one bar with a description, a count, a rate and the time left. It draws
only when its stream is a terminal (``isatty``), so logs, pipes and CI output stay free of control characters;
when it does not draw it costs one integer addition per update. The stream is stderr, so a command's JSON result
on stdout stays machine-readable while the bar is drawn.
"""

from __future__ import annotations

import sys
from types import TracebackType
from typing import TextIO

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, TaskProgressColumn, TextColumn, TimeRemainingColumn
from rich.progress import Progress as RichProgress


class Progress:
    """A progress bar of ``total`` units of work (frames, steps).

    Parameters
    ----------
    total : int
        Units of work planned (at least 1 is shown).
    description : str
        What is being done, shown left of the bar.
    enabled : bool or None
        None: draw only when ``stream`` is a terminal; False: never draw; True: draw when ``stream`` is a terminal
        (a caller's "progress" option can switch the bar off, never force control characters into a pipe).
    stream : text stream
        Where the bar is drawn (default stderr).

    Use it as a context manager, or call :meth:`close`; calling the object advances it by ``n`` units.
    """

    def __init__(self, total: int, description: str = "", enabled: bool | None = None, stream: TextIO | None = None):
        self.stream = sys.stderr if stream is None else stream
        self.done = 0
        self.total = max(int(total), 1)
        self._description = description
        self.active = enabled is not False and _is_terminal(self.stream)
        self._bar: RichProgress | None = None
        if self.active:
            self._bar = RichProgress(
                TextColumn("{task.description}"),
                BarColumn(),
                TaskProgressColumn(),
                MofNCompleteColumn(),
                TimeRemainingColumn(),
                console=Console(file=self.stream),
                transient=False,
            )
            self._task = self._bar.add_task(description, total=self.total)
            self._bar.start()

    def __call__(self, n: int = 1) -> None:
        """Advance by ``n`` units."""
        self.done += n
        if self._bar is not None:
            self._bar.update(self._task, completed=self.done)

    def update(self, done: int, total: int) -> None:
        """Set the units done and the total (for work whose size is known only once it starts)."""
        self.done, self.total = done, max(int(total), 1)
        if self._bar is not None:
            self._bar.update(self._task, completed=done, total=self.total)

    @property
    def label(self) -> str:
        """The description shown beside the bar (e.g. the configuration being evaluated)."""
        return self._description

    @label.setter
    def label(self, text: str) -> None:
        self._description = text
        if self._bar is not None:
            self._bar.update(self._task, description=text)

    def close(self) -> None:
        """Stop drawing (the last state stays on the terminal)."""
        if self._bar is not None:
            self._bar.stop()
            self._bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _is_terminal(stream: TextIO) -> bool:
    isatty = getattr(stream, "isatty", None)
    return bool(isatty is not None and isatty())


__all__ = ["Progress"]
