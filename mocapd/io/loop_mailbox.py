"""One mailbox per event loop: worker threads hand it callbacks, and the loop is woken once per batch, not per callback.

Why: every captured frame of every camera crosses from its capture thread to the event loop, and so do its tracked
keypoints and the detector's results. With ``loop.call_soon_threadsafe`` each crossing writes a byte to the loop's
self-pipe: a ``send`` syscall in the posting thread, an epoll wake-up and a ``_read_from_self`` on the loop, and the
interpreter lock handed back and forth. On the 4-camera demo that is ~480 writes a second. Measured (issue 39, 2-core
``Intel(R) Xeon(R) Processor``, ``mocapd demo``, /proc per-thread counters, py-spy): ``call_soon_threadsafe`` ->
``_write_to_self`` was 8-10 % of each capture thread's active samples, the loop spent ~2 % in ``_read_from_self``
and its epoll wake-ups, and it switched ~1200-1900 times a second voluntarily (20-30 per tick) on a saturated machine
where every wake-up is a chance to lose the CPU or the lock to another thread.

:meth:`LoopMailbox.post` appends ``(callback, args)`` to a queue and calls ``call_soon_threadsafe(drain)`` only
when no drain is scheduled; the drain runs, on the loop, every callback queued when it started, in posting order. So
while the loop is busy (a tick, a solve) the frames arriving meanwhile cost one wake-up between them.

What stays as with ``call_soon_threadsafe``:

- each callback runs with the arguments it was posted with (stamps taken in the posting thread stay theirs), in
  posting order, and **no later** than ``call_soon_threadsafe`` would have run it: a post either schedules its own
  drain (where its handle would have gone) or joins a drain already waiting in the loop's queue, ahead of it;
- an exception raised by one callback goes to the loop's exception handler (``loop.call_exception_handler``) and the
  next callbacks still run; ``SystemExit`` and ``KeyboardInterrupt`` propagate, the callbacks left are run by a
  new drain;
- a post to a closed loop is dropped (:meth:`LoopMailbox.post` returns False), and what was queued when the loop
  closed is dropped with it, as the loop's own queue is.

What differs: a callback may now run before one another thread (or this one) posted earlier straight with
``call_soon_threadsafe`` while a drain was already waiting; callbacks run in the posting thread's context only as
the drain's (``contextvars`` are not copied per post: none of the callbacks posted here reads one).
"""

from __future__ import annotations

import asyncio
import threading
import weakref
from collections import deque
from collections.abc import Callable
from typing import TypeVarTuple, Unpack

Ts = TypeVarTuple("Ts")

_mailboxes: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, LoopMailbox] = weakref.WeakKeyDictionary()
_mailboxes_lock = threading.Lock()


class LoopMailbox:
    """A thread-safe queue of callbacks that one event loop drains; get a loop's with :func:`loop_mailbox`.

    Parameters
    ----------
    loop : asyncio.AbstractEventLoop
        The loop that runs the callbacks (held weakly: the registry of mailboxes must not keep a loop alive).
    """

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = weakref.ref(loop)
        self._lock = threading.Lock()
        self._queue: deque[tuple[Callable[..., object], tuple[object, ...]]] = deque()
        self._scheduled = False  # a drain is in the loop's queue and has not started yet
        #: ``call_soon_threadsafe`` calls made (one per drain scheduled from a thread): the wake-ups
        self.wakeups = 0
        #: callbacks posted and run through the mailbox
        self.posted = 0

    def post(self, callback: Callable[[Unpack[Ts]], object], *args: *Ts) -> bool:
        """Run ``callback(*args)`` on the loop soon (from any thread); False when the loop is closed (dropped)."""
        loop = self._loop()
        if loop is None or loop.is_closed():
            return False
        with self._lock:
            self._queue.append((callback, args))
            self.posted += 1
            if self._scheduled:  # a drain waits in the loop's queue, ahead of where this post's handle would go
                return True
            # Under the lock, so that a post that finds a drain scheduled finds it in the loop's queue already.
            self._scheduled = True
            self.wakeups += 1
            try:
                loop.call_soon_threadsafe(self._drain)
            except RuntimeError:
                if not loop.is_closed():
                    raise
                self._queue.clear()  # the loop closed since the check above: dropped, as a post after close is
                self._scheduled = False
                return False
        return True

    def _drain(self) -> None:
        """On the loop: run the callbacks queued so far, in order (those posted meanwhile wait for the next drain,
        which their post scheduled: as with ``call_soon_threadsafe``, they run in the loop's next pass)."""
        with self._lock:
            self._scheduled = False  # before running them: a post from now on schedules the next drain
            count = len(self._queue)
        queue = self._queue
        try:
            for _ in range(count):
                callback, args = queue.popleft()
                try:
                    callback(*args)
                except (SystemExit, KeyboardInterrupt):
                    raise
                except BaseException as exc:  # as asyncio's Handle does: reported, and the loop goes on
                    self._report(callback, exc)
        except BaseException:
            self._reschedule()
            raise

    def _report(self, callback: Callable[..., object], exc: BaseException) -> None:
        loop = self._loop()
        if loop is not None:
            loop.call_exception_handler({"message": f"Exception in callback {callback!r}", "exception": exc})

    def _reschedule(self) -> None:
        """After a drain cut short (``SystemExit``, ``KeyboardInterrupt``): the callbacks left get a drain."""
        loop = self._loop()
        with self._lock:
            if self._queue and not self._scheduled and loop is not None and not loop.is_closed():
                self._scheduled = True
                loop.call_soon(self._drain)


def loop_mailbox(loop: asyncio.AbstractEventLoop) -> LoopMailbox:
    """The mailbox of ``loop`` (made on first use, from any thread; one per loop, so that every thread's posts
    share its wake-ups)."""
    with _mailboxes_lock:
        box = _mailboxes.get(loop)
        if box is None:
            box = _mailboxes[loop] = LoopMailbox(loop)
        return box
