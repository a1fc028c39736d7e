"""A one-slot queue between capture and processing that always holds the newest frame.

When processing is slower than the camera, the frame waiting in the slot is replaced by
the newer one and counted as dropped: the pose published is always about the most recent
image, and a slow stage can never build up a backlog (and with it, latency).
"""

from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass

from cubeloc.drivers.base import Frame


@dataclass(frozen=True)
class CapturedFrame:
    """A frame as the daemon numbers it."""

    frame: Frame
    seq: int  # the daemon's frame counter, continuous across camera reconnects
    received_monotonic_ns: int  # when the driver handed it over (time.monotonic_ns)
    restart: bool = False  # a new timeline starts here (clock stepped back): reset the processor


class LatestFrameSlot:
    """Thread-safe newest-frame slot: ``put`` never blocks, ``get`` waits with a timeout.

    Items are ``CapturedFrame``s (capture -> processing), or any frozen dataclass without
    a ``restart`` field (processing -> the Foxglove viewer, daemon/viewer.py)."""

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._item: CapturedFrame | None = None
        self._dropped = 0
        self._closed = False

    def put(self, item: CapturedFrame) -> None:
        with self._condition:
            if self._item is not None:
                self._dropped += 1
                if getattr(self._item, "restart", False) and not item.restart:  # the reset must not be lost
                    item = dataclasses.replace(item, restart=True)
            self._item = item
            self._condition.notify()

    def get(self, timeout_s: float) -> CapturedFrame | None:
        """The newest frame not yet taken, or None after ``timeout_s`` or once closed."""
        with self._condition:
            if self._item is None and not self._closed:
                self._condition.wait(timeout_s)
            item, self._item = self._item, None
            return item

    def close(self) -> None:
        """Wake a waiting ``get`` (at shutdown)."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()

    @property
    def dropped(self) -> int:
        with self._condition:
            return self._dropped
