"""A mocapd process from its first line to its last: stop signals, the phase it is in, children that end with it,
and a quick exit.

**Stop signals.** SIGINT (Ctrl-C), SIGTERM (``kill``, systemd) and SIGHUP (the terminal or SSH session closed)
mean the same thing: stop cleanly. :func:`install_stop_signals` is the first thing the ``mocapd`` command does,
before the seconds of imports (NumPy, SciPy, OpenCV) that follow, so there is no window where a signal prints a
``KeyboardInterrupt`` traceback or is lost. A SIGINT inherited as *ignored* (a background job of a shell script)
is handled all the same: a script that sends it means it. A SIGHUP inherited as ignored (``nohup``) stays
ignored: closing that terminal is not a stop.

What a stop signal does depends on where the process is:

- while something waits for it (:func:`on_stop`: the daemon's stop event, :func:`stop_event`, a parent that
  forwards it to its child), each waiting target is called and nothing is raised;
- while the process is still ``starting`` (imports, arguments, config: nothing opened, nothing written), it
  ends at once with the command's stop status: an exception raised into C code there is not safe (NumPy's
  import turned one into an ``ImportError`` and a traceback);
- otherwise the first one raises :class:`StopRequested` in the main thread (the way Python raises
  ``KeyboardInterrupt``), unwinding whatever runs through its ``finally`` blocks — never inside an import (it is
  raised once the import is done) — unless that code said it checks for itself (:func:`deferred`).

Either way one line goes to stderr naming the signal and the :func:`phase` the process was in, so a technician
knows what was interrupted. Repeated signals are counted, not acted on twice.

**Children.** Every child process mocapd starts is started through this module (:func:`child_command` for a
Python function, :func:`guarded_command` for any program): it first asks the kernel (``PR_SET_PDEATHSIG``) for
SIGTERM when its parent ends, however the parent ends — SIGKILL, the OOM killer, a crash — so no camera server or
namespace child is left holding a port, and a child that is mocapd stops as cleanly as on Ctrl-C (its recording
closed). The setting survives ``exec`` (of ``unshare``/``nsenter``, which put children in private namespaces),
and is set in the child itself, not in a ``preexec_fn`` (unsafe in a process with threads). It is tied to the
parent *thread*: children are started from the thread that outlives them, the main thread, whose event loop runs
the daemon. A Python child then installs the same stop signals before it imports its module.

**Exit.** :func:`exit_now` ends a process whose work is closed without the interpreter's teardown (seconds of
numeric libraries' finalisers on a loaded machine), after removing the temporary directories registered with
:func:`remove_at_exit` (a stop during start-up may leave a builder thread behind, abandoned: what it made on disk
must not be).
"""

from __future__ import annotations

# Light on purpose: this module is imported first, and until it has installed the handlers a stop signal has
# Python's default effect. asyncio, logging, ctypes are imported where they are used.
import contextlib
import os
import signal
import sys
import time
from collections.abc import Callable, Coroutine, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn, TypeVar

if TYPE_CHECKING:
    import asyncio

    from mocapd.io.log_throttle import RepeatFilter

#: the signals that ask a mocapd process to stop
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
#: Linux prctl(2) option: the signal this process gets when its parent thread ends
PR_SET_PDEATHSIG = 1
T = TypeVar("T")


class StopRequested(BaseException):
    """A stop signal arrived where nothing waits for it: raised in the main thread to unwind the command.

    A ``BaseException``, like ``KeyboardInterrupt``: ``except Exception`` blocks let it through.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class _State:
    """The process's stop state (a plain class: ``dataclasses`` costs this early module 17 ms of imports)."""

    def __init__(self) -> None:
        self.installed = False
        self.signum: int | None = None
        self.received_ns: int | None = None
        self.count = 0
        self.raise_outside = True
        self.phase = "starting"
        self.name = "mocapd"
        self.targets: list[Callable[[int], None]] = []
        self.quiet = 0  # targets that announce the stop themselves (a child the signal is forwarded to)
        self.starting_status: Callable[[int], int] = lambda _signum: 0
        self.remove: list[Path] = []
        self.previous: dict[int, object] = {}


_state = _State()


def signal_name(signum: int) -> str:
    return signal.Signals(signum).name


# ---------------------------------------------------------------------------------------------- stop signals
def install_stop_signals(name: str = "mocapd", starting_status: Callable[[int], int] | None = None) -> None:
    """Handle SIGINT, SIGTERM and SIGHUP as stop requests from now on (main thread only; once).

    ``name`` starts the line said on stderr when one arrives (``mocapd run``, ``fake camera CAM01``);
    ``starting_status(signum)`` is the exit status of a stop while still starting (default 0).
    """
    _state.name = name
    if starting_status is not None:
        _state.starting_status = starting_status
    if _state.installed:
        return
    for sig in STOP_SIGNALS:
        current = signal.getsignal(sig)
        if sig == signal.SIGHUP and current is signal.SIG_IGN:
            continue  # nohup: the terminal closing is not a stop
        _state.previous[sig] = current
        signal.signal(sig, _on_signal)
    _state.installed = True


def uninstall_stop_signals() -> None:
    """Put back the handlers :func:`install_stop_signals` replaced (for callers that installed them for a while)."""
    for sig, handler in _state.previous.items():
        signal.signal(sig, handler)  # type: ignore[arg-type]
    _state.previous.clear()
    _state.installed = False


def _on_signal(signum: int, _frame: object) -> None:
    _state.count += 1
    first = _state.signum is None
    if first:
        _state.signum = signum
        _state.received_ns = time.monotonic_ns()
    if first and not _state.quiet:
        # os.write, not print: a handler may run in the middle of a print to the same stream (reentrant call).
        line = f"{_state.name}: {signal_name(signum)} while {_state.phase}: stopping\n"
        with contextlib.suppress(OSError):
            os.write(2, line.encode(errors="replace"))
    for target in list(_state.targets):
        target(signum)
    if _state.targets or not first:
        return
    if _state.phase == "starting":  # nothing opened or written yet: end now, no exception into C code
        with contextlib.suppress(Exception):
            sys.stdout.flush()
        os._exit(_state.starting_status(signum))
    if _state.raise_outside:
        _raise_when_safe(signum, _frame)


def _in_import(frame: Any) -> bool:
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _raise_when_safe(signum: int, frame: Any) -> None:
    """Raise :class:`StopRequested` now, or (inside an import, whose C parts turn exceptions into ImportErrors)
    as soon as the import is done: SIGALRM every 20 ms looks again."""
    if not _in_import(frame):
        signal.setitimer(signal.ITIMER_REAL, 0)
        raise StopRequested(signum)
    signal.signal(signal.SIGALRM, lambda _s, f: _raise_when_safe(signum, f))
    signal.setitimer(signal.ITIMER_REAL, 0.02)


def requested() -> int | None:
    """The first stop signal received so far (None: none)."""
    return _state.signum


def received_ns() -> int | None:
    """``time.monotonic_ns()`` when the first stop signal arrived (None: none)."""
    return _state.received_ns


def reset() -> None:
    """Forget the stop signals received (for a process that runs several commands: tests in one process)."""
    _state.signum = _state.received_ns = None
    _state.count = 0
    _state.phase = "starting"


def enter_phase(phase: str) -> None:
    """Say what the process is doing now: named by the line a stop signal prints, and sent to systemd (or a
    test) as ``STATUS=<phase>`` where ``$NOTIFY_SOCKET`` is set."""
    _state.phase = phase
    if os.environ.get("NOTIFY_SOCKET"):
        from mocapd.io.sd_notify import SdNotifier

        notifier = SdNotifier()
        notifier.notify(f"STATUS={phase}")
        notifier.close()


def phase() -> str:
    return _state.phase


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Inside, a stop signal nobody waits for is only recorded (:func:`requested`), never raised: for code that
    checks for itself, such as the start of an event loop before its stop event exists."""
    before = _state.raise_outside
    _state.raise_outside = False
    try:
        yield
    finally:
        _state.raise_outside = before


def interruptible(fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
    """``fn(*args, **kwargs)`` in a worker thread, the main thread waiting for it in 0.1 s naps: a stop signal is then
    handled within 0.1 s (raised here as :class:`StopRequested`) even while ``fn`` spends minutes in one C call that
    released the GIL, where Python would run the handler only once the call returns (issue 45: ``calibrate
    cameras`` deaf to SIGINT and SIGTERM inside OpenCV for two minutes). The worker is a daemon thread, abandoned
    on a stop: the command ends with :func:`exit_now`. ``fn``'s exception is raised here."""
    import threading

    outcome: list[Any] = []

    def work() -> None:
        try:
            outcome.append((True, fn(*args, **kwargs)))
        except BaseException as exc:  # handed to the main thread, raised there
            outcome.append((False, exc))

    worker = threading.Thread(target=work, name=getattr(fn, "__name__", "work"), daemon=True)
    worker.start()
    while worker.is_alive():
        worker.join(0.1)
    ok, value = outcome[0]
    if not ok:
        raise value
    return value  # type: ignore[no-any-return]


@contextlib.contextmanager
def on_stop(target: Callable[[int], None], *, quiet: bool = False) -> Iterator[None]:
    """Call ``target(signum)`` on every stop signal while inside (at once if one came already). It runs in the
    signal handler, in the main thread, between two bytecodes of whatever runs there: it must only set flags,
    schedule work or send signals. ``quiet``: the target says what stops itself (a child the signal is forwarded
    to prints its own line), this process does not."""
    _state.targets.append(target)
    _state.quiet += quiet
    try:
        if _state.signum is not None:
            target(_state.signum)
        yield
    finally:
        _state.quiet -= quiet
        _state.targets.remove(target)


def run_until_stopped(main: Callable[[asyncio.Event], Coroutine[Any, Any, T]]) -> T:
    """``asyncio.run(main(stop))`` with stop signals setting ``stop`` from the loop's first instant to its last
    (none is raised into the loop's machinery)."""

    import asyncio

    async def wrapper() -> T:
        stop = asyncio.Event()
        with stop_event(stop):
            return await main(stop)

    with deferred():
        return asyncio.run(wrapper())


@contextlib.contextmanager
def stop_event(stop: asyncio.Event) -> Iterator[None]:
    """Stop signals set ``stop`` while inside (call on the event loop's thread). A process that did not
    :func:`install_stop_signals` (a test, a library user) gets them for the time inside, on the main thread."""
    import asyncio
    import threading

    loop = asyncio.get_running_loop()

    def fire(_signum: int) -> None:
        with contextlib.suppress(RuntimeError):  # the loop closed: nothing waits any more
            loop.call_soon_threadsafe(stop.set)

    main = threading.current_thread() is threading.main_thread()
    temporary = not _state.installed and main
    if temporary:
        install_stop_signals(_state.name)
    try:
        with deferred(), on_stop(fire), _loop_woken_by_signals(loop) if main else contextlib.nullcontext():
            yield
    finally:
        if temporary:
            uninstall_stop_signals()


@contextlib.contextmanager
def _loop_woken_by_signals(loop: asyncio.AbstractEventLoop) -> Iterator[None]:
    """While inside, a signal wakes ``loop`` whichever thread the kernel delivers it to.

    Python runs a signal's handler in the main thread, the next time that thread runs bytecode. The kernel may
    deliver a process-directed signal to any thread: one delivered to a worker (a kernel compile, a model load,
    a camera's capture thread) while the loop sleeps in ``epoll_wait`` with nothing scheduled left the handler
    waiting until something else woke the loop (CI: a SIGHUP during the solver kernel's compile was acted on
    15 s later, when the compile finished, after READY). The C-level handler writes the signal's number to the
    wakeup fd from whichever thread it runs on; the loop reads it, and the main thread then runs the handler.
    """
    import socket

    reader, writer = socket.socketpair()
    reader.setblocking(False)
    writer.setblocking(False)

    def drain() -> None:
        with contextlib.suppress(OSError):
            while reader.recv(4096):
                pass

    loop.add_reader(reader.fileno(), drain)
    previous = signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
    try:
        yield
    finally:
        signal.set_wakeup_fd(previous)
        loop.remove_reader(reader.fileno())
        reader.close()
        writer.close()


# ---------------------------------------------------------------------------------------------- children
def die_with_parent(parent: int, sig: int = signal.SIGTERM) -> None:
    """In a child process: receive ``sig`` when the parent thread that started it ends, however it ends.

    ``parent`` is the pid the child was started by: if it died before this call, the child is re-parented
    already and no signal would come, so it is sent now.
    """
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    libc.prctl.restype = ctypes.c_int
    if libc.prctl(PR_SET_PDEATHSIG, sig, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent:
        os.kill(os.getpid(), sig)


def child_command(target: str, *args: str) -> list[str]:
    """The command line that runs ``target`` (``"package.module:function"``, called with the list ``args``) in a
    child Python process that ends with this one and handles stop signals from its first line
    (:func:`child_main`)."""
    return [sys.executable, "-m", "mocapd.io.lifecycle", "--parent", str(os.getpid()), target, *args]


def guarded_command(cmd: list[str]) -> list[str]:
    r"""``cmd`` (any program: ``unshare``, ``nsenter``, ``pip``, Blender) started so that it ends with this
    process: a small Python sets its parent-death signal and ``exec``\s it (the setting survives ``exec``)."""
    return [sys.executable, "-m", "mocapd.io.lifecycle", "--parent", str(os.getpid()), "--exec", *cmd]


def child_main(argv: list[str] | None = None) -> NoReturn:
    """``python -m mocapd.io.lifecycle [--parent PID] (--exec PROGRAM ARGS... | MODULE:FUNCTION ARGS...)``.

    With ``--parent``, the process ends with that parent (:func:`die_with_parent`). ``--exec`` then runs the
    program in this process. Otherwise: stop signals installed, logging rate-limited, then ``FUNCTION(ARGS)`` of
    ``MODULE`` (returning an exit status); a stop before it serves ends it with status 0.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--parent"]:
        die_with_parent(int(argv[1]))
        argv = argv[2:]
    if argv[:1] == ["--exec"]:
        os.execvp(argv[1], argv[1:])
    target = argv.pop(0)
    module, _, function = target.partition(":")
    install_stop_signals(f"{module.rsplit('.', 1)[-1]} (pid {os.getpid()})")
    setup_logging()
    try:
        import importlib

        code = int(getattr(importlib.import_module(module), function)(argv))
    except StopRequested:
        code = 0
    exit_now(code)


# ---------------------------------------------------------------------------------------------- logging, exit
def setup_logging(level: int | None = None) -> RepeatFilter:
    """The process's log lines: one format on stderr (WARNING and above unless ``level``), every call site
    rate-limited with a count (:mod:`mocapd.io.log_throttle`). Idempotent."""
    import logging

    from mocapd.io.log_throttle import install

    logging.basicConfig(level=logging.WARNING if level is None else level,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")  # fmt: skip
    return install()


def remove_at_exit(path: Path) -> None:
    """Remove directory ``path`` when the process ends through :func:`exit_now` (unless forgotten first)."""
    _state.remove.append(path)


def forget_at_exit(path: Path) -> None:
    """The owner removed ``path`` itself."""
    with contextlib.suppress(ValueError):
        _state.remove.remove(path)


def exit_now(code: int) -> NoReturn:
    """Flush the log and standard streams and end the process without the interpreter's teardown.

    Only for a process whose work is closed (devices, sockets, sessions flushed and fsynced, threads joined) or
    abandoned on purpose (a model load or kernel compile in a daemon thread when a stop came during start-up):
    tearing down the numeric libraries (numba, onnxruntime, OpenCV, SciPy, matplotlib) takes a second or more on
    a loaded 2-core machine, and a daemon asked to stop must be gone within ``daemon.shutdown_timeout_s`` plus a
    second (systemd's ``TimeoutStopSec``, a technician's Ctrl-C).
    """
    import logging
    import shutil

    from mocapd.io.log_throttle import RepeatFilter

    for path in _state.remove:
        shutil.rmtree(path, ignore_errors=True)
    for handler in logging.getLogger().handlers:  # counts of rate-limited log lines not yet said
        for f in handler.filters:
            if isinstance(f, RepeatFilter):
                f.flush()
    logging.shutdown()
    with contextlib.suppress(OSError, ValueError):
        sys.stdout.flush()
    with contextlib.suppress(OSError, ValueError):
        sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":  # run as a script this file is a second module: use the one everything else imports
    from mocapd.io.lifecycle import child_main as _child_main

    _child_main()
