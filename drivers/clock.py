"""Device clock -> host CLOCK_REALTIME: the mapping behind ``Frame.stamp_ns``.

A camera stamps each frame with its own clock (arbitrary epoch, ns). The host notes when
the frame arrived (CLOCK_REALTIME, ns). Their difference is the clock offset plus the
transport latency, and the latency jitters (packet scheduling, interrupts, GIL). The
smallest difference seen recently is the offset plus the *minimum* latency, which barely
moves, so

    offset  = min over a window of (host_receipt_ns - device_ns)
    stamp   = device_ns + offset

maps a frame to the host time at which the camera stamped it, late by only the minimum
transport latency (typically well under a millisecond on GigE) and free of the jitter.
Every stamp is at or before the host receipt time of its frame.

The window (in device time, default 10 s) lets the offset follow the slow drift between
the two crystals (tens of ppm: under a millisecond over the window). Resets:

* the device clock going backwards (camera reset, reconnect, acquisition restart on some
  models) clears the window: the old offsets mean nothing any more;
* a host clock stepped backwards (NTP) gives smaller differences, taken at once by the min;
* a host clock stepped forwards is taken when the old samples leave the window, or at
  once when a difference exceeds the current offset by more than ``step_ns`` (1 s) for
  ``step_samples`` frames in a row, so a step is not mistaken for latency.

Pure: no clocks are read here; the caller passes both times.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class ClockMapping:
    """The mapping for one frame."""

    stamp_ns: int  # host CLOCK_REALTIME at the device timestamp
    offset_ns: int  # host - device offset in use
    reset: bool  # the window was cleared by this sample


class DeviceClockMapper:
    """Running-minimum offset between a device clock and the host clock."""

    def __init__(self, window_ns: int = 10_000_000_000, step_ns: int = 1_000_000_000, step_samples: int = 5) -> None:
        if window_ns <= 0 or step_ns <= 0 or step_samples < 1:
            raise ValueError("window_ns, step_ns and step_samples must be positive")
        self.window_ns = window_ns
        self.step_ns = step_ns
        self.step_samples = step_samples
        # (device_ns, difference) with differences increasing from left to right: the
        # classic monotonic deque for a sliding-window minimum (O(1) amortised per sample).
        self._window: deque[tuple[int, int]] = deque()
        self._last_device_ns: int | None = None
        self._above_in_a_row = 0
        self.resets = 0

    def reset(self) -> None:
        """Forget all samples (call after reconnecting to a camera)."""
        self._window.clear()
        self._last_device_ns = None
        self._above_in_a_row = 0

    @property
    def offset_ns(self) -> int | None:
        return self._window[0][1] if self._window else None

    def map(self, device_ns: int, host_receipt_ns: int) -> ClockMapping:
        """Add one frame's sample and return its host-clock stamp."""
        reset = False
        if self._last_device_ns is not None and device_ns <= self._last_device_ns:
            self.reset()
            reset = True
        difference = host_receipt_ns - device_ns
        if self._window and difference - self._window[0][1] > self.step_ns:
            self._above_in_a_row += 1
            if self._above_in_a_row >= self.step_samples:
                self._window.clear()  # the host clock stepped forwards: start afresh
                reset = True
        else:
            self._above_in_a_row = 0
        if reset:
            self.resets += 1
        while self._window and self._window[-1][1] >= difference:
            self._window.pop()
        self._window.append((device_ns, difference))
        while device_ns - self._window[0][0] > self.window_ns:
            self._window.popleft()
        self._last_device_ns = device_ns
        offset = self._window[0][1]
        return ClockMapping(stamp_ns=device_ns + offset, offset_ns=offset, reset=reset)
