"""mocapd.io.gc_watch: the daemon's garbage collections counted per generation, with their pauses (issue 45's
soak puts them beside each second of missed ticks)."""

from __future__ import annotations

import gc

import pytest

from mocapd.io.gc_watch import GcWatch


def test_each_collection_is_counted_in_its_generation_with_its_pause() -> None:
    watch = GcWatch()
    watch.install()
    watch.install()  # once only: a second install does not count every collection twice
    try:
        before = watch.status()["generations"]
        cycle: list[object] = []
        cycle.append(cycle)  # something for the collector to free
        del cycle
        gc.collect(2)
        gc.collect(0)
        after = watch.status()["generations"]
    finally:
        watch.uninstall()
    assert after[2]["collections"] == before[2]["collections"] + 1
    assert after[0]["collections"] >= before[0]["collections"] + 1
    assert after[2]["collected"] >= 1
    assert 0 < after[2]["max_pause_ms"] <= after[2]["pause_ms"]
    gc.collect(2)  # uninstalled: no longer counted
    assert watch.status()["generations"][2]["collections"] == after[2]["collections"]
    assert watch._callback not in gc.callbacks


def test_the_frozen_objects_are_counted_at_the_freeze_not_at_every_status(monkeypatch: pytest.MonkeyPatch) -> None:
    """``gc.get_freeze_count`` walks the whole frozen list: ~14 ms of the daemon's event loop at every ``/status``
    snapshot (issue 39's camera demo with the viewer open). The count is taken once, at the freeze."""
    watch = GcWatch()
    kept = [[i] for i in range(1000)]
    try:
        watch.freeze()
        assert watch.frozen >= len(kept)

        def walked() -> int:
            raise AssertionError("status() walked the frozen list")

        monkeypatch.setattr(gc, "get_freeze_count", walked)
        assert watch.status()["frozen"] == watch.frozen
    finally:
        gc.unfreeze()
