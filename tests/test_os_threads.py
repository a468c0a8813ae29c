"""Threads as the OS sees them (mocapd.io.os_threads): names and per-thread nice values, inherited by the threads
they start (onnxruntime's intra-op pool is started that way from a detector worker)."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from mocapd.io.os_threads import MAX_NICE, nice_this_thread, thread_nice
from mocapd.pipeline.detector_pool import detector_executor


def _comm() -> str:
    return Path(f"/proc/self/task/{threading.get_native_id()}/comm").read_text().strip()


def _child_view() -> tuple[int, str]:
    """(nice, OS name) of a thread started from the calling thread, as that new thread sees itself."""
    got: list[tuple[int, str]] = []
    t = threading.Thread(target=lambda: got.append((thread_nice(), _comm())))
    t.start()
    t.join()
    return got[0]


def test_detector_workers_and_the_threads_they_start_run_nicer_and_the_caller_does_not() -> None:
    base = thread_nice()
    with detector_executor(1, nice=3) as pool:
        worker = pool.submit(lambda: (thread_nice(), _comm())).result()
        started = pool.submit(_child_view).result()
    assert worker == (min(base + 3, MAX_NICE), "mocapd-detect")
    assert started == worker  # what onnxruntime's own threads inherit
    assert thread_nice() == base  # the caller (the event loop in the daemon) keeps its priority
    assert _child_view()[0] == base


def test_nice_is_capped_and_never_raised() -> None:
    def work() -> tuple[int, int]:
        return nice_this_thread(50), nice_this_thread(0)

    with detector_executor(1) as pool:
        assert pool.submit(work).result() == (MAX_NICE, MAX_NICE)
        with pytest.raises(ValueError, match=">= 0"):
            pool.submit(nice_this_thread, -1).result()
