"""Record any camera into a sequence (EuRoC layout): the library half of ``cubeloc record``.

Stopping is cooperative: a signal handler sets ``stop``; the loop notices within one
frame timeout, and the writer closes, so the sequence on disk is always valid (the
writer's own guarantee: no truncated PNG, CSV rows only for whole frames). A camera that
disappears is reconnected with back-off (``drivers.reconnect``) while the recording
waits; frames stamped not after the previous one are skipped and counted.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import structlog

from cubeloc.drivers.base import Camera, CaptureStats, EndOfStream, FrameTimeout, StreamBroken
from cubeloc.drivers.reconnect import reopen_with_backoff
from cubeloc.drivers.sequence import SequenceWriter

log = structlog.get_logger()


@dataclass(frozen=True)
class RecordSummary:
    frames: int
    seconds: float
    skipped_non_increasing: int
    stats: CaptureStats
    reason: str  # why the recording ended: "frames", "seconds", "stopped", "end of stream"


def record_sequence(
    camera: Camera,
    writer: SequenceWriter,
    *,
    stop: threading.Event,
    max_frames: int | None = None,
    max_seconds: float | None = None,
    frame_timeout_s: float = 1.0,
) -> RecordSummary:
    """Write frames from a started ``camera`` until a limit, the end, or ``stop``."""
    started = time.monotonic()
    last_stamp: int | None = None
    skipped = 0
    reason = "stopped"
    while not stop.is_set():
        if max_frames is not None and writer.frames >= max_frames:
            reason = "frames"
            break
        if max_seconds is not None and time.monotonic() - started >= max_seconds:
            reason = "seconds"
            break
        try:
            frame = camera.next_frame(frame_timeout_s)
        except FrameTimeout:
            continue
        except EndOfStream:
            reason = "end of stream"
            break
        except StreamBroken as exc:
            log.warning("camera lost while recording; reconnecting", error=str(exc), frames=writer.frames)
            if not reopen_with_backoff(camera, stop=stop):
                break
            continue
        if last_stamp is not None and frame.stamp_ns <= last_stamp:
            skipped += 1  # the clock mapping stepped back (host clock set): keep the CSV ordered
            continue
        writer.write(frame.stamp_ns, frame.image)
        last_stamp = frame.stamp_ns
    return RecordSummary(frames=writer.frames, seconds=time.monotonic() - started,
                         skipped_non_increasing=skipped, stats=camera.stats, reason=reason)
