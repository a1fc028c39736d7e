"""The capture thread: keeps a camera streaming into the newest-frame slot, whatever happens.

No camera at boot, a pulled cable, a stream that stops: none of it ends the process. The
thread closes what is left of the camera, waits (exponential back-off on monotonic
deadlines, cut short by shutdown), opens a fresh camera with the same settings and carries
on; its state shows on ``status`` and in the logs. A finite source (replay, synthetic)
that ends sets ``ended``. Anything that is not a camera error is a bug: it is kept in
``failure`` and stops the daemon.

Every frame is checked at this boundary before the processor can see it (a driver bug, a
misconfigured camera, a clock step): a frame that is not Mono8 (H, W) uint8, of another
size than the camera settings, or stamped at or before the previous frame, is dropped;
a frame-id jump is counted. Each kind is counted (``faults``, on ``status``) and logged
(the first at once, then at most every ``FAULT_LOG_PERIOD_S`` with the count). Stamps
that stay behind for ``STAMP_RESTART_FRAMES`` frames in a row are a host clock stepped
back (NTP): the new timeline is accepted and the frame is marked ``restart`` so the
processor starts afresh, rather than dropping frames until the clock catches up.
"""

from __future__ import annotations

import collections
import contextlib
import threading
import time
from collections.abc import Callable

import numpy as np
import structlog

from cubeloc.daemon.cameras import make_camera
from cubeloc.daemon.frame_queue import CapturedFrame, LatestFrameSlot
from cubeloc.daemon.messages import CameraStatus
from cubeloc.drivers.base import (
    Camera,
    CameraError,
    CameraSettings,
    EndOfStream,
    Frame,
    FrameTimeout,
)
from cubeloc.errors import CubelocError

log = structlog.get_logger()

# next_frame is called with at most this timeout so that a shutdown is seen quickly even
# when the configured frame timeout is long.
POLL_S = 0.25
FAULT_LOG_PERIOD_S = 10.0
STAMP_RESTART_FRAMES = 3
# The backends' own counters shown on status ("timeouts" is not: the backends count every
# short poll of this thread that found no frame; frame_timeout above is the real one).
CAMERA_COUNTERS = ("incomplete", "bad_timestamp", "frame_id_gaps")
DROPPED_KINDS = ("bad_format", "wrong_size", "stamp_not_increasing")  # the faults that drop the frame
GEV1_MAX_BLOCK_ID = 0xFFFF  # GigE Vision 1 block ids are 16-bit and skip 0 when they wrap


class CaptureThread(threading.Thread):
    def __init__(
        self,
        source: str,
        settings: CameraSettings,
        slot: LatestFrameSlot,
        stop: threading.Event,
        *,
        frame_timeout_s: float = 1.0,
        timeout_streak: int = 3,
        backoff_initial_s: float = 0.5,
        backoff_max_s: float = 10.0,
        camera_factory: Callable[[str, CameraSettings], Camera] = make_camera,
    ) -> None:
        super().__init__(name="capture", daemon=True)
        self.source = source
        self._settings = settings
        self._slot = slot
        self._stop_event = stop
        self._frame_timeout_s = frame_timeout_s
        self._timeout_streak = timeout_streak
        self._backoff_initial_s = backoff_initial_s
        self._backoff_max_s = backoff_max_s
        self._camera_factory = camera_factory
        self._lock = threading.Lock()
        self._status = CameraStatus(source=source, state="connecting")
        self._camera: Camera | None = None
        self._dropped_before = 0  # driver-dropped frames of cameras already closed
        self._next_seq = 0
        self._expected_size = (settings.width, settings.height)
        self._last_stamp_ns: int | None = None  # the last frame passed on (across reconnects)
        self._stamp_back_streak = 0
        self._last_frame_id: int | None = None  # within one stream
        self._restart_next = False
        self._faults: collections.Counter = collections.Counter()
        self._fault_logged_at: dict[str, float] = {}
        self._camera_counts_before: collections.Counter = collections.Counter()  # closed cameras
        self.last_fault: tuple[float, str] | None = None  # (monotonic time, what) of the last dropped frame
        self.last_accepted: float | None = None  # monotonic time of the last frame passed on
        self.heartbeat = time.monotonic()  # last time the loop was seen alive
        self.ended = threading.Event()
        self.streaming = threading.Event()
        self.failure: BaseException | None = None

    # -- state shared with the status thread ---------------------------------------------
    def status(self) -> CameraStatus:
        with self._lock:
            status = self._status
            camera = self._camera
            dropped = self._dropped_before
        dropped += camera.stats.dropped if camera is not None else 0
        return CameraStatus(**{**status.__dict__, "dropped": dropped})

    def faults(self) -> dict[str, int]:
        """Counts of what went wrong at the camera boundary, for ``status``: frames dropped
        here (bad_format, wrong_size, stamp_not_increasing), frame-id jumps, frame
        timeouts, clock restarts, and the camera backends' own counters (summed over
        reconnects)."""
        with self._lock:
            counts = collections.Counter(self._faults)
            counts.update(self._camera_counts_before)
            camera = self._camera
        if camera is not None:
            counts.update(_camera_counts(camera))
        return {k: v for k, v in sorted(counts.items()) if v}

    def _count_fault(self, kind: str, message: str, **fields: object) -> None:
        with self._lock:
            self._faults[kind] += 1
            count = self._faults[kind]
        now = time.monotonic()
        if kind in DROPPED_KINDS:
            self.last_fault = (now, f"{message} ({', '.join(f'{k} {v}' for k, v in fields.items())})")
        if now - self._fault_logged_at.get(kind, -FAULT_LOG_PERIOD_S) >= FAULT_LOG_PERIOD_S:
            self._fault_logged_at[kind] = now
            log.warning(message, source=self.source, fault=kind, count=count, **fields)

    def _set_state(self, state: str, detail: str = "", **fields: object) -> None:
        with self._lock:
            self._status = CameraStatus(**{**self._status.__dict__, "state": state, "detail": detail, **fields})
        if state in ("streaming", "no_frames"):  # no_frames: open and started, but silent
            self.streaming.set()
        else:
            self.streaming.clear()

    # -- the loop -----------------------------------------------------------------------
    def run(self) -> None:
        try:
            self._run()
        except BaseException as exc:  # a bug (or a non-camera user error): stop the daemon
            self.failure = exc
            self._set_state("failed", f"{type(exc).__name__}: {exc}")
            self._stop_event.set()
        finally:
            self._close_camera()
            self._slot.close()

    def _run(self) -> None:
        backoff_s = self._backoff_initial_s
        attempt = 0
        while not self._stop_event.is_set():
            attempt += 1
            try:
                camera = self._open()
            except CameraError as exc:
                # "waiting": never had a camera (none at boot); "reconnecting": lost one.
                state = "reconnecting" if self.status().reconnects else "waiting"
                log.warning("camera unavailable", source=self.source, error=str(exc), retry_in_s=round(backoff_s, 2), attempt=attempt)
                self._set_state(state, str(exc))
                self._sleep(backoff_s)
                backoff_s = min(backoff_s * 2, self._backoff_max_s)
                continue
            info = camera.info
            self._set_state("streaming", "", model=f"{info.vendor} {info.model}".strip(), serial=info.serial)
            log.info("camera streaming", source=self.source, model=info.model, serial=info.serial, attempt=attempt)
            try:
                reason = self._stream(camera)
            finally:
                self._close_camera()
            if reason == "ended":
                log.info("camera source ended", source=self.source)
                self._set_state("ended", "the source has no more frames")
                self.ended.set()
                return
            if reason == "stopped":
                self._set_state("stopped")
                return
            # The stream failed: reconnect, starting the back-off afresh if it had worked.
            with self._lock:
                self._status = CameraStatus(**{**self._status.__dict__, "reconnects": self._status.reconnects + 1})
            log.warning("camera lost, reconnecting", source=self.source, reason=reason, retry_in_s=round(self._backoff_initial_s, 2))
            self._set_state("reconnecting", reason)
            backoff_s = self._backoff_initial_s
            attempt = 0
            self._sleep(backoff_s)
            backoff_s = min(backoff_s * 2, self._backoff_max_s)
        self._set_state("stopped")

    def _open(self) -> Camera:
        self.heartbeat = time.monotonic()
        camera = self._camera_factory(self.source, self._settings)
        try:
            camera.open()
            camera.start()
        except BaseException:
            with contextlib.suppress(CubelocError):
                camera.close()
            raise
        with self._lock:
            self._camera = camera
        return camera

    def _stream(self, camera: Camera) -> str:
        """Deliver frames until the stream fails (returns why), ends or the daemon stops."""
        timeouts_in_row = 0
        waiting_since = time.monotonic()
        while not self._stop_event.is_set():
            self.heartbeat = time.monotonic()
            try:
                frame = camera.next_frame(min(POLL_S, self._frame_timeout_s))
            except FrameTimeout:
                if time.monotonic() - waiting_since < self._frame_timeout_s:
                    continue
                timeouts_in_row += 1
                with self._lock:
                    self._faults["frame_timeout"] += 1
                waiting_since = time.monotonic()
                # status says so from the first timeout (the rate drops to 0 with it)
                self._set_state("no_frames", f"no frame for {self._frame_timeout_s * timeouts_in_row:g} s")
                log.warning("no frame within the timeout", source=self.source, timeout_s=self._frame_timeout_s, in_a_row=timeouts_in_row)
                if timeouts_in_row >= self._timeout_streak:
                    return f"{timeouts_in_row} frame timeouts in a row"
                continue
            except EndOfStream:
                return "ended"
            except CameraError as exc:  # StreamBroken, CameraNotFound: the camera is gone
                return f"{type(exc).__name__}: {exc}"
            if timeouts_in_row:
                self._set_state("streaming", "")
            timeouts_in_row = 0
            waiting_since = time.monotonic()
            if not self._accept(frame):
                continue
            seq = self._next_seq
            self._next_seq += 1
            restart, self._restart_next = self._restart_next, False
            self.last_accepted = time.monotonic()
            self._slot.put(CapturedFrame(frame, seq, time.monotonic_ns(), restart=restart))
        return "stopped"

    def _accept(self, frame: Frame) -> bool:
        """Check one frame from the driver; False: dropped (counted and logged)."""
        # Every frame received counts for the ids, good or bad (a bad frame is not a lost one).
        last_id, self._last_frame_id = self._last_frame_id, frame.frame_id
        wrapped = last_id == GEV1_MAX_BLOCK_ID and frame.frame_id == 1
        if last_id is not None and frame.frame_id != last_id + 1 and not wrapped:
            self._count_fault("frame_id_jump", "frame id jumped", previous=last_id, frame_id=frame.frame_id)
        image = frame.image
        if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8:
            shape = getattr(image, "shape", None)
            self._count_fault("bad_format", "frame dropped: not Mono8", shape=str(shape),
                              dtype=str(getattr(image, "dtype", type(image).__name__)), frame_id=frame.frame_id)
            return False
        height, width = image.shape
        if (width, height) != self._expected_size:
            self._count_fault("wrong_size", "frame dropped: size differs from the camera settings",
                              size=f"{width}x{height}", expected=f"{self._expected_size[0]}x{self._expected_size[1]}",
                              frame_id=frame.frame_id)
            return False
        last = self._last_stamp_ns
        if last is not None and frame.stamp_ns <= last:
            self._stamp_back_streak += 1
            if self._stamp_back_streak < STAMP_RESTART_FRAMES:
                self._count_fault("stamp_not_increasing", "frame dropped: timestamp not after the previous frame's",
                                  stamp_ns=frame.stamp_ns, previous_ns=last, frame_id=frame.frame_id)
                return False
            # Behind for several frames in a row: the clock stepped back; start a new timeline.
            self._count_fault("clock_restart", "timestamps went back for several frames: new timeline, processor reset",
                              stamp_ns=frame.stamp_ns, previous_ns=last)
            self._restart_next = True
        self._stamp_back_streak = 0
        self._last_stamp_ns = frame.stamp_ns
        return True

    def _close_camera(self) -> None:
        with self._lock:
            camera, self._camera = self._camera, None
            if camera is not None:  # its counters move to the totals in the same step
                self._dropped_before += camera.stats.dropped
                self._camera_counts_before.update(_camera_counts(camera))
        if camera is None:
            return
        self._last_frame_id = None  # a new stream numbers its frames afresh
        with contextlib.suppress(CubelocError):
            camera.stop()
        with contextlib.suppress(CubelocError):
            camera.close()

    def _sleep(self, seconds: float) -> None:
        """Wait on a monotonic deadline, keeping the heartbeat fresh; return early on stop."""
        deadline = time.monotonic() + seconds
        while not self._stop_event.is_set():
            self.heartbeat = time.monotonic()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            self._stop_event.wait(min(remaining, POLL_S))


def _camera_counts(camera: Camera) -> dict[str, int]:
    """The backend's counters for ``status.extra.faults``: camera_incomplete (and by cause,
    camera_incomplete_missing_packets ...), camera_bad_timestamp, camera_frame_id_gaps."""
    counts = {f"camera_{k}": getattr(camera.stats, k) for k in CAMERA_COUNTERS}
    counts.update({f"camera_incomplete_{cause}": n for cause, n in camera.stats.incomplete_causes.items()})
    return counts
