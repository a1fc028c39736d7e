"""The camera protocol: what every backend (Aravis, replay, synthetic) provides.

A camera is opened, started, asked for frames with a timeout, stopped and closed.
Discovery (listing devices) is kept apart from streaming: see ``drivers.discovery``.

Frames a backend cannot trust (bad buffer status, zero or non-monotonic timestamp) are
dropped and counted in ``CaptureStats``; they never reach the caller.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from cubeloc.errors import CubelocError

UsbMode = Literal["async", "sync", "default"]
PixelFormat = Literal["Mono8", "Mono10", "Mono12", "Mono16"]
PIXEL_BITS: dict[str, int] = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono16": 16}
TriggerMode = Literal["free", "software", "line0"]


class CameraError(CubelocError):
    """A camera problem a user can act on."""


class CameraNotFound(CameraError):
    """No camera matches the requested id, serial or path."""


class CameraBusy(CameraError):
    """Another process owns the camera (the message names it when known)."""


class FeatureNotSupported(CameraError):
    """A requested setting is not offered by this camera (the message names the feature)."""


class FrameTimeout(CameraError):
    """No frame arrived within the timeout. The stream may still recover by itself."""


class StreamBroken(CameraError):
    """The stream cannot continue (camera gone, cable pulled): close and reopen."""


class EndOfStream(CameraError):
    """A finite source (a recorded sequence, a synthetic trajectory) has no more frames."""


@dataclass(frozen=True)
class Frame:
    """One Mono8 image and its timing.

    ``stamp_ns`` is the capture time on the host's CLOCK_REALTIME in integer nanoseconds:
    the device timestamp mapped to the host clock (see ``drivers.clock``), or for sources
    without a device clock the recorded or simulated time. It is what goes on the wire.
    """

    image: np.ndarray  # (H, W) uint8, C-contiguous
    frame_id: int  # the camera's own frame counter (gaps mean lost frames)
    device_timestamp_ns: int  # the camera's clock, arbitrary epoch
    stamp_ns: int  # host CLOCK_REALTIME at exposure, ns
    exposure_us: float  # exposure time actually used, microseconds


@dataclass(frozen=True)
class CameraSettings:
    """What a user may set. ``None`` leaves the camera's own value (or turns auto on)."""

    width: int = 1280
    height: int = 1024
    offset_x: int = 0
    offset_y: int = 0
    exposure_us: float | None = None  # None: auto exposure where the camera has it
    gain_db: float | None = None  # None: auto gain where the camera has it
    frame_rate_hz: float | None = None  # None: as fast as the camera runs
    trigger: TriggerMode = "free"
    # The stream (Aravis; other backends ignore them). Buffers in flight: 8 x 1.3 MB at
    # 1280x1024 Mono8 fits Linux' default usbfs budget of 16 MB (cubeloc doctor checks it).
    stream_buffers: int = 8
    # USB3 Vision transfers: "async" keeps several in flight (Aravis' choice for sustained
    # rates), "sync" one at a time, "default" leaves Aravis' own default
    usb_mode: UsbMode = "async"
    usb_bandwidth_mbps: float | None = None  # DeviceLinkThroughputLimit; None: the camera's
    # What the camera streams: 8-bit mono, or 10/12/16 bits in two bytes a pixel (unpacked),
    # brought to Mono8 by dropping the low bits (``PIXEL_BITS``). Aravis only.
    pixel_format: PixelFormat = "Mono8"


@dataclass(frozen=True)
class DeviceInfo:
    """One camera as discovery sees it."""

    device_id: str  # what ``--camera`` / ``camera.source`` accepts
    vendor: str
    model: str
    serial: str
    transport: str  # "gige", "usb3", "usb", "fake", "replay", "synthetic"
    address: str = ""  # IP address or USB bus:port, where known
    notes: tuple[str, ...] = ()  # problems and fixes (permissions, USB2 link, ...)


@dataclass
class CaptureStats:
    """Counters a backend keeps while streaming; reported on ``status``."""

    delivered: int = 0
    incomplete: int = 0  # buffers with a bad status, dropped
    # ...by cause ("missing_packets", "size_mismatch", "timeout", "short_data", ...): a
    # cable (missing packets) told apart from a setting (size mismatch)
    incomplete_causes: dict[str, int] = field(default_factory=dict)
    bad_timestamp: int = 0  # zero or non-monotonic timestamps, dropped
    frame_id_gaps: int = 0  # frames the camera numbered but we never got
    timeouts: int = 0
    reconnects: int = 0
    extra: dict[str, int] = field(default_factory=dict)

    @property
    def dropped(self) -> int:
        return self.incomplete + self.bad_timestamp + self.frame_id_gaps


@runtime_checkable
class Camera(Protocol):
    """The protocol every backend implements. Use as a context manager for open/close."""

    @property
    def info(self) -> DeviceInfo: ...

    @property
    def settings(self) -> CameraSettings: ...

    @property
    def stats(self) -> CaptureStats: ...

    def open(self) -> None:
        """Connect and apply the settings. Raises CameraNotFound, CameraBusy, FeatureNotSupported."""

    def start(self) -> None:
        """Start acquisition."""

    def next_frame(self, timeout_s: float) -> Frame:
        """The next good frame. Raises FrameTimeout, StreamBroken or EndOfStream."""

    def stop(self) -> None:
        """Stop acquisition; the camera stays open."""

    def close(self) -> None:
        """Release the camera. Safe to call twice."""

    def __enter__(self) -> Camera: ...

    def __exit__(self, *exc: object) -> None: ...


class CameraBase:
    """Shared behaviour for backends: the context manager, and the protocol's read-only
    ``info``, ``settings`` and ``stats`` served from ``_info``, ``_settings`` and ``_stats``
    (a backend that computes one overrides the property)."""

    _info: DeviceInfo
    _settings: CameraSettings
    _stats: CaptureStats

    @property
    def info(self) -> DeviceInfo:
        return self._info

    @property
    def settings(self) -> CameraSettings:
        return self._settings

    @property
    def stats(self) -> CaptureStats:
        return self._stats

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
