"""Counters and rolling figures of the processing loop, read by the status publisher.

Written by the processing thread, read by the status thread: every access takes the lock.
Rates are over a sliding window of monotonic times (never loop ticks); latency
percentiles over the last few hundred frames.
"""

from __future__ import annotations

import collections
import threading
import time

import numpy as np

from cubeloc.positioning.estimator import PoseSource

FPS_WINDOW_S = 3.0
LATENCY_WINDOW = 500


class LoopStats:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._frame_times: collections.deque[float] = collections.deque()
        self._latencies_ms: collections.deque[float] = collections.deque(maxlen=LATENCY_WINDOW)
        self.frames = 0
        self.poses = 0
        self.rejected_poses = 0
        self.processor_errors = 0
        self.last_status = "starting"
        self.last_detail = ""
        self.last_tags: tuple[int, ...] = ()
        self.last_seq = -1
        # Time without a pose once there has been one (the tracker lost, the lens covered),
        # and the poses by what measured them (held: orientation from rays, position by the
        # motion model; odometry: the wheels alone).
        self._had_pose = False
        self._last_frame_at: float | None = None
        self._lost_since: float | None = None
        self.lost_s = 0.0
        self.poses_by_source: collections.Counter[str] = collections.Counter()
        self.last_source: PoseSource | None = None
        # Per-second summary counters (reset by ``take_summary``).
        self._summary = collections.Counter()

    def source_now(self) -> str | None:
        """The last frame's pose source (None: that frame had no pose)."""
        with self._lock:
            return None if self.last_source is None else self.last_source.value

    def source_counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self.poses_by_source)

    @property
    def held_frames(self) -> int:
        """Frames whose pose was held on rays (``PoseSource.HELD``)."""
        with self._lock:
            return self.poses_by_source[PoseSource.HELD.value]

    def record_frame(self, seq: int, status: str, detail: str, tags: tuple[int, ...],
                     source: PoseSource | None = None) -> None:
        """One processed frame; ``source`` is its published pose's, None when it has none."""
        now = time.monotonic()
        with self._lock:
            if self._had_pose and source is None and self._last_frame_at is not None:
                self.lost_s += now - self._last_frame_at
                self._lost_since = self._lost_since if self._lost_since is not None else self._last_frame_at
            if source is not None:
                self._had_pose, self._lost_since = True, None
                self.poses_by_source[source.value] += 1
            self.last_source = source
            self._last_frame_at = now
            self.frames += 1
            self.last_seq = seq
            self.last_status, self.last_detail, self.last_tags = status, detail, tags
            self._frame_times.append(now)
            while self._frame_times and now - self._frame_times[0] > FPS_WINDOW_S:
                self._frame_times.popleft()
            self._summary["frames"] += 1
            self._summary[f"status:{status}"] += 1

    def lost_now_s(self) -> float:
        """How long the frames have come without a pose (0 while there is one)."""
        with self._lock:
            return 0.0 if self._lost_since is None else time.monotonic() - self._lost_since

    def record_pose(self, latency_ms: float) -> None:
        with self._lock:
            self.poses += 1
            self._latencies_ms.append(latency_ms)
            self._summary["poses"] += 1

    def record_rejected(self) -> None:
        with self._lock:
            self.rejected_poses += 1

    def record_error(self) -> None:
        with self._lock:
            self.processor_errors += 1

    def fps(self) -> float:
        now = time.monotonic()
        with self._lock:
            times = [t for t in self._frame_times if now - t <= FPS_WINDOW_S]
        if len(times) < 2:
            return 0.0
        # Frames per second between the first and last frame in the window, so the figure
        # does not ramp up slowly after a start or reconnect.
        span = times[-1] - times[0]
        return (len(times) - 1) / span if span > 0 else 0.0

    def latency_percentiles(self) -> dict[str, float | None]:
        with self._lock:
            values = list(self._latencies_ms)
        if not values:
            return {"p50": None, "p99": None}
        p50, p99 = np.percentile(values, [50, 99])
        return {"p50": round(float(p50), 2), "p99": round(float(p99), 2)}

    def take_summary(self) -> collections.Counter:
        """The counters since the last call (for the once-a-second log line)."""
        with self._lock:
            summary, self._summary = self._summary, collections.Counter()
        return summary
