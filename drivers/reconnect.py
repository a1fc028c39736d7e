"""Reconnecting a camera after StreamBroken, with back-off on monotonic deadlines.

The contract (every backend): after ``next_frame`` raised StreamBroken, ``close()`` and
then ``open()`` + ``start()`` bring the same camera object back with its requested
settings re-applied and its counters kept. ``reopen_with_backoff`` does that until it
works: camera unplugged -> wait -> reconnect, without restarting the process.
"""

from __future__ import annotations

import threading
import time

import structlog

from cubeloc.drivers.base import Camera, CameraBusy, CameraError, FeatureNotSupported, StreamBroken

log = structlog.get_logger()


def reopen_with_backoff(
    camera: Camera,
    *,
    stop: threading.Event | None = None,
    give_up_after_s: float | None = None,
    first_delay_s: float = 0.5,
    max_delay_s: float = 8.0,
) -> bool:
    """Close ``camera``, then retry open + start, doubling the wait up to ``max_delay_s``.

    Returns True once streaming again, False if ``stop`` was set first. Raises
    StreamBroken after ``give_up_after_s`` (None: never give up), and at once the errors a
    retry cannot fix: CameraBusy (another process took the camera) and
    FeatureNotSupported (the camera that came back is a different one).
    """
    stop = stop or threading.Event()
    camera.close()
    started = time.monotonic()
    deadline = None if give_up_after_s is None else started + give_up_after_s
    delay = first_delay_s
    attempt = 0
    while not stop.is_set():
        attempt += 1
        try:
            camera.open()
            camera.start()
        except (CameraBusy, FeatureNotSupported):
            camera.close()
            raise
        except CameraError as exc:
            camera.close()
            now = time.monotonic()
            if deadline is not None and now + delay > deadline:
                raise StreamBroken(f"camera {camera.info.device_id} did not come back within "
                                   f"{give_up_after_s:g} s ({exc})") from None
            log.warning("camera not back yet", camera=camera.info.device_id, attempt=attempt,
                        error=str(exc), retry_in_s=delay)
            stop.wait(delay)
            delay = min(delay * 2, max_delay_s)
            continue
        camera.stats.reconnects += 1
        log.info("camera reconnected", camera=camera.info.device_id, attempt=attempt,
                 after_s=round(time.monotonic() - started, 2))
        return True
    return False
