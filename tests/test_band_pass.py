"""The IMU offset estimate's band-pass in NumPy: SciPy's ``sosfiltfilt`` of its ``butter`` band-pass, to rounding."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import butter, sosfiltfilt

from mocapd.core.band_pass import EDGE, band_pass


@pytest.mark.parametrize(
    ("rate_hz", "low_hz", "high_hz", "n"),
    [
        (100.0, 0.3, 5.0, 500),  # the IMU estimate's filter on 5 s (what the IMU buffers hold)
        (100.0, 0.3, 5.0, 3000),
        (60.0, 0.5, 8.0, 300),
        (100.0, 10.0, 10.5, 800),  # narrow: nearly equal poles
        (100.0, 0.05, 49.0, 400),  # wide: poles near both ends of the circle
        (30.0, 1.0, 2.0, EDGE + 1),  # the shortest input sosfiltfilt takes
    ],
)
def test_the_same_numbers_as_scipys_sosfiltfilt(rate_hz: float, low_hz: float, high_hz: float, n: int) -> None:
    rng = np.random.default_rng(n)
    # a drifting walk with an offset and a tone: the padding, the start from rest and the band all matter
    x = np.cumsum(rng.normal(size=n)) + 5.0 + np.sin(np.arange(n) / 10)
    expected = sosfiltfilt(butter(2, [low_hz, high_hz], btype="bandpass", fs=rate_hz, output="sos"), x)
    got = band_pass(x, rate_hz, low_hz, high_hz)
    assert got.shape == x.shape
    assert np.max(np.abs(got - expected)) <= 1e-10 * np.max(np.abs(expected))


def test_a_tone_in_the_band_passes_without_delay_and_one_outside_does_not() -> None:
    t = np.arange(4000) / 100.0
    inside, outside = np.sin(2 * np.pi * 1.5 * t), np.sin(2 * np.pi * 30.0 * t)
    y = band_pass(inside + outside, 100.0, 0.3, 5.0)
    middle = slice(1500, 2500)  # away from the ends' transients (the 0.3 Hz edge's last seconds)
    assert np.max(np.abs(y[middle] - inside[middle])) < 0.01  # forward-backward: no phase shift


def test_a_band_outside_nyquist_or_too_short_an_input_is_refused() -> None:
    x = np.zeros(100)
    with pytest.raises(ValueError, match="band"):
        band_pass(x, 100.0, 5.0, 60.0)
    with pytest.raises(ValueError, match="band"):
        band_pass(x, 100.0, 5.0, 0.3)
    with pytest.raises(ValueError, match="samples"):
        band_pass(np.zeros(EDGE), 100.0, 0.3, 5.0)
