"""The per-pass choice between packed and whole-frame detection (:class:`ModeChooser`), from each candidate pass's
input pixels and each mode's measured detector time per pixel."""

from __future__ import annotations

import pytest

from mocapd.errors import InputError
from mocapd.pipeline.detection_mode import ModeChooser, ModeChooserOptions, PassCost

MS = 1_000_000
CANVAS = 640 * 640
FITTED = 384 * 640  # a 9:16 camera's whole frame at its aspect
NS_PER_PIXEL = 150.0  # a 640 x 640 canvas in 61 ms: the 2-core laptop's CPU
NO_EXPLORING = ModeChooserOptions(margin=0.05, explore_unsettled_s=1e9, explore_after_s=1e9, explore_always_s=1e9)


def simulate(
    chooser: ModeChooser, seconds: float, ns_per_pixel: dict[str, float], packed_frames: int = 3, noise: float = 0.0
) -> dict[str, int]:
    """Passes for ``seconds`` of detector time on a rig whose packed pass detects ``packed_frames`` cameras on one
    canvas and whose whole pass one camera on a fitted frame; true costs ``ns_per_pixel`` (x :data:`NS_PER_PIXEL`,
    with +-``noise`` alternating). Returns camera frames detected per mode."""
    busy, frames, k = 0.0, {"packed": 0, "whole": 0}, 0
    while busy < seconds * 1e9:
        mode = chooser.choose(PassCost(packed_frames, CANVAS), PassCost(1, FITTED))
        pixels, n = (CANVAS, packed_frames) if mode == "packed" else (FITTED, 1)
        k += 1
        ns = int(NS_PER_PIXEL * ns_per_pixel[mode] * pixels * (1 + (noise if k % 2 else -noise)))
        chooser.record(mode, n, n, pixels, ns)
        busy += ns
        frames[mode] += n
    return frames


def test_before_any_measurement_pixels_per_frame_decide() -> None:
    chooser = ModeChooser(first="whole")
    assert chooser.choose(PassCost(3, CANVAS), PassCost(1, FITTED)) == "packed"  # 137k px a frame against 246k
    assert chooser.choose(PassCost(1, CANVAS), PassCost(1, FITTED)) == "whole"  # one camera on a whole canvas
    # A one-camera canvas cropped to the fitted size costs what the whole frame costs: the last mode keeps it.
    assert chooser.choose(PassCost(1, FITTED), PassCost(1, FITTED)) == "whole"
    assert chooser.choose(PassCost(2, CANVAS), None) == "packed"  # the only candidate
    st = chooser.status()
    assert st["predicted_ms_per_frame"]["whole"] is None and st["switches"] == 3


def test_measured_cost_per_pixel_decides_and_a_switch_needs_the_margin() -> None:
    chooser = ModeChooser(NO_EXPLORING, first="packed")
    # Whole frames measured at 2.2x the cost per pixel (letterboxing, a pass per camera): packing 2 cameras a
    # canvas (205k px a frame) beats a whole frame (246k px x 2.2) ...
    chooser.record("whole", 1, 1, FITTED, int(2.2 * FITTED))
    chooser.record("packed", 2, 2, CANVAS, CANVAS)
    assert chooser.choose(PassCost(2, CANVAS), PassCost(1, FITTED)) == "packed"
    # ... and a whole frame cheaper by less than the margin does not take the pass from the mode that ran last.
    chooser = ModeChooser(NO_EXPLORING, first="packed")
    chooser.record("packed", 1, 1, CANVAS, CANVAS)
    chooser.record("whole", 1, 1, FITTED, int(CANVAS * 0.97))  # 0.97 of a packed pass per frame
    assert chooser.choose(PassCost(1, CANVAS), PassCost(1, FITTED)) == "packed"
    chooser.record("whole", 1, 1, FITTED, int(CANVAS * 0.5))
    chooser.record("whole", 1, 1, FITTED, int(CANVAS * 0.5))
    assert chooser.choose(PassCost(1, CANVAS), PassCost(1, FITTED)) == "whole"
    st = chooser.status()
    assert st["passes"] == {"packed": 1, "whole": 3} and st["chosen"] == "whole"
    assert st["ns_per_pixel"]["packed"] == pytest.approx(1.0)


def test_close_costs_cost_no_throughput_and_never_flap() -> None:
    """The issue-15 bandit's failure: two modes within ~10 % of each other. Per-pass choices lose nothing against
    the better mode forced, however noisy the passes, and do not alternate."""
    ns = {"packed": 1.0, "whole": 3.0 * CANVAS / FITTED / 2.9}  # whole 3 % dearer per frame than a 3-camera canvas
    auto = ModeChooser(ModeChooserOptions(explore_after_s=30.0))
    got = simulate(auto, 300.0, ns, noise=0.08)
    forced = simulate(ModeChooser(NO_EXPLORING), 300.0, {"packed": 1.0, "whole": 1e9})
    assert sum(got.values()) >= 0.99 * sum(forced.values()), (got, forced)
    st = auto.status()
    # One exploring whole pass per 30 s of packed time at most, each a switch there and back.
    assert st["explorations"] <= 10 and st["switches"] <= 2 * st["explorations"] + 2, st


def test_the_rig_changing_moves_the_choice_and_a_stale_mode_is_remeasured() -> None:
    options = ModeChooserOptions(explore_after_s=5.0, explore_margin=0.3, explore_always_s=30.0, window=4)
    chooser = ModeChooser(options)
    simulate(chooser, 20.0, {"packed": 1.0, "whole": 1.0})  # 3 cameras a canvas: packed
    assert chooser.status()["passes"]["packed"] > 0
    # People fill the frames: a camera a canvas (a quarter dearer per frame than a whole frame) ...
    frames = simulate(chooser, 40.0, {"packed": 0.75, "whole": 1.0}, packed_frames=1)
    assert frames["whole"] > 10 * frames["packed"], frames
    # ... and packing, predicted far dearer (its cost per pixel was measured before), is still measured again
    # after explore_always_s, which brings its estimate down to what it costs now.
    packed = chooser.ns_per_pixel["packed"]
    assert chooser.explorations >= 1 and packed is not None and packed < 0.9 * NS_PER_PIXEL
    # A mode never run is measured settle_passes times (3 s of detector time apart), then, 5x dearer, left alone
    # until explore_always_s.
    chooser2 = ModeChooser(options)
    simulate(chooser2, 25.0, {"packed": 1.0, "whole": 5.0})
    assert chooser2.explorations == 3 and chooser2.status()["passes"]["whole"] == 3


def test_options_are_checked() -> None:
    with pytest.raises(InputError):
        ModeChooserOptions(window=0)
    with pytest.raises(InputError):
        ModeChooserOptions(explore_after_s=0.0)
    with pytest.raises(InputError):
        ModeChooser(first="tiles")
    with pytest.raises(InputError):
        ModeChooser().choose(None, None)
    with pytest.raises(InputError):
        ModeChooser().record("tiles", 1, 1, 1, 1)


def test_a_slow_first_pass_does_not_condemn_its_mode() -> None:
    """Live on a loaded machine a mode's first pass ran 6x slower than the rest (sessions warming up) and its
    mode was never chosen again in the run: the median of its passes and the early re-measuring undo that."""
    chooser = ModeChooser(first="whole")
    chooser.record("whole", 1, 1, FITTED, int(NS_PER_PIXEL * FITTED))
    chooser.record("packed", 3, 3, CANVAS, int(6 * NS_PER_PIXEL * CANVAS))  # its first pass: warming up
    frames = simulate(chooser, 30.0, {"packed": 1.0, "whole": 1.0})  # 3 cameras a canvas: packing costs less
    assert frames["packed"] > 5 * frames["whole"], frames
