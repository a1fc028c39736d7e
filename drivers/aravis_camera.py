"""The Aravis backend: GigE Vision and USB3 Vision cameras through PyGObject.

Source strings (see ``drivers.registry``): ``aravis`` opens the first camera Aravis finds;
``aravis:X`` opens the camera whose Aravis device id, serial number, IP address or USB
physical id is X. ``aravis:Fake_1`` turns on Aravis' built-in fake interface first.

What it does and why:

* **Ownership.** The camera's lock file (``drivers.ownership``) is taken before the camera
  is touched, so a second process gets CameraBusy naming the holder.
* **Features are probed, not assumed** (``drivers.genicam``): a setting the camera lacks
  raises FeatureNotSupported naming the feature. ``None`` settings turn auto on where
  the camera has it and otherwise leave the camera's value.
* **Buffers.** A pool of Aravis-allocated buffers (PyGObject cannot hand Aravis memory it
  owns); each good frame is copied once, into the bytes object ``get_image_data``
  returns, which the frame's numpy array views (so the array is read-only).
* **Accounting** (``drivers.frame_accounting``): bad buffer status, zero or non-monotonic
  timestamps are dropped and counted; frame-id gaps are counted.
* **Time** (``drivers.clock``): ``stamp_ns`` is the device timestamp mapped onto the host
  CLOCK_REALTIME by a running minimum of (arrival - device time).
* **GigE packet size** is negotiated with ``gv_auto_packet_size`` (largest size the path
  passes), falling back to 1400 bytes, which any 1500-byte-MTU network passes.
* **Loss of the camera.** Aravis emits ``control-lost`` when GVCP heartbeats fail; a
  watchdog also declares the stream broken when a free-running camera sends nothing for
  ``watchdog_s``. Either way ``next_frame`` raises StreamBroken and the caller reconnects
  with ``drivers.reconnect.reopen_with_backoff`` (close, then open + start with back-off
  on monotonic deadlines). ``open`` re-applies the requested settings, so a camera that
  lost power comes back configured; counters survive the reconnect.
"""

from __future__ import annotations

import ipaddress
import threading
import time

import numpy as np
import structlog

from cubeloc.drivers.aravis_settings import apply_settings, read_settings
from cubeloc.drivers.base import (
    PIXEL_BITS,
    CameraBase,
    CameraNotFound,
    CameraSettings,
    CaptureStats,
    DeviceInfo,
    Frame,
    FrameTimeout,
    StreamBroken,
)
from cubeloc.drivers.clock import DeviceClockMapper
from cubeloc.drivers.frame_accounting import FrameAccounting, Verdict
from cubeloc.drivers.genicam import FeatureMap, probe_features
from cubeloc.drivers.ownership import CameraLock
from cubeloc.images import to_mono8

log = structlog.get_logger()

BUFFER_COUNT = 8
POP_SLICE_S = 0.2  # wait for buffers in slices this long, so control-lost is seen promptly
PERIODIC_READ_INTERVAL_S = 1.0  # exposure under auto, Aravis' stream counters
TRANSPORTS = {"GigEVision": "gige", "USB3Vision": "usb3", "Fake": "fake"}


def _aravis():
    """Import Aravis lazily: the pipeline never imports gi."""
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis, GLib

    return Aravis, GLib


def list_aravis_devices(include_fake: bool = False) -> list[DeviceInfo]:
    """Every camera Aravis sees (GigE Vision broadcast discovery, USB3 Vision)."""
    Aravis, _ = _aravis()
    if include_fake:
        Aravis.enable_interface("Fake")
    Aravis.update_device_list()
    devices = []
    for index in range(Aravis.get_n_devices()):
        protocol = Aravis.get_device_protocol(index) or ""
        devices.append(
            DeviceInfo(
                device_id=f"aravis:{Aravis.get_device_id(index)}",
                vendor=Aravis.get_device_vendor(index) or "",
                model=Aravis.get_device_model(index) or "",
                serial=Aravis.get_device_serial_nbr(index) or "",
                transport=TRANSPORTS.get(protocol, protocol.lower()),
                address=Aravis.get_device_address(index) or Aravis.get_device_physical_id(index) or "",
            )
        )
    return devices


def camera_lock_key(device: DeviceInfo) -> str:
    """The one lock name of a camera however it is reached: vendor-model-serial when the
    serial is known (discovery calls the fake "Aravis-Fake-GV01"; the same camera opened by
    IP address says its device id is "GV01"), else the id it was opened by."""
    if device.serial:
        return "-".join(part for part in (device.vendor, device.model, device.serial) if part)
    return device.device_id.removeprefix("aravis:")


def _release(objects: list) -> None:
    """Drop the last references (in a background thread: see AravisCamera._teardown)."""
    objects.clear()


def _matches(device: DeviceInfo, wanted: str) -> bool:
    aravis_id = device.device_id.removeprefix("aravis:")
    return wanted in (aravis_id, device.serial, device.address)


def _is_ip_address(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return True


class AravisCamera(CameraBase):
    """One GigE Vision / USB3 Vision camera. ``watchdog_s=None``: 3 s or 5 frame periods."""

    def __init__(self, wanted: str, settings: CameraSettings, *, buffers: int = BUFFER_COUNT,
                 watchdog_s: float | None = None) -> None:
        self._wanted = wanted
        self._settings = settings
        self._buffers = buffers
        self._watchdog_s = watchdog_s
        self._stats = CaptureStats()
        self._info = DeviceInfo(device_id=f"aravis:{wanted}" if wanted else "aravis",
                                vendor="", model="", serial="", transport="")
        self._accounting = FrameAccounting(self._stats)
        self._clock = DeviceClockMapper()
        self._lock: CameraLock | None = None
        self._resolved: DeviceInfo | None = None  # the device found by the first open
        self._camera = None  # Aravis.Camera while open
        self._stream = None  # Aravis.Stream while open
        self._features: FeatureMap | None = None
        self._lost = threading.Event()
        self._lost_handler: int | None = None
        self._streaming = False
        self._last_buffer_at = 0.0
        self._exposure_us = 0.0
        self._exposure_read_at = 0.0

    # -- protocol properties ---------------------------------------------------------
    @property
    def features(self) -> FeatureMap | None:
        return self._features

    # -- open / close ------------------------------------------------------------------
    def open(self) -> None:
        if self._camera is not None:
            return
        Aravis, GLib = _aravis()
        if self._wanted.startswith("Fake_"):
            Aravis.enable_interface("Fake")
        # After a first open, reconnects go straight to the same device (same lock key).
        info = self._resolved or self._resolve()
        aravis_id = info.device_id.removeprefix("aravis:")
        try:
            if info.serial:  # discovered: lock before anything touches the camera
                self._take_lock(camera_lock_key(info))
            try:
                self._camera = Aravis.Camera.new(aravis_id)
            except GLib.Error as exc:
                raise CameraNotFound(f"camera {aravis_id}: cannot open ({exc.message}); "
                                     "check power, cable and 'cubeloc devices'") from None
            if not info.serial:
                # Opened by IP without discovery: name it as discovery would, then lock under
                # that name (a second GigE opener only gets read access: nothing disturbed).
                info = self._describe_opened(info)
                self._take_lock(camera_lock_key(info))
            self._info = info
            self._features = probe_features(self._camera.get_device(), aravis_id)
            self._clock.reset()  # a reconnected camera may have restarted its clock
            apply_settings(self._camera, self._features, self._settings, Aravis, GLib)
            self._exposure_us = self._read_exposure_us(GLib)
            self._lost.clear()
            self._lost_handler = self._camera.get_device().connect("control-lost", self._on_control_lost)
            self._stream = self._camera.create_stream(None, None)
            payload = self._camera.get_payload()
            for _ in range(self._buffers):
                self._stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        except BaseException:
            self.close()
            raise
        self._resolved = info
        log.info("camera open", camera=aravis_id, vendor=info.vendor, model=info.model,
                 transport=info.transport, features={k: v for k, v in self._features.names.items() if v})

    def _take_lock(self, key: str) -> None:
        if self._lock is not None and self._lock.camera_key != key:
            self._lock.release()  # the device turned out to have another name
            self._lock = None
        if self._lock is None:
            lock = CameraLock(key)
            lock.acquire()  # CameraBusy naming the holder
            self._lock = lock

    def _describe_opened(self, info: DeviceInfo) -> DeviceInfo:
        cam = self._camera
        return DeviceInfo(device_id=f"aravis:{cam.get_device_id() or info.address}",
                          vendor=cam.get_vendor_name() or "", model=cam.get_model_name() or "",
                          serial=cam.get_device_serial_number() or "", transport=info.transport,
                          address=info.address)

    def _resolve(self) -> DeviceInfo:
        """The device to open: by id, serial, address, or the first one found."""
        devices = list_aravis_devices()
        if not self._wanted:
            if not devices:
                raise CameraNotFound("no GigE Vision or USB3 Vision camera found; check power, "
                                     "cable and network, and run 'cubeloc devices'")
            return devices[0]
        found = next((d for d in devices if _matches(d, self._wanted)), None)
        if found is not None:
            return found
        if _is_ip_address(self._wanted):
            # A GigE camera on another subnet answers unicast but not broadcast discovery.
            return DeviceInfo(device_id=f"aravis:{self._wanted}", vendor="", model="", serial="",
                              transport="gige", address=self._wanted)
        known = ", ".join(d.device_id.removeprefix("aravis:") for d in devices) or "none"
        raise CameraNotFound(f"no camera {self._wanted!r} (device id, serial or IP address); "
                             f"cameras found: {known}; see 'cubeloc devices'")

    def close(self) -> None:
        self._teardown()
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def _teardown(self, camera_gone: bool = False) -> None:
        """Drop the Aravis objects but keep the lock (used on close and on a broken stream).

        When the camera is gone, Aravis' clean-up of a stream and device (register writes
        to a camera that never answers, with retries) takes 10 s or more; it runs in a
        background thread (PyGObject releases the GIL while unreferencing) so the caller
        learns of the broken stream at once and can start reconnecting.
        """
        streaming = self._streaming
        # Closing a camera that silently went away (not yet noticed by next_frame): the same.
        camera_gone = camera_gone or self._seems_gone()
        camera, stream = self._camera, self._stream
        self._camera = self._stream = None
        self._streaming = False
        if camera is None:
            return
        if self._lost_handler is not None:
            camera.get_device().disconnect(self._lost_handler)
            self._lost_handler = None
        if camera_gone:
            doomed = [stream, camera]
            del stream, camera  # the thread must hold the last references, not this frame
            threading.Thread(target=_release, args=(doomed,), name="aravis-release",
                             daemon=True).start()
            return
        if streaming:
            _, GLib = _aravis()
            try:
                camera.stop_acquisition()
            except GLib.Error as exc:  # the camera went away just now: nothing to stop
                log.debug("stop_acquisition failed", error=exc.message)

    def _on_control_lost(self, _device) -> None:
        # Called from an Aravis thread: only set a flag; next_frame acts on it.
        self._lost.set()

    def read_settings(self) -> CameraSettings:
        """The settings the camera reports now (for checks and the status line)."""
        return read_settings(self._require_open(), self._settings)

    def _require_open(self):
        if self._camera is None:
            raise StreamBroken(f"camera {self._info.device_id} is not open; call open() first")
        return self._camera

    # -- streaming -------------------------------------------------------------------------
    def start(self) -> None:
        cam = self._require_open()
        if self._streaming:
            return
        self._accounting.restart()
        _, GLib = _aravis()
        try:
            cam.start_acquisition()
        except GLib.Error as exc:
            self._teardown()
            raise StreamBroken(f"camera {self._info.device_id}: cannot start acquisition ({exc.message})") from None
        self._streaming = True
        self._last_buffer_at = time.monotonic()

    def stop(self) -> None:
        if self._camera is None or not self._streaming:
            return
        if self._seems_gone():
            self._teardown(camera_gone=True)  # nothing to stop; close() then releases the lock
            return
        _, GLib = _aravis()
        try:
            self._camera.stop_acquisition()
        except GLib.Error as exc:
            log.warning("stop_acquisition failed", camera=self._info.device_id, error=exc.message)
        self._streaming = False

    def _seems_gone(self) -> bool:
        """Control lost, or a streaming camera silent for longer than the watchdog."""
        watchdog = self._watchdog_limit_s()
        return self._lost.is_set() or (
            self._streaming and watchdog is not None and time.monotonic() - self._last_buffer_at > watchdog)

    def _watchdog_limit_s(self) -> float | None:
        if self._settings.trigger == "line0":
            return None  # an external trigger may legitimately pause for any time
        if self._watchdog_s is not None:
            return self._watchdog_s
        rate = self._settings.frame_rate_hz
        return max(3.0, 5.0 / rate) if rate else 3.0

    def _broken(self, reason: str) -> StreamBroken:
        self._teardown(camera_gone=True)  # keep the lock: we mean to come back
        log.warning("camera stream broken", camera=self._info.device_id, reason=reason)
        return StreamBroken(f"camera {self._info.device_id}: {reason}")

    def next_frame(self, timeout_s: float) -> Frame:
        if self._stream is None or not self._streaming:
            raise StreamBroken(f"camera {self._info.device_id} is not streaming; open() and start() it")
        Aravis, GLib = _aravis()
        deadline = time.monotonic() + timeout_s
        watchdog = self._watchdog_limit_s()
        triggered = False
        while True:
            if self._lost.is_set():
                raise self._broken("control lost (no answer to heartbeats: power, cable or network)")
            now = time.monotonic()
            if watchdog is not None and now - self._last_buffer_at > watchdog:
                raise self._broken(f"no frame for {now - self._last_buffer_at:.1f} s")
            if now >= deadline:
                self._stats.timeouts += 1
                raise FrameTimeout(f"camera {self._info.device_id}: no frame within {timeout_s:g} s")
            if self._settings.trigger == "software" and not triggered:
                try:
                    self._camera.software_trigger()
                except GLib.Error as exc:
                    raise self._broken(f"software trigger failed ({exc.message})") from None
                triggered = True
            slice_s = min(POP_SLICE_S, deadline - now)
            buffer = self._stream.timeout_pop_buffer(max(1, int(slice_s * 1e6)))
            if buffer is None:
                continue
            self._last_buffer_at = time.monotonic()
            try:
                frame = self._frame_from(buffer, Aravis)
            finally:
                self._stream.push_buffer(buffer)
            if frame is not None:
                return frame

    def _frame_from(self, buffer, Aravis) -> Frame | None:
        status = buffer.get_status()
        image_payload = buffer.get_payload_type() == Aravis.BufferPayloadType.IMAGE
        status_ok = status == Aravis.BufferStatus.SUCCESS and image_payload
        # missing_packets, size_mismatch, timeout, wrong_packet_id, aborted ... (Aravis' names)
        cause = (getattr(status, "value_nick", str(int(status))).replace("-", "_")
                 if status != Aravis.BufferStatus.SUCCESS else "not_an_image")
        device_ns = buffer.get_timestamp()
        verdict = self._accounting.judge(status_ok, buffer.get_frame_id(), device_ns, cause)
        if verdict is not Verdict.ACCEPT:
            return None
        width, height = buffer.get_image_width(), buffer.get_image_height()
        data = buffer.get_image_data()  # the one copy: C buffer -> bytes
        bits = PIXEL_BITS[self._settings.pixel_format]
        size = width * height * (1 if bits == 8 else 2)
        if len(data) < size:
            self._stats.delivered -= 1
            self._stats.incomplete += 1
            self._stats.incomplete_causes["short_data"] = self._stats.incomplete_causes.get("short_data", 0) + 1
            return None
        if bits == 8:
            image = np.frombuffer(data, dtype=np.uint8, count=width * height).reshape(height, width)
        else:  # two bytes a pixel, little-endian (GenICam's unpacked Mono10/12/16): the top 8 bits
            image = to_mono8(np.frombuffer(data, dtype="<u2", count=width * height).reshape(height, width), bits)
        receipt_ns = buffer.get_system_timestamp() or time.time_ns()
        stamp_ns = self._clock.map(device_ns, receipt_ns).stamp_ns
        return Frame(image=image, frame_id=buffer.get_frame_id(), device_timestamp_ns=device_ns,
                     stamp_ns=stamp_ns, exposure_us=self._current_exposure_us())

    def _current_exposure_us(self) -> float:
        # Register reads cost a network round trip: under auto exposure the value changes,
        # so re-read it (and Aravis' stream counters) at most once a second.
        now = time.monotonic()
        if now - self._exposure_read_at > PERIODIC_READ_INTERVAL_S and self._camera is not None:
            _, GLib = _aravis()
            if self._settings.exposure_us is None:
                self._exposure_us = self._read_exposure_us(GLib)
            self._stats.extra.update(self.stream_counters())
            self._exposure_read_at = now
        return self._exposure_us

    def _read_exposure_us(self, GLib) -> float:
        try:
            if self._camera.is_exposure_time_available():
                return float(self._camera.get_exposure_time())
        except GLib.Error:
            pass  # keep the last value; a lost camera shows up on the next pop
        return self._exposure_us

    def stream_counters(self) -> dict[str, int]:
        """Aravis' own stream counters (underruns, missing/resent packets, ...), non-zero ones."""
        stream = self._stream
        if stream is None:
            return {}
        counters = {}
        for index in range(stream.get_n_infos()):
            name = stream.get_info_name(index)
            if name.startswith("n_") and name != "n_transferred_bytes":
                value = stream.get_info_uint64(index)
                if value:
                    counters[f"aravis_{name}"] = int(value)
        return counters


def open_aravis_source(argument: str, settings: CameraSettings) -> AravisCamera:
    """Factory for ``aravis[:ID]`` (see ``drivers.registry``); the camera is not opened yet."""
    return AravisCamera(argument, settings, buffers=settings.stream_buffers)
