"""The replay backend: a recorded sequence (EuRoC camera layout) as a camera.

``replay:DIR`` delivers the frames as fast as they can be decoded; ``replay:DIR@pace``
at the pace they were recorded (frame k waits until ``(t_k - t_0)`` after ``start()``).
A frame's ``stamp_ns`` and ``device_timestamp_ns`` are the recorded timestamp, its
``frame_id`` the row number (from 0), its exposure 0.0 (not recorded in the layout).
Rows whose timestamp does not increase, and images that cannot be read (missing,
truncated), are dropped and counted (``bad_timestamp``, ``incomplete``) with a warning
naming the file, like a live camera's bad frames. After the last frame ``next_frame``
raises EndOfStream. A missing or malformed sequence (its directory, its index) raises
InputFileError naming the file, when the source is made.
"""

from __future__ import annotations

import time
from pathlib import Path

import structlog

from cubeloc.drivers.base import (
    CameraBase,
    CameraSettings,
    CaptureStats,
    DeviceInfo,
    EndOfStream,
    Frame,
    FrameTimeout,
    StreamBroken,
)
from cubeloc.drivers.sequence import SequenceEntry, read_image, read_sequence_index
from cubeloc.errors import InputFileError

log = structlog.get_logger()

PACE_SUFFIX = "@pace"


def parse_replay_argument(argument: str) -> tuple[Path, bool]:
    """``DIR`` or ``DIR@pace`` -> (directory, paced)."""
    paced = argument.endswith(PACE_SUFFIX)
    directory = argument[: -len(PACE_SUFFIX)] if paced else argument
    return Path(directory), paced


class ReplayCamera(CameraBase):
    """A recorded sequence played back through the camera protocol."""

    def __init__(self, directory: Path, settings: CameraSettings, *, paced: bool = False) -> None:
        self.directory = directory
        self.paced = paced
        self._settings = settings
        self._stats = CaptureStats()
        self._info = DeviceInfo(device_id=f"replay:{directory}{PACE_SUFFIX if paced else ''}",
                                vendor="", model="recorded sequence", serial="",
                                transport="replay", address=str(directory))
        self._entries: list[SequenceEntry] | None = None
        self._position = 0
        self._last_stamp_ns: int | None = None
        self._started_at: float | None = None
        self._pace_origin_ns = 0  # recorded time of the first frame after start()

    @property
    def frame_count(self) -> int:
        return len(self._entries or ())

    def open(self) -> None:
        if self._entries is None:
            self._entries = read_sequence_index(self.directory)  # InputFileError if bad
            self._position = 0
            self._last_stamp_ns = None

    def start(self) -> None:
        if self._entries is None:
            raise StreamBroken(f"replay {self.directory} is not open; call open() first")
        self._started_at = time.monotonic()
        if self._position < len(self._entries):
            self._pace_origin_ns = self._entries[self._position].stamp_ns

    def next_frame(self, timeout_s: float) -> Frame:
        if self._entries is None or self._started_at is None:
            raise StreamBroken(f"replay {self.directory} is not started; open() and start() it")
        while self._position < len(self._entries):
            entry = self._entries[self._position]
            if self._last_stamp_ns is not None and entry.stamp_ns <= self._last_stamp_ns:
                self._position += 1
                self._stats.bad_timestamp += 1
                continue
            if self.paced:
                due = self._started_at + (entry.stamp_ns - self._pace_origin_ns) / 1e9
                wait = due - time.monotonic()
                if wait > timeout_s:
                    time.sleep(max(timeout_s, 0.0))
                    self._stats.timeouts += 1
                    raise FrameTimeout(f"replay {self.directory}: next frame due in {wait:.2f} s")
                if wait > 0:
                    time.sleep(wait)
            try:
                image = read_image(entry.path)
            except InputFileError as exc:  # as a camera's bad buffer: dropped and counted
                self._position += 1
                self._stats.incomplete += 1
                log.warning("replay frame dropped", error=str(exc), dropped=self._stats.incomplete)
                continue
            frame = Frame(image=image, frame_id=self._position, device_timestamp_ns=entry.stamp_ns,
                          stamp_ns=entry.stamp_ns, exposure_us=0.0)
            self._position += 1
            self._last_stamp_ns = entry.stamp_ns
            self._stats.delivered += 1
            return frame
        raise EndOfStream(f"replay {self.directory}: end of the sequence ({len(self._entries)} frames)")

    def stop(self) -> None:
        self._started_at = None

    def close(self) -> None:
        self._entries = None
        self._started_at = None


def open_replay_source(argument: str, settings: CameraSettings) -> ReplayCamera:
    """Factory for ``replay:DIR[@pace]`` (see ``drivers.registry``), opened: its index is
    read here, so a missing directory or one that is not a sequence fails where the source
    is made (``cubeloc run --check`` as well as ``run``), as InputFileError naming it."""
    if not argument:
        raise InputFileError("replay source needs a directory: 'replay:DIR' or 'replay:DIR@pace'")
    directory, paced = parse_replay_argument(argument)
    camera = ReplayCamera(directory, settings, paced=paced)
    camera.open()
    return camera
