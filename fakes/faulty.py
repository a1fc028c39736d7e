"""Cameras for fault and soak tests: pre-rendered frames at a real frame rate, and faults on cue.

``CyclingCamera`` plays a short list of pre-rendered frames forwards then backwards (a
continuous back-and-forth motion, so a tracker never sees a jump) at ``fps`` on the host
clock, for as long as wanted: rendering (about a second a frame) is done once, not per
frame, so a 30-minute soak runs at the camera's full rate. Like a real camera it numbers
its frames, stamps them on the host clock, and loses the frames a slow consumer did not
take (counted as frame-id gaps). ``ground_truth(stamp_ns)`` is the true pose of a frame.

``FaultyCamera`` wraps any camera and, at given frame numbers, does what real cameras
and drivers do wrong: time out, break the stream (a pulled USB or GigE cable: the next
opens fail with ``CameraNotFound`` for a while), deliver an incomplete image, jump the
frame id, step the timestamp back, change the image size or pixel format. ``FaultyCamera``
is also the camera factory the daemon takes (``camera_factory=faulty``): every reconnect
gets the same object back, reopened, so the schedule runs on across reconnects.
"""

from __future__ import annotations

import dataclasses
import functools
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cubeloc.drivers.base import (
    Camera,
    CameraBase,
    CameraNotFound,
    CameraSettings,
    CaptureStats,
    DeviceInfo,
    Frame,
    FrameTimeout,
    StreamBroken,
)
from cubeloc.positioning.geometry import Transform

FAULT_KINDS = (
    "timeout",  # no frame for `seconds`: every call in that time waits its timeout, FrameTimeout
    "unplug",  # StreamBroken now, then opens fail (CameraNotFound) for `seconds`
    "incomplete",  # the frame with rows from `fraction` of the height down zeroed
    "frame_id_jump",  # the camera's frame counter jumps forward by `count` (and stays there)
    "stamp_back",  # this frame's timestamps `seconds` before the previous frame's
    "wrong_size",  # `count` frames cropped to half their width and height
    "wrong_format",  # `count` frames as 16-bit (`format="mono16"`) or 3-channel (`"rgb8"`)
    "clock_step",  # from now on every timestamp `seconds` earlier (a host clock stepped back)
)


@dataclass(frozen=True)
class Fault:
    kind: str
    count: int = 1
    seconds: float = 0.5
    fraction: float = 0.5
    format: str = "mono16"

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault {self.kind!r}; known: {', '.join(FAULT_KINDS)}")


class CyclingCamera(CameraBase):
    """``images`` (with their true poses ``poses``) played back and forth at ``fps``."""

    def __init__(
        self,
        images: Sequence[np.ndarray],
        poses: Sequence[Transform] | None = None,
        *,
        fps: float = 10.0,
        name: str = "cycling",
    ) -> None:
        if not images:
            raise ValueError("CyclingCamera needs at least one image")
        self.images = list(images)
        self.poses = list(poses) if poses is not None else None
        self.period_ns = int(round(1e9 / fps))
        height, width = self.images[0].shape[:2]
        self._settings = CameraSettings(width=width, height=height, frame_rate_hz=fps)
        self._stats = CaptureStats()
        self._info = DeviceInfo(f"cycling:{name}", "cubeloc", "cycling camera", name, "synthetic")
        self._streaming = False
        self._start_monotonic_ns = 0
        self._origin_ns = 0
        self._next = 0
        self._lock = threading.Lock()
        # host time of frame 0 of every start (one per reconnect): ground truth from the
        # stamp alone, with nothing kept per frame (a soak must not grow by its own hand)
        self._origins: list[int] = []

    def open(self) -> None:
        pass

    def start(self) -> None:
        self._start_monotonic_ns = time.monotonic_ns()
        self._origin_ns = time.time_ns()
        with self._lock:
            self._origins.append(self._origin_ns)
        self._next = 0
        self._streaming = True

    def image_index(self, k: int) -> int:
        """The image shown as frame ``k``: 0, 1, ..., n-1, n-2, ..., 1, 0, 1, ..."""
        n = len(self.images)
        if n == 1:
            return 0
        phase = k % (2 * n - 2)
        return phase if phase < n else 2 * n - 2 - phase

    def next_frame(self, timeout_s: float) -> Frame:
        if not self._streaming:
            raise StreamBroken(f"{self._info.device_id}: not streaming")
        now = time.monotonic_ns()
        due = (now - self._start_monotonic_ns) // self.period_ns  # the newest frame exposed
        k = max(self._next, due)
        wait_s = (self._start_monotonic_ns + k * self.period_ns - now) / 1e9
        if wait_s > timeout_s:
            time.sleep(max(0.0, timeout_s))
            self._stats.timeouts += 1
            raise FrameTimeout(f"{self._info.device_id}: no frame within {timeout_s:g} s")
        if wait_s > 0:
            time.sleep(wait_s)
        self._stats.frame_id_gaps += k - self._next  # frames the consumer was too slow for
        self._next = k + 1
        self._stats.delivered += 1
        index = self.image_index(k)
        stamp_ns = self._origin_ns + k * self.period_ns
        return Frame(self.images[index], k, k * self.period_ns, stamp_ns, 5000.0)

    def ground_truth(self, stamp_ns: int) -> Transform | None:
        """The true ``T_world_camera`` of the frame delivered with ``stamp_ns``."""
        if self.poses is None:
            return None
        with self._lock:
            origins = list(self._origins)
        for origin in reversed(origins):  # the latest start at or before the stamp
            k, remainder = divmod(stamp_ns - origin, self.period_ns)
            if k >= 0:
                return self.poses[self.image_index(k)] if remainder == 0 else None
        return None

    def stop(self) -> None:
        self._streaming = False

    def close(self) -> None:
        self._streaming = False


class FaultyCamera(CameraBase):
    """``inner`` with ``faults`` injected: {frame number: Fault}, frames counted from 1 over
    the whole run (reconnects included). Also the daemon's camera factory."""

    def __init__(self, inner: Camera, faults: dict[int, Fault] | None = None) -> None:
        self.inner = inner
        self.faults = dict(faults or {})
        self.log: list[tuple] = []  # ("fault", kind, frame number) / ("open",): events, not frames
        self.frames = 0  # frames pulled from the inner camera
        self._silent_until = 0.0
        self._unplugged_until = 0.0
        self._id_offset = 0
        self._stamp_shift_ns = 0  # clock steps so far
        self._repeat: tuple[Fault, int] | None = None  # a fault on the next frames too
        self.bad_stamps: set[int] = set()  # stamps of frames given a wrong timestamp
        self.shifts_ns: list[int] = [0]  # the total clock shift of each timeline (inner stamp - delivered)
        self._last_device_ns = 0
        self._last_stamp_ns = 0
        self.opens = 0
        self.failed_opens = 0

    # the daemon's camera_factory signature
    def __call__(self, source: str, settings: CameraSettings) -> FaultyCamera:
        return self

    @property
    def info(self) -> DeviceInfo:
        return self.inner.info

    @property
    def settings(self) -> CameraSettings:
        return self.inner.settings

    @property
    def stats(self) -> CaptureStats:
        return self.inner.stats

    def open(self) -> None:
        if time.monotonic() < self._unplugged_until:
            self.failed_opens += 1
            raise CameraNotFound(f"{self.inner.info.device_id}: no such device (unplugged, injected)")
        self.opens += 1
        self.log.append(("open",))
        self.inner.open()

    def start(self) -> None:
        self.inner.start()

    def stop(self) -> None:
        self.inner.stop()

    def close(self) -> None:
        self.inner.close()

    def next_frame(self, timeout_s: float) -> Frame:
        if time.monotonic() < self._silent_until:
            time.sleep(max(0.0, min(timeout_s, self._silent_until - time.monotonic())))
            raise FrameTimeout(f"{self.inner.info.device_id}: no frame within {timeout_s:g} s (injected)")
        frame = self.inner.next_frame(timeout_s)
        self.frames += 1
        fault = self.faults.pop(self.frames, None)
        if fault is not None:
            self.log.append(("fault", fault.kind, self.frames))
            if fault.kind in ("wrong_size", "wrong_format") and fault.count > 1:
                self._repeat = (fault, fault.count - 1)
        elif self._repeat is not None:
            fault, left = self._repeat
            self._repeat = (fault, left - 1) if left > 1 else None
        if fault is not None:
            frame = self._inject(fault, frame, timeout_s)
        frame = dataclasses.replace(frame, frame_id=frame.frame_id + self._id_offset,
                                    device_timestamp_ns=frame.device_timestamp_ns - self._stamp_shift_ns,
                                    stamp_ns=frame.stamp_ns - self._stamp_shift_ns)
        self._last_device_ns = frame.device_timestamp_ns
        self._last_stamp_ns = frame.stamp_ns
        return frame

    def _inject(self, fault: Fault, frame: Frame, timeout_s: float) -> Frame:
        kind = fault.kind
        if kind == "timeout":
            self._silent_until = time.monotonic() + fault.seconds
            time.sleep(min(timeout_s, fault.seconds))
            raise FrameTimeout(f"{self.inner.info.device_id}: no frame within {timeout_s:g} s (injected)")
        if kind == "unplug":
            self._unplugged_until = time.monotonic() + fault.seconds
            raise StreamBroken(f"{self.inner.info.device_id}: device disconnected (injected unplug)")
        if kind == "incomplete":
            image = frame.image.copy()
            image[int(image.shape[0] * fault.fraction):, :] = 0
            return dataclasses.replace(frame, image=image)
        if kind == "frame_id_jump":
            self._id_offset += fault.count
            return frame
        if kind == "stamp_back":  # (the clock-step shift is subtracted again by the caller)
            back_ns = int(fault.seconds * 1e9) - self._stamp_shift_ns
            self.bad_stamps.add(self._last_stamp_ns - back_ns - self._stamp_shift_ns)
            return dataclasses.replace(frame, device_timestamp_ns=self._last_device_ns - back_ns,
                                       stamp_ns=self._last_stamp_ns - back_ns)
        if kind == "clock_step":
            self._stamp_shift_ns += int(fault.seconds * 1e9)
            self.shifts_ns.append(self._stamp_shift_ns)
            return frame
        if kind == "wrong_size":
            h, w = frame.image.shape[:2]
            return dataclasses.replace(frame, image=np.ascontiguousarray(frame.image[: h // 2, : w // 2]))
        # wrong_format
        if fault.format == "rgb8":
            image = np.repeat(frame.image[:, :, None], 3, axis=2)
        else:
            image = frame.image.astype(np.uint16) * 257
        return dataclasses.replace(frame, image=image)


def render_orbit_frames(count: int, *, arc_deg: float = 6.0, radius_m: float = 1.6, height_m: float = 0.9,
                        seed: int = 0, room: bool = True) -> tuple[list[np.ndarray], list[Transform]]:
    """``count`` frames of the default cube along a short arc (the camera looking at the
    cube's centre): the images and their true ``T_world_camera``."""
    from cubeloc.fakes.render import render_view
    from cubeloc.positioning.geometry import look_at

    start = np.deg2rad(-40.0)
    images, poses = [], []
    for k in range(count):
        azimuth = start + np.deg2rad(arc_deg) * (k / max(1, count - 1))
        position = np.array([radius_m * np.cos(azimuth), radius_m * np.sin(azimuth), height_m])
        pose = look_at(position, np.zeros(3))
        images.append(render_view(pose, room=room, seed=seed * 1000 + k))
        poses.append(pose)
    return images, poses


@functools.lru_cache(maxsize=4)
def orbit_frames(count: int, seed: int = 0, room: bool = True) -> tuple[tuple[np.ndarray, ...], tuple[Transform, ...]]:
    """``render_orbit_frames(count)``, rendered once per process (tests share them).
    ``room=False`` (a plain background) skips building the room, which takes seconds."""
    images, poses = render_orbit_frames(count, seed=seed, room=room)
    for image in images:
        image.setflags(write=False)  # shared: nobody may draw on them
    return tuple(images), tuple(poses)
