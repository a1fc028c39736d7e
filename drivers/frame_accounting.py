"""Which buffers become frames, and the counting of those that do not.

Pure bookkeeping shared by streaming backends, kept apart so it can be tested on recorded
buffer sequences at boundaries a real camera rarely produces (wraps, resets, gaps).

* A buffer whose status is not success (missing packets, size mismatch, timeout ...) is
  dropped and counted ``incomplete``, and by its cause in ``incomplete_causes``. Its frame id is used only if it is ahead of the last
  one: a failed buffer may carry the stale id of a frame already delivered.
* A zero device timestamp, or one not after the last accepted frame's, is dropped and
  counted ``bad_timestamp``: downstream code (the clock mapping, the tracker, the
  sequence writer) relies on strictly increasing times.
* Frame ids the camera numbered but we never saw are counted ``frame_id_gaps``. GigE
  Vision 1.x block ids are 16-bit and skip 0 when they wrap (65535 -> 1); GigE Vision 2
  and USB3 Vision ids are 64-bit. An id going backwards other than by a wrap, or jumping
  forwards by more than ``max_gap``, is a counter reset (acquisition restart, camera
  reboot), not a loss.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from cubeloc.drivers.base import CaptureStats

GEV1_MAX_BLOCK_ID = 0xFFFF


class Verdict(Enum):
    ACCEPT = "accept"
    INCOMPLETE = "incomplete"
    BAD_TIMESTAMP = "bad_timestamp"


@dataclass
class FrameAccounting:
    """Feed every buffer through ``judge``; only ACCEPT buffers become frames."""

    stats: CaptureStats
    max_gap: int = 1 << 15
    last_frame_id: int | None = None
    last_timestamp_ns: int | None = None
    id_resets: int = 0

    def restart(self) -> None:
        """Forget the previous stream (after stop/start or a reconnect): ids and clocks restart."""
        self.last_frame_id = None
        self.last_timestamp_ns = None

    def judge(self, status_ok: bool, frame_id: int, timestamp_ns: int, cause: str = "bad_status") -> Verdict:
        """``cause``: why a buffer is not ok (the backend's name for its status), counted
        in ``stats.incomplete_causes``."""
        if not status_ok:
            self.stats.incomplete_causes[cause] = self.stats.incomplete_causes.get(cause, 0) + 1
            # An incomplete frame is not also a gap, so its id counts, but only forwards:
            # Aravis hands back failed buffers with the stale id of a frame already seen.
            if self.last_frame_id is None or frame_id > self.last_frame_id:
                self._count_gap(frame_id)
            self.stats.incomplete += 1
            return Verdict.INCOMPLETE
        self._count_gap(frame_id)
        if timestamp_ns <= 0 or (self.last_timestamp_ns is not None and timestamp_ns <= self.last_timestamp_ns):
            self.stats.bad_timestamp += 1
            return Verdict.BAD_TIMESTAMP
        self.last_timestamp_ns = timestamp_ns
        self.stats.delivered += 1
        return Verdict.ACCEPT

    def _count_gap(self, frame_id: int) -> None:
        last, self.last_frame_id = self.last_frame_id, frame_id
        if last is None:
            return
        if frame_id > last:
            missing = frame_id - last - 1
        elif last <= GEV1_MAX_BLOCK_ID and frame_id < last and last - frame_id > GEV1_MAX_BLOCK_ID // 2:
            # A 16-bit block id wrapped: ids after `last` up to 65535, then 1 .. frame_id-1.
            missing = (GEV1_MAX_BLOCK_ID - last) + max(frame_id - 1, 0)
        else:
            missing = -1  # backwards or repeated: the counter restarted
        if missing < 0 or missing > self.max_gap:
            self.id_resets += 1
            return
        self.stats.frame_id_gaps += missing
