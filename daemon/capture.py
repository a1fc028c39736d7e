"""The capture thread: keeps a camera streaming into the newest-frame slot, whatever happens.

No camera at boot, a pulled cable, a stream that stops: none of it ends the process. The
thread closes what is left of the camera, waits (exponential back-off on monotonic
deadlines, cut short by shutdown), opens a fresh camera with the same settings and carries
on; its state shows on ``status`` and in the logs. A finite source (replay, synthetic)
that ends sets ``ended``. Anything that is not a camera error is a bug: it is kept in
``failure`` and stops the daemon.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable

import structlog

from cubeloc.errors import CubelocError
from daemon.frame_queue import CapturedFrame, LatestFrameSlot
from daemon.messages import CameraStatus
from drivers.base import (
    Camera,
    CameraError,
    CameraSettings,
    EndOfStream,
    FrameTimeout,
)
from drivers.registry import make_camera

log = structlog.get_logger()

# next_frame is called with at most this timeout so that a shutdown is seen quickly even
# when the configured frame timeout is long.
POLL_S = 0.25


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
        self.heartbeat = time.monotonic()  # last time the loop was seen alive
        self.ended = threading.Event()
        self.streaming = threading.Event()
        self.failure: BaseException | None = None

    # -- state shared with the status thread ---------------------------------------------
    def status(self) -> CameraStatus:
        with self._lock:
            status = self._status
            camera = self._camera
        dropped = self._dropped_before + (camera.stats.dropped if camera is not None else 0)
        return CameraStatus(**{**status.__dict__, "dropped": dropped})

    def _set_state(self, state: str, detail: str = "", **fields: object) -> None:
        with self._lock:
            self._status = CameraStatus(**{**self._status.__dict__, "state": state, "detail": detail, **fields})
        if state == "streaming":
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
                waiting_since = time.monotonic()
                log.warning("no frame within the timeout", source=self.source, timeout_s=self._frame_timeout_s, in_a_row=timeouts_in_row)
                if timeouts_in_row >= self._timeout_streak:
                    return f"{timeouts_in_row} frame timeouts in a row"
                continue
            except EndOfStream:
                return "ended"
            except CameraError as exc:  # StreamBroken, CameraNotFound: the camera is gone
                return f"{type(exc).__name__}: {exc}"
            timeouts_in_row = 0
            waiting_since = time.monotonic()
            seq = self._next_seq
            self._next_seq += 1
            self._slot.put(CapturedFrame(frame, seq, time.monotonic_ns()))
        return "stopped"

    def _close_camera(self) -> None:
        with self._lock:
            camera, self._camera = self._camera, None
        if camera is None:
            return
        self._dropped_before += camera.stats.dropped
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
