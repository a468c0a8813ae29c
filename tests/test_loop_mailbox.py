"""The event loop's mailbox (:mod:`mocapd.io.loop_mailbox`) on a real loop with real threads: callbacks posted while
the loop is busy wake it once between them, every callback runs once with its own arguments in posting order (also
when posts race the drain, or come from a callback being drained), an exception in one is reported to the loop's
exception handler and the others still run, and posts to a closed loop are dropped."""

from __future__ import annotations

import asyncio
import gc
import threading
import time
import weakref
from collections.abc import Callable
from typing import Any

import pytest

from mocapd.io.loop_mailbox import loop_mailbox
from tests.loop_spy import spy_wakeups

THREADS, POSTS = 4, 500


async def _until(done: Callable[[], bool], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not done():
        assert time.monotonic() < deadline, "the posted callbacks did not all run"
        await asyncio.sleep(0.001)


def _per_thread_in_order(ran: list[tuple[int, int, int]]) -> None:
    """Every thread's posts ran once each, in the order it posted them, with the stamps it took."""
    for t in range(THREADS):
        mine = [(i, stamp) for thread, i, stamp in ran if thread == t]
        assert [i for i, _ in mine] == list(range(POSTS)), t
        stamps = [stamp for _, stamp in mine]
        assert stamps == sorted(stamps)


def test_posts_made_while_the_loop_is_busy_wake_it_once_and_run_in_posting_order() -> None:
    loop = asyncio.new_event_loop()
    try:
        wakeups = spy_wakeups(loop)
        box = loop_mailbox(loop)
        ran: list[tuple[int, int, int]] = []

        def poster(t: int) -> None:
            for i in range(POSTS):
                box.post(ran.append, (t, i, time.monotonic_ns()))  # stamped in the posting thread

        async def main() -> None:
            threads = [threading.Thread(target=poster, args=(t,)) for t in range(THREADS)]
            for th in threads:
                th.start()
            for th in threads:  # the loop is busy (blocked here) while every post is made
                th.join()
            assert ran == []  # nothing runs before the loop gets back to its queue
            await _until(lambda: len(ran) == THREADS * POSTS)

        loop.run_until_complete(main())
    finally:
        loop.close()
    _per_thread_in_order(ran)
    # call_soon_threadsafe would have written the self-pipe 2000 times; the mailbox wrote it once.
    assert wakeups == ["_drain"] and box.wakeups == 1 and box.posted == THREADS * POSTS


def test_posts_racing_the_drain_are_neither_lost_nor_run_twice() -> None:
    """Threads post while the loop drains (each callback takes a little time, so posts land mid-drain): every
    callback runs exactly once, each thread's in order, and the loop is woken at most once per post."""
    loop = asyncio.new_event_loop()
    try:
        wakeups = spy_wakeups(loop)
        box = loop_mailbox(loop)
        ran: list[tuple[int, int, int]] = []

        def slow_append(item: tuple[int, int, int]) -> None:
            ran.append(item)
            if item[1] % 50 == 0:
                time.sleep(0.001)  # a drain in progress while the threads keep posting

        def poster(t: int) -> None:
            for i in range(POSTS):
                box.post(slow_append, (t, i, time.monotonic_ns()))
                if i % 100 == 0:
                    time.sleep(0.002)  # let the loop drain between bursts: drains start and end under the posts

        async def main() -> None:
            threads = [threading.Thread(target=poster, args=(t,)) for t in range(THREADS)]
            for th in threads:
                th.start()
            await _until(lambda: len(ran) == THREADS * POSTS)
            for th in threads:
                await asyncio.to_thread(th.join)
            await asyncio.sleep(0.05)  # a drain scheduled but empty would run now: nothing more may run

        loop.run_until_complete(main())
    finally:
        loop.close()
    assert len(ran) == THREADS * POSTS
    _per_thread_in_order(ran)
    drains = wakeups.count("_drain")
    assert 1 <= drains == box.wakeups <= THREADS * POSTS


def test_a_callback_posted_by_a_callback_being_drained_runs_in_a_later_drain() -> None:
    loop = asyncio.new_event_loop()
    try:
        box = loop_mailbox(loop)
        ran: list[str] = []

        def first() -> None:
            ran.append("first")
            box.post(ran.append, "posted during the drain")  # the drain cleared its flag before running us

        async def main() -> None:
            box.post(first)
            box.post(ran.append, "second")
            await _until(lambda: len(ran) == 3)

        loop.run_until_complete(main())
    finally:
        loop.close()
    assert ran == ["first", "second", "posted during the drain"]


def test_an_exception_goes_to_the_loops_handler_and_the_next_callbacks_still_run() -> None:
    loop = asyncio.new_event_loop()
    reported: list[dict[str, Any]] = []
    loop.set_exception_handler(lambda _loop, context: reported.append(context))
    try:
        box = loop_mailbox(loop)
        ran: list[int] = []

        def boom(n: int) -> None:
            raise ValueError(f"bad frame {n}")

        def poster() -> None:
            box.post(ran.append, 1)
            box.post(boom, 2)
            box.post(ran.append, 3)

        async def main() -> None:
            th = threading.Thread(target=poster)
            th.start()
            th.join()  # all three in one drain
            await _until(lambda: len(ran) == 2)

        loop.run_until_complete(main())
    finally:
        loop.close()
    assert ran == [1, 3]
    assert len(reported) == 1
    exc = reported[0]["exception"]
    assert isinstance(exc, ValueError) and str(exc) == "bad frame 2"
    assert "boom" in reported[0]["message"]


def test_system_exit_leaves_the_rest_for_the_next_run_of_the_loop() -> None:
    """As with call_soon_threadsafe: SystemExit stops the loop, and the callbacks after it run when it runs again."""
    loop = asyncio.new_event_loop()
    try:
        box = loop_mailbox(loop)
        ran: list[int] = []

        def leave() -> None:
            raise SystemExit(3)

        box.post(ran.append, 1)
        box.post(leave)
        box.post(ran.append, 2)
        with pytest.raises(SystemExit):
            loop.run_until_complete(asyncio.sleep(0.05))
        assert ran == [1]
        loop.run_until_complete(asyncio.sleep(0.05))
    finally:
        loop.close()
    assert ran == [1, 2]


def test_posts_to_a_closed_loop_are_dropped() -> None:
    loop = asyncio.new_event_loop()
    box = loop_mailbox(loop)
    ran: list[int] = []
    assert box.post(ran.append, 1)  # queued, never run: the loop closes first
    loop.close()
    assert not box.post(ran.append, 2)
    # A thread posting while the loop closes under it ends with False, never an exception.
    loop2 = asyncio.new_event_loop()
    box2 = loop_mailbox(loop2)
    results: list[bool] = []
    errors: list[BaseException] = []

    def poster() -> None:
        try:
            while True:
                ok = box2.post(ran.append, 3)
                results.append(ok)
                if not ok:
                    return
        except BaseException as exc:  # the test's point: nothing may escape
            errors.append(exc)

    th = threading.Thread(target=poster)
    th.start()
    time.sleep(0.01)
    loop2.close()
    th.join(10)
    assert not th.is_alive() and errors == [] and results[-1] is False and all(results[:-1])
    assert ran == []


def test_one_mailbox_per_loop_that_does_not_keep_its_loop_alive() -> None:
    loop, other = asyncio.new_event_loop(), asyncio.new_event_loop()
    box = loop_mailbox(loop)
    assert loop_mailbox(loop) is box and loop_mailbox(other) is not box
    ref = weakref.ref(loop)
    loop.close()
    other.close()
    del loop
    gc.collect()
    assert ref() is None
    assert not box.post(print, "gone")  # its loop is gone: dropped
