"""The processing stage: newest frame -> ``FrameProcessor`` -> ``pose`` publication.

The loop knows positioning only through ``positioning.estimator.FrameProcessor``: the
tracker (``mode = "tracker"``, the default) or the single-frame target pose (``"target"``);
both see the target through the same ``positioning.observer.TargetObserver``.
A frame whose result carries a trustworthy estimate is published as ``cubeloc.pose/3``,
then handed to the pose sinks (the robot's base in the map as ``cubeloc.pose/4`` with
``[frames]``, the ROS 2 messages with ``[ros2]``); any other frame publishes nothing, and
its status word shows on ``status``.

This loop is also the systemd watchdog's only source (daemon/sdnotify.py): it pets the
watchdog when it processed a frame, or when it found no frame but the capture thread is
alive (waiting for a camera is the daemon working as intended); a hung loop or a hung
capture thread stops the pets and systemd restarts the service.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import structlog

from cubeloc.daemon.capture import CaptureThread
from cubeloc.daemon.frame_queue import CapturedFrame, LatestFrameSlot
from cubeloc.daemon.loop_stats import LoopStats
from cubeloc.daemon.messages import UnpublishablePose, pose_message
from cubeloc.daemon.sdnotify import SystemdNotifier
from cubeloc.positioning.estimator import FrameProcessor, FrameResult, PoseEstimate

# Called with (seq, stamp_ns, estimate) for every pose published on ``pose``: the base's
# pose in the map (``base_pose``), the ROS 2 messages. One that raises costs its own output.
PoseSink = Callable[[int, int, PoseEstimate], None]
# Called with every processed frame and its result, pose or not (the Foxglove viewer); it
# must not block (the viewer's takes the frame into a one-slot queue).
FrameSink = Callable[[CapturedFrame, FrameResult], None]

log = structlog.get_logger()

GET_TIMEOUT_S = 0.2
# Beyond the capture thread's own frame timeout, how long it may go without a sign of life.
CAPTURE_STALL_MARGIN_S = 5.0


class ProcessingLoop:
    def __init__(
        self,
        processor: FrameProcessor,
        slot: LatestFrameSlot,
        capture: CaptureThread,
        stats: LoopStats,
        publish_pose: Callable[[bytes], None],
        notifier: SystemdNotifier,
        stop: threading.Event,
        *,
        expected_size: tuple[int, int],  # (width, height) of the calibration
        capture_stall_s: float,
        summary_period_s: float = 1.0,
        pose_sinks: tuple[PoseSink, ...] = (),
        frame_sinks: tuple[FrameSink, ...] = (),
    ) -> None:
        self._pose_sinks = pose_sinks
        self._frame_sinks = frame_sinks
        self._processor = processor
        self._slot = slot
        self._capture = capture
        self._stats = stats
        self._publish_pose = publish_pose
        self._notifier = notifier
        self._stop = stop
        self._expected_size = expected_size
        self._capture_stall_s = capture_stall_s
        self._summary_period_s = summary_period_s
        self._reset = threading.Condition()
        self._reset_requested = 0
        self._reset_done = 0
        self._size_warned = False
        self._swap_lock = threading.Lock()
        self._swap: tuple[FrameProcessor, tuple[int, int]] | None = None

    # -- a reload: another processor, from a reload thread ---------------------------------
    def swap_processor(self, processor: FrameProcessor, expected_size: tuple[int, int],
                       handover: Callable[[FrameProcessor, FrameProcessor], None] | None = None) -> None:
        """From the next frame on, ``processor`` (for images of ``expected_size``) instead
        of the current one, which is then closed: no frame sees half of each. ``handover(old,
        new)`` runs in the loop's thread just before (the tracker's map saved for the new one)."""
        with self._swap_lock:
            self._swap = (processor, expected_size, handover)

    def _swap_if_requested(self) -> None:
        with self._swap_lock:
            swap, self._swap = self._swap, None
        if swap is None:
            return
        old, (self._processor, self._expected_size, handover) = self._processor, swap
        self._size_warned = False
        if handover is not None:
            try:
                handover(old, self._processor)
            except Exception:  # noqa: BLE001 - the new processor goes on as it was made
                log.exception("handover to the reloaded processor failed")
        close = getattr(old, "close", None)
        if close is not None:
            close()
        log.info("processor swapped in", size=f"{self._expected_size[0]}x{self._expected_size[1]}")

    @property
    def processor(self) -> FrameProcessor:
        return self._processor

    # -- reset, asked for from a Zenoh thread ---------------------------------------------
    def request_reset(self, timeout_s: float = 2.0) -> bool:
        """Ask the loop to reset the processor; True once it has (within ``timeout_s``)."""
        with self._reset:
            self._reset_requested += 1
            ticket = self._reset_requested
            return self._reset.wait_for(lambda: self._reset_done >= ticket or self._stop.is_set(), timeout_s) and self._reset_done >= ticket

    def _reset_if_requested(self) -> None:
        with self._reset:
            pending = self._reset_requested
            if pending <= self._reset_done:
                return
        self._processor.reset()
        log.info("processor reset", requests=pending - self._reset_done)
        with self._reset:
            self._reset_done = pending
            self._reset.notify_all()

    # -- the loop -------------------------------------------------------------------------
    def run(self) -> None:
        next_summary = time.monotonic() + self._summary_period_s
        while not self._stop.is_set():
            self._swap_if_requested()
            self._reset_if_requested()
            item = self._slot.get(GET_TIMEOUT_S)
            if item is not None:
                self._process(item)
                self._notifier.ready(status="streaming")
                self._notifier.watchdog()
            elif self._capture_alive():
                self._notifier.watchdog()
            if self._capture.ended.is_set() and item is None:
                break  # a finite source ran out and the last frame is done
            now = time.monotonic()
            if now >= next_summary:
                self._log_summary()
                next_summary = now + self._summary_period_s
        self._log_summary()
        self._swap_if_requested()  # a processor handed over at the very end is closed too
        with self._reset:
            self._reset.notify_all()  # release reset requests waiting on a stopped loop

    def _capture_alive(self) -> bool:
        return self._capture.is_alive() and time.monotonic() - self._capture.heartbeat < self._capture_stall_s

    def _process(self, item: CapturedFrame) -> None:
        frame = item.frame
        bound = log.bind(seq=item.seq)
        if item.restart:
            # The capture thread saw the clock step back: nothing before this frame may
            # constrain what comes after it (a tracker's motion model, its keyframes).
            self._processor.reset()
            bound.warning("processor reset: the frame timeline restarted")
        height, width = frame.image.shape[:2]
        if (width, height) != self._expected_size:
            result = FrameResult(None, "calibration_mismatch",
                                 f"frame is {width}x{height}, the calibration {self._expected_size[0]}x{self._expected_size[1]}")
            if not self._size_warned:
                bound.error("frame size differs from the calibration; no poses until fixed", detail=result.detail)
                self._size_warned = True
        else:
            try:
                result = self._processor.process(frame.image, frame.stamp_ns, item.seq)
            except Exception:
                # A processor must not raise; if it does it is a bug: log it with its
                # traceback, count it on status, and go on with the next frame.
                bound.exception("frame processor raised")
                self._stats.record_error()
                result = FrameResult(None, "error", "the frame processor raised; see the log")
        for frame_sink in self._frame_sinks:
            try:
                frame_sink(item, result)
            except Exception:  # a bug in a sink: logged and counted, the loop goes on
                bound.exception("frame sink raised", sink=getattr(frame_sink, "__name__", repr(frame_sink)))
                self._stats.record_error()
        if result.estimate is None:
            self._stats.record_frame(item.seq, result.status, result.detail, result.tags_seen)
            return
        try:
            payload = pose_message(item.seq, frame.stamp_ns, result.estimate, time.time_ns())
        except UnpublishablePose as exc:
            bound.warning("pose not published", reason=str(exc))
            self._stats.record_rejected()
            self._stats.record_frame(item.seq, "rejected", str(exc), result.tags_seen)
            return
        self._publish_pose(payload)
        for sink in self._pose_sinks:
            try:
                sink(item.seq, frame.stamp_ns, result.estimate)
            except UnpublishablePose as exc:  # the camera's pose was fine: what the sink made of it is not
                bound.warning("pose not published by a sink", sink=getattr(sink, "__name__", repr(sink)),
                              reason=str(exc))
                self._stats.record_rejected()
            except Exception:  # a bug in a sink: logged and counted, the loop goes on
                bound.exception("pose sink raised", sink=getattr(sink, "__name__", repr(sink)))
                self._stats.record_error()
        self._stats.record_pose((time.monotonic_ns() - item.received_monotonic_ns) / 1e6)
        # On status, a frame with a pose shows the pose's state ("target", "tracking"...).
        self._stats.record_frame(item.seq, result.estimate.state.value, result.detail, result.tags_seen,
                                 result.estimate.source)

    def _log_summary(self) -> None:
        summary = self._stats.take_summary()
        if not summary:
            return
        statuses = {k.split(":", 1)[1]: v for k, v in summary.items() if k.startswith("status:")}
        log.info(
            "processing",
            frames=summary["frames"],
            poses=summary["poses"],
            statuses=statuses,
            fps=round(self._stats.fps(), 1),
            dropped_frames=self._slot.dropped,
            last_seq=self._stats.last_seq,
            camera=self._capture.status().state,
        )
