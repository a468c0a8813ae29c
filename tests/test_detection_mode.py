"""The online choice between packed and whole-frame detection (:class:`ModeChooser`), fed with pass results."""

from __future__ import annotations

import itertools

import pytest

from mocapd.errors import InputError
from mocapd.pipeline.detection_mode import ModeChooser, ModeChooserOptions

MS = 1_000_000


def run(chooser: ModeChooser, seconds: float, rate: dict[str, tuple[int, int, int]]) -> list[str]:
    """Passes for ``seconds`` of detector time; ``rate[mode]`` = (usable, frames, pass ns). Returns the modes run."""
    busy, modes = 0, []
    while busy < seconds * 1e9:
        mode = chooser.mode
        usable, frames, ns = rate[mode]
        modes.append(mode)
        chooser.record(mode, usable, frames, ns)
        busy += ns
    return modes


def test_measures_both_then_runs_the_better_and_rechecks_the_other() -> None:
    chooser = ModeChooser(ModeChooserOptions(epoch_s=2.0, first_explore_s=4.0, explore_every_s=20.0, margin=0.1))
    # Packed: 4 camera frames (3 with people) per 250 ms pass = 12 usable/s; whole: 1 per 100 ms = 10 usable/s.
    rates = {"packed": (3, 4, 250 * MS), "whole": (1, 1, 100 * MS)}
    modes = run(chooser, 4.0, rates)
    assert modes[0] == "packed" and "whole" in modes  # both measured, one epoch each
    assert chooser.best == "packed" and chooser.mode == "packed"
    st = chooser.status()
    assert st["rates"]["packed"]["usable_frames_per_s"] == pytest.approx(12.0)
    assert st["rates"]["whole"]["usable_frames_per_s"] == pytest.approx(10.0)
    assert st["rates"]["packed"]["camera_frames_per_s"] == pytest.approx(16.0)
    # The choice holds: the other mode is re-checked after 4 s of packed time, then 8, 16, and 20 (the cap).
    modes = run(chooser, 4 + 2 + 8 + 2 + 16 + 2 + 20 + 2 + 19, rates)
    runs = [m for i, m in enumerate(modes) if i == 0 or modes[i - 1] != m]
    packed_lengths = [sum(1 for _ in g) for m, g in itertools.groupby(modes) if m == "packed"]
    assert runs.count("whole") == 4 and chooser.best == "packed"
    assert [n * 0.25 for n in packed_lengths[:4]] == [4.0, 8.0, 16.0, 20.0]
    # The rig changes (people fill the frames: packing needs a canvas per camera): packed epochs measure the
    # drop, and the next check of the other mode finds it better.
    rates = {"packed": (4, 4, 500 * MS), "whole": (1, 1, 100 * MS)}
    modes = run(chooser, 26.0, rates)
    assert chooser.best == "whole" and modes.count("whole") > modes.count("packed")


def test_a_mode_that_falls_far_below_the_other_is_rechecked_at_once() -> None:
    chooser = ModeChooser(ModeChooserOptions(epoch_s=1.0, first_explore_s=50.0, explore_every_s=100.0))
    run(chooser, 2.0, {"packed": (3, 4, 250 * MS), "whole": (1, 1, 100 * MS)})  # 12 vs 10 usable/s
    assert chooser.best == "packed"
    # Packed drops to 4 usable/s (30 % below whole's 10 and more): whole gets its epoch after the next one,
    # not after the 50 s wait.
    modes = run(chooser, 5.0, {"packed": (4, 4, 1000 * MS), "whole": (1, 1, 100 * MS)})
    assert modes.index("whole") <= 2 and chooser.best == "whole"


def test_a_challenger_within_the_margin_does_not_take_over() -> None:
    chooser = ModeChooser(ModeChooserOptions(epoch_s=1.0, first_explore_s=2.0, explore_every_s=5.0, margin=0.1))
    run(chooser, 30.0, {"packed": (10, 10, 1000 * MS), "whole": (21, 21, 2000 * MS)})  # 10/s vs 10.5/s
    assert chooser.best == "packed"
    # A pass that started before the mode changed counts for nothing.
    epochs = chooser.epochs
    other = "whole" if chooser.mode == "packed" else "packed"
    chooser.record(other, 100, 100, 10**12)
    assert chooser.epochs == epochs


def test_options_are_checked() -> None:
    with pytest.raises(InputError):
        ModeChooserOptions(epoch_s=0.0)
    with pytest.raises(InputError):
        ModeChooser(first="tiles")
