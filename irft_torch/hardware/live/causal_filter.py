"""The offline pipeline's moving average, run causally: samples in one at a time, the same smoothed
values out, each ``(window - 1) / 2`` samples late.

``pipeline.zero_phase_filter`` averages ``window`` samples centred on each one: it needs the
``h = (window - 1) / 2`` samples after it. Live, those have not arrived yet. A trailing average
(output at sample k = mean of samples k - 2h .. k) lags the force by h samples against the contacts
it is paired with (2 ms at 1 kHz for the default window 5), and a lag is an error in every sample
where the force changes. ``CausalMovingAverage`` instead pairs the trailing average with the sample
it is centred on, h samples back: its output for sample k is exactly the centred average, published
when sample k + h arrives. The cost is latency, not accuracy: h samples (2 ms at 1 kHz, 10 ms at
200 Hz), plus, across a masked stretch, the wait for the next valid sample (a masked stretch is
bridged by linear interpolation between its valid neighbours, as ``zero_phase_filter`` bridges it).

Where the two differ: nowhere inside a stream. At a stream's ends both pad with the nearest value
(scipy's ``mode="nearest"``); at a live stream's end that is ``flush``. The numbers agree to
rounding (``tests/hardware/test_causal_filter.py`` checks 1e-12 N against ``zero_phase_filter``).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["CausalMovingAverage", "FilteredSample"]


@dataclass
class FilteredSample:
    """One sample out of the filter: time t [s], the smoothed value (C,) (NaN where masked), whether
    the sample was valid, and whatever was pushed with it (``payload``)."""

    time: float
    value: np.ndarray
    valid: bool
    payload: Any = None


class CausalMovingAverage:
    """The centred moving average of ``pipeline.zero_phase_filter``, causally.

    Args:
        window: samples averaged, odd (1: no filtering, no delay).
        channels: values per sample (2 for (F_x, F_z)).

    Example:
        >>> f = CausalMovingAverage(window=5)
        >>> out = [s for k in range(10) for s in f.push(k * 1e-3, np.array([k, 0.0]))] + f.flush()
        >>> [round(float(s.value[0]), 3) for s in out[:4]]   # nearest padding at the start
        [0.6, 1.2, 2.0, 3.0]
    """

    def __init__(self, window: int = 5, channels: int = 2) -> None:
        if int(window) != window or window < 1 or window % 2 == 0:
            raise ValueError(f"window must be an odd positive integer (samples), got {window}")
        if int(channels) != channels or channels < 1:
            raise ValueError(f"channels must be a positive integer, got {channels}")
        self.window, self.channels, self.half = int(window), int(channels), (int(window) - 1) // 2
        self._filled: deque = deque(maxlen=self.window)  # the last ``window`` bridged values
        self._waiting: deque = deque()  # (time, valid, payload) of samples not yet published, oldest first
        self._masked: list = []  # masked samples since the last valid one: (time, payload), awaiting a bridge
        self._last: np.ndarray | None = None  # the last valid value
        self._n_in = 0

    @property
    def delay(self) -> int:
        """Samples between a sample's arrival and its smoothed value (without masked stretches)."""
        return self.half

    def push(self, time: float, value, valid: bool = True, payload: Any = None) -> list[FilteredSample]:
        """Add one sample: ``value`` (C,), ``valid`` False for a masked one (its value is ignored).
        Returns the samples whose smoothed value is now known (oldest first; usually one, none while
        the window fills or while a masked stretch waits for its next valid neighbour)."""
        if not valid:
            self._masked.append((float(time), payload))
            return []
        x = np.asarray(value, dtype=float).reshape(self.channels)
        if not np.isfinite(x).all():
            raise ValueError(f"value must be finite for a valid sample, got {x.tolist()} at t = {time}")
        out: list[FilteredSample] = []
        if self._masked:  # bridge the masked stretch: linear in sample index, as zero_phase_filter does
            start = self._last if self._last is not None else x  # masked first samples hold the first value
            n = len(self._masked) + 1
            for j, (t_m, p_m) in enumerate(self._masked, start=1):
                out += self._append(start + (x - start) * (j / n), t_m, False, p_m)
            self._masked = []
        out += self._append(x, float(time), True, payload)
        self._last = x
        return out

    def flush(self) -> list[FilteredSample]:
        """End of the stream: the last samples, padded with the last value (``mode="nearest"``)."""
        out: list[FilteredSample] = []
        if self._last is None:  # nothing valid ever arrived
            out = [FilteredSample(t, np.full(self.channels, np.nan), False, p) for t, p in self._masked]
            self._masked = []
            return out
        for t_m, p_m in self._masked:  # masked last samples hold the last valid value
            out += self._append(self._last, t_m, False, p_m)
        self._masked = []
        last = self._filled[-1]
        while self._waiting:
            self._filled.append(last)
            out.append(self._emit())
        return out

    def _append(self, x: np.ndarray, t: float, valid: bool, payload: Any) -> list[FilteredSample]:
        if self._n_in == 0:  # nearest padding before the first sample
            self._filled.extend([x] * self.half)
        self._n_in += 1
        self._filled.append(x)
        self._waiting.append((t, valid, payload))
        return [self._emit()] if len(self._filled) == self.window and len(self._waiting) > self.half else []

    def _emit(self) -> FilteredSample:
        t, valid, payload = self._waiting.popleft()
        value = np.mean(np.stack(self._filled), axis=0) if valid else np.full(self.channels, np.nan)
        return FilteredSample(t, value, valid, payload)
