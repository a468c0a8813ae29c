"""Zero-phase Butterworth band-pass: SciPy's ``sosfiltfilt(butter(2, band, "bandpass", fs=rate, output="sos"), x)``
in NumPy.

The IMU offset estimate (:func:`mocapd.pipeline.time_alignment.estimate_imu_lag`) band-passes two velocities with
this filter. SciPy's signal package took ~1 s of CPU to import (it imports ``scipy.stats`` on the way), paid by the
daemon's warm-up at every ``mocapd run`` and ``demo`` start (imported later, it stalled the first estimate's tick
instead); this module needs none of it and gives the same numbers (to ~1e-13 of the signal's size, tested against
SciPy).

How: the filter is linear, so it is its impulse response ``h`` (computed in closed form from the poles) convolved
with the input, from rest. ``sosfiltfilt`` starts each pass in the filter's steady state for the first sample
``x0``; the filter has zeros at DC (a band-pass), so that start gives the response of ``x - x0`` from rest. The
padding is ``sosfiltfilt``'s: an odd extension of ``3 * 5`` samples at each end (its 2 sections' 5 taps).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]

ORDER = 2
"""The analog prototype's order (a band-pass of it is of twice the order: 2 second-order sections)."""
EDGE = 3 * (2 * ORDER + 1)
"""Samples of odd extension at each end: ``sosfiltfilt``'s default ``padlen`` for 2 sections with no zero tap."""


def band_pass(x: FloatArray, rate_hz: float, low_hz: float, high_hz: float) -> FloatArray:
    """Forward-backward 2nd-order Butterworth band-pass of ``x``: no phase delay.

    Parameters
    ----------
    x : array, shape (n,)
        Samples at ``rate_hz``; ``n`` > 15.
    rate_hz : float
    low_hz, high_hz : float
        The band's -3 dB edges (of one pass), ``0 < low_hz < high_hz < rate_hz / 2``.

    Returns
    -------
    array, shape (n,)
    """
    x = np.asarray(x, dtype=np.float64)
    if not 0 < low_hz < high_hz < rate_hz / 2:
        raise ValueError(f"band must be 0 < low < high < rate / 2, got {low_hz:g}..{high_hz:g} Hz at {rate_hz:g} Hz")
    if x.ndim != 1 or len(x) <= EDGE:
        raise ValueError(f"x must be 1-D with more than {EDGE} samples, got shape {x.shape}")
    ext = np.concatenate([2 * x[0] - x[EDGE:0:-1], x, 2 * x[-1] - x[-2 : -(EDGE + 2) : -1]])
    h = impulse_response(*digital_poles(rate_hz, low_hz, high_hz), len(ext))
    forward = np.convolve(ext - ext[0], h)[: len(ext)]
    backward = np.convolve(forward[::-1] - forward[-1], h)[: len(ext)]
    return np.ascontiguousarray(backward[::-1][EDGE:-EDGE])


def digital_poles(rate_hz: float, low_hz: float, high_hz: float) -> tuple[ComplexArray, float]:
    """The band-pass's poles in the upper half plane (one of each conjugate pair) and its gain; its zeros are
    ``+1, +1, -1, -1``. SciPy's ``butter`` steps: the analog prototype's poles, frequencies pre-warped, the
    low-pass to band-pass transform, the bilinear transform (at ``fs = 2``, as ``butter`` does).

    Returns
    -------
    poles : complex array, shape (2,)
    gain : float
    """
    fs2 = 4.0  # 2 * fs, fs = 2: frequencies in half-cycles per sample
    analog = -np.exp(1j * np.pi * np.arange(-ORDER + 1, ORDER, 2) / (2 * ORDER))
    w1, w2 = (fs2 * np.tan(np.pi * f / rate_hz) for f in (low_hz, high_hz))
    w0, bw = np.sqrt(w1 * w2), w2 - w1
    p = analog * bw / 2
    root = np.sqrt(p**2 - w0**2)
    p_bp = np.concatenate([p + root, p - root])
    p_z = (fs2 + p_bp) / (fs2 - p_bp)
    # the analog zeros (ORDER at s = 0) map to z = 1; the bilinear transform's added ones are at z = -1
    gain = float(bw**ORDER * np.real(fs2**ORDER / np.prod(fs2 - p_bp)))
    return np.asarray(p_z[p_z.imag > 0], dtype=np.complex128), gain


def impulse_response(poles: ComplexArray, gain: float, n: int) -> FloatArray:
    """The first ``n`` samples of the impulse response of ``gain (1 - z⁻²)² / ∏ (1 - p z⁻¹)(1 - p̄ z⁻¹)``.

    Each conjugate pair's all-pole response is ``Im(p^(k+1)) / Im(p)`` (closed form: no recursion, no division
    by a difference of nearly equal poles); the pairs' responses convolved, then the zeros' FIR ``1 - 2 z⁻² + z⁻⁴``.

    Returns
    -------
    array, shape (n,)
    """
    k = np.arange(1, n + 1)
    h = np.ones(1)
    for p in poles:
        h = np.convolve(h, np.imag(p**k) / np.imag(p))[:n]
    out = h.copy()
    out[2:] -= 2 * h[:-2]
    out[4:] += h[:-4]
    return gain * out
