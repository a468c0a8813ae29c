"""Device-time → host-time mapping with drift tracking (pure: times come in as arguments).

An IMU stamps each sample with its own counter (Xsens SampleTimeFine: 10 kHz ticks, 32-bit, wraps every
~4.97 days). The host stamps the same sample when its bytes arrive (``time.monotonic_ns()`` in the I/O layer).
The arrival stamp is the measurement time plus a transport delay that is never negative and often jittery
(USB polling, serial buffering, scheduler), while the two clocks differ by an offset and a slow rate
difference (tens of ppm).

The estimator keeps the last ``window`` pairs and fits ``host = offset + rate · device``: a least-squares
fit, a refit without the stalls (residuals above a quantile), then a shift down to the *lower envelope*
(a 2 % quantile of the residuals). The result maps a device
stamp to the earliest time the host could have received it, i.e. measurement time + minimum transport delay,
with the delay jitter removed. The fit is refreshed every ``refit_every`` samples, which keeps the per-sample
cost to a ring-buffer write.

A device counter that jumps backwards by less than half its range (a device reset, a reconnect) restarts the
estimate; a jump by more than half the range is a wrap and is unwrapped.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


class ClockSync:
    """Drift-tracking map from a device counter to host nanoseconds.

    Parameters
    ----------
    tick_hz : float
        Device counter frequency (10 000 for SampleTimeFine).
    wrap_bits : int
        Width of the device counter.
    window : int
        Number of recent (device, host) pairs used by the fit.
    refit_every : int
        Refit after this many new pairs once the window holds 256 (more often before).
    envelope_quantile : float
        Fraction of least-delayed points used to refit the rate.
    """

    def __init__(
        self,
        *,
        tick_hz: float = 10_000.0,
        wrap_bits: int = 32,
        window: int = 2048,
        refit_every: int = 128,
        envelope_quantile: float = 0.25,
    ) -> None:
        self.tick_hz = tick_hz
        self._period = 1 << wrap_bits
        self._window = window
        self._refit_every = refit_every
        self._quantile = envelope_quantile
        self._dev = np.zeros(window)  # unwrapped device seconds relative to _dev_ref
        self._host = np.zeros(window)  # host seconds relative to _host_ref
        self.resets = 0
        self._reset_state()

    def _reset_state(self) -> None:
        self._n = 0
        self._next = 0
        self._since_fit = 0
        self._last_raw: int | None = None
        self._wraps = 0
        self._dev_ref = 0
        self._host_ref = 0
        self._offset_s = 0.0  # host seconds (rel. _host_ref) at device 0 (rel. _dev_ref)
        self._rate = 1.0
        self._fitted = False

    def _unwrap(self, raw: int) -> int:
        return raw + self._wraps * self._period

    def update(self, device_ticks: int, host_ns: int) -> None:
        """Add one (device counter, host arrival time) pair."""
        if self._last_raw is not None and device_ticks < self._last_raw:
            if self._last_raw - device_ticks > self._period // 2:
                self._wraps += 1
            else:
                self.resets += 1
                self._reset_state()
        if self._last_raw is None:
            self._dev_ref = self._unwrap(device_ticks)
            self._host_ref = host_ns
        self._last_raw = device_ticks
        i = self._next
        self._dev[i] = (self._unwrap(device_ticks) - self._dev_ref) / self.tick_hz
        self._host[i] = (host_ns - self._host_ref) * 1e-9
        self._next = (i + 1) % self._window
        self._n = min(self._n + 1, self._window)
        self._since_fit += 1
        # Refit often while the window fills (the estimate improves quickly), then every refit_every samples:
        # the fitted rate extrapolates, so a fit a second old is off by the rate error × 1 s (microseconds).
        every = 1 if self._n < 16 else (16 if self._n < 256 else self._refit_every)
        if not self._fitted or self._since_fit >= every:
            self._fit()

    def _fit(self) -> None:
        self._since_fit = 0
        d = self._dev[: self._n]
        h = self._host[: self._n]
        if self._n < 8:
            # Too few points for a rate: keep rate 1 and take the least-delayed offset.
            self._rate = 1.0
            self._offset_s = float(np.min(h - d))
            self._fitted = True
            return
        rate, offset = _lstsq_line(d, h)
        resid = h - (offset + rate * d)
        # Refit on the least-delayed points: their spread is much smaller than that of all points, so the rate
        # is less noisy; the offset is then the lower envelope of the residuals. np.partition instead of
        # np.quantile: same order statistic, a fraction of the cost.
        calm = resid <= _order_statistic(resid, self._quantile)
        if np.count_nonzero(calm) >= 4:
            d_calm = d[calm]
            if d_calm.max() > d_calm.min():
                rate, offset = _lstsq_line(d_calm, h[calm])
                resid = h - (offset + rate * d)
        self._rate = rate
        self._offset_s = offset + _order_statistic(resid, 0.02)
        self._fitted = True

    @property
    def ready(self) -> bool:
        """True once at least one pair was seen."""
        return self._fitted

    @property
    def skew_ppm(self) -> float:
        """Estimated rate difference, (host rate / device rate - 1) in parts per million."""
        return (self._rate - 1.0) * 1e6

    def to_host_ns(self, device_ticks: int) -> int | None:
        """Host time (ns) of a device stamp near the latest one, or None before the first pair."""
        if not self._fitted or self._last_raw is None:
            return None
        unwrapped = self._unwrap(device_ticks)
        # A stamp just before a wrap we already counted (or just after one we have not) is off by one period.
        last = self._unwrap(self._last_raw)
        if unwrapped - last > self._period // 2:
            unwrapped -= self._period
        elif last - unwrapped > self._period // 2:
            unwrapped += self._period
        d = (unwrapped - self._dev_ref) / self.tick_hz
        return self._host_ref + round((self._offset_s + self._rate * d) * 1e9)


def _order_statistic(x: NDArray[np.float64], q: float) -> float:
    """The ``q``-quantile of ``x`` as its ``floor(q · (n - 1))``-th smallest element."""
    k = int(q * (len(x) - 1))
    return float(np.partition(x, k)[k])


def _lstsq_line(x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[float, float]:
    """Slope and intercept of the least-squares line through (x, y); centred for numerical stability."""
    xm = float(x.mean())
    ym = float(y.mean())
    dx = x - xm
    denom = float(dx @ dx)
    slope = float(dx @ (y - ym)) / denom if denom > 0.0 else 1.0
    return slope, ym - slope * xm


def offline_clock_map(
    device_ticks: NDArray[np.int64], host_ns: NDArray[np.int64], *, tick_hz: float = 10_000.0, wrap_bits: int = 32
) -> NDArray[np.int64] | None:
    """Host time of every sample of a whole recording, from one fit over all of it (non-causal).

    The arrival times lie on or above the line ``host = offset + rate · device`` (arrival = measurement + a
    delay ≥ the minimum delay). The line that touches them from below with the smallest total delay is the
    support line of their lower convex hull at the mean device time (the linear programme "maximise
    ``offset + rate · mean(device)`` with every residual ≥ 0"). Unlike the live estimate of
    :class:`ClockSync` (a recent window, quantile-based), it is not biased by delays that change over the
    recording, e.g. a host that falls behind for seconds.

    Parameters
    ----------
    device_ticks : int array, shape (n,)
        The device counter of each sample, in arrival order (wraps of ``wrap_bits`` are unwrapped).
    host_ns : int array, shape (n,)
        Host arrival times.

    Returns
    -------
    int array, shape (n,), or None
        Measurement time + minimum delay on the host clock; None when the counter went backwards (a device
        reset), fewer than 2 samples were given, or the fitted rate is not within 1 % of the nominal one.
    """
    ticks = np.asarray(device_ticks, dtype=np.int64)
    host = np.asarray(host_ns, dtype=np.int64)
    if ticks.size < 2:
        return None
    period = 1 << wrap_bits
    step = np.diff(ticks)
    wraps = step < -(period // 2)
    if np.any((step < 0) & ~wraps):
        return None
    unwrapped = ticks + period * np.concatenate(([0], np.cumsum(wraps)))
    x = (unwrapped - unwrapped[0]) / tick_hz
    y = (host - host[0]) * 1e-9
    hull: list[int] = []
    for i in np.lexsort((y, x)):  # by device time, lowest arrival first
        if hull and x[hull[-1]] == x[i]:
            continue
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            # keep b only if it lies strictly below the segment a -> i
            if (x[b] - x[a]) * (y[i] - y[a]) - (y[b] - y[a]) * (x[i] - x[a]) > 0:
                break
            hull.pop()
        hull.append(int(i))
    if len(hull) < 2:
        return None
    hx = x[hull]
    k = int(np.clip(np.searchsorted(hx, x.mean(), side="right") - 1, 0, len(hull) - 2))
    a, b = hull[k], hull[k + 1]
    rate = (y[b] - y[a]) / (x[b] - x[a])
    if not abs(rate - 1.0) < 0.01:
        return None
    out: NDArray[np.int64] = host[0] + np.round((y[a] + rate * (x - x[a])) * 1e9).astype(np.int64)
    return out
