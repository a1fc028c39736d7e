"""Applying ``CameraSettings`` to an Aravis camera, and reading them back.

Where ``ArvCamera`` has a high-level call that knows the vendor quirks (frame rate behind
an enable switch, ``...Abs`` names), it is used; ``drivers.genicam`` names the features in
the errors and covers what ``ArvCamera`` does not (the frame-rate enable switch for
"no limit"). ``None`` settings turn auto on where the camera has it, otherwise leave the
camera's value. Values outside the camera's range, or a region that does not fit the
sensor, raise FeatureNotSupported naming the setting and the range.

Order matters: trigger off before the frame rate (many cameras lock the rate under a
trigger), region before anything sized by it (the payload).
"""

from __future__ import annotations

import dataclasses

import structlog

from cubeloc.drivers.base import CameraError, CameraSettings, FeatureNotSupported
from cubeloc.drivers.genicam import FeatureMap

log = structlog.get_logger()

SAFE_PACKET_SIZE = 1400  # fits a 1500-byte MTU with IP/UDP/GVSP headers


def apply_settings(cam, features: FeatureMap, settings: CameraSettings, Aravis, GLib) -> None:
    """Apply ``settings`` to an open, idle ``Aravis.Camera``; errors name the feature."""
    name = features.camera
    try:
        cam.set_acquisition_mode(Aravis.AcquisitionMode.CONTINUOUS)
        formats = cam.dup_available_pixel_formats_as_strings() or []
        if settings.pixel_format not in formats:
            raise FeatureNotSupported(f"camera {name} has no PixelFormat {settings.pixel_format} (it offers "
                                      f"{', '.join(formats) or 'none'}); set camera.pixel_format to a mono "
                                      "format it has (Mono8, Mono10, Mono12 or Mono16)")
        cam.set_pixel_format_from_string(settings.pixel_format)
        _set_region(cam, settings, name)
        _set_trigger(cam, features, settings.trigger)
        _set_frame_rate(cam, features, settings.frame_rate_hz)
        _set_exposure(cam, features, settings.exposure_us, Aravis)
        _set_gain(cam, features, settings.gain_db, Aravis)
        if cam.is_uv_device():
            _set_usb(cam, settings, name, Aravis)
        if cam.is_gv_device():
            try:
                cam.gv_auto_packet_size()
            except GLib.Error as exc:
                log.warning("packet size negotiation failed", camera=name, error=exc.message,
                            packet_size=SAFE_PACKET_SIZE)
                cam.gv_set_packet_size(SAFE_PACKET_SIZE)
    except GLib.Error as exc:
        raise CameraError(f"camera {name}: applying the settings failed ({exc.message}); "
                          "check the [camera] values against the camera's ranges") from None


def _set_usb(cam, s: CameraSettings, name: str, Aravis) -> None:
    """USB3 Vision: the transfer mode, and the link throughput limit when one is asked."""
    if s.usb_mode != "default":
        cam.uv_set_usb_mode(Aravis.UvUsbMode.ASYNC if s.usb_mode == "async" else Aravis.UvUsbMode.SYNC)
    if s.usb_bandwidth_mbps is not None:
        if not cam.uv_is_bandwidth_control_available():
            raise FeatureNotSupported(f"camera {name} has no DeviceLinkThroughputLimit; "
                                      "remove camera.usb_bandwidth_mbps")
        low, high = cam.uv_get_bandwidth_bounds()  # bytes per second
        wanted = int(s.usb_bandwidth_mbps * 1e6 / 8)
        if not low <= wanted <= high:
            raise FeatureNotSupported(f"camera {name}: usb_bandwidth_mbps = {s.usb_bandwidth_mbps:g} is outside "
                                      f"its range {low * 8 / 1e6:g}..{high * 8 / 1e6:g}")
        cam.uv_set_bandwidth(wanted)


def _set_region(cam, s: CameraSettings, name: str) -> None:
    sensor = cam.get_sensor_size()
    width_max, height_max = cam.get_width_bounds()[1], cam.get_height_bounds()[1]
    width_max, height_max = max(width_max, sensor[0]), max(height_max, sensor[1])
    if s.offset_x + s.width > width_max or s.offset_y + s.height > height_max:
        raise FeatureNotSupported(
            f"camera {name}: region {s.width}x{s.height}+{s.offset_x}+{s.offset_y} does not fit "
            f"the sensor ({width_max}x{height_max}); choose a smaller width/height or offset")
    cam.set_region(s.offset_x, s.offset_y, s.width, s.height)
    got = tuple(cam.get_region())
    if got != (s.offset_x, s.offset_y, s.width, s.height):
        raise FeatureNotSupported(
            f"camera {name}: region {s.width}x{s.height}+{s.offset_x}+{s.offset_y} became "
            f"{got[2]}x{got[3]}+{got[0]}+{got[1]} (size/offset increments); choose multiples "
            f"of {cam.get_width_increment()}x{cam.get_height_increment()}")


def _set_trigger(cam, features: FeatureMap, trigger: str) -> None:
    if trigger == "free":
        if features.get("trigger_mode"):
            cam.clear_triggers()
        return
    features.require("trigger_mode", f"trigger = {trigger!r}")
    if trigger == "software":
        features.require("trigger_software", "trigger = 'software'")
        cam.set_trigger("Software")
    else:
        features.require("trigger_source", "trigger = 'line0'")
        sources = cam.dup_available_trigger_sources() or []
        if "Line0" not in sources:
            raise FeatureNotSupported(f"camera {features.camera} has no TriggerSource Line0 "
                                      f"(it offers {', '.join(sources) or 'none'})")
        cam.set_trigger("Line0")


def _set_frame_rate(cam, features: FeatureMap, rate: float | None) -> None:
    enable = features.get("frame_rate_enable")
    if rate is None:
        if enable:  # no limit: as fast as exposure and bandwidth allow
            cam.set_boolean(enable, False)
        return
    if not cam.is_frame_rate_available():
        features.require("frame_rate", f"frame_rate_hz = {rate}")
    low, high = cam.get_frame_rate_bounds()
    if not low <= rate <= high:
        raise FeatureNotSupported(f"camera {features.camera}: frame_rate_hz = {rate} is outside "
                                  f"its range {low:g}..{high:g} Hz")
    cam.set_frame_rate(rate)  # Aravis knows the vendor quirks (enable switches, Abs names)


def _set_exposure(cam, features: FeatureMap, exposure: float | None, Aravis) -> None:
    if exposure is None:
        if cam.is_exposure_auto_available():
            cam.set_exposure_time_auto(Aravis.Auto.CONTINUOUS)
        return
    if not cam.is_exposure_time_available():
        features.require("exposure", f"exposure_us = {exposure}")
    if cam.is_exposure_auto_available():
        cam.set_exposure_time_auto(Aravis.Auto.OFF)
    low, high = cam.get_exposure_time_bounds()
    if not low <= exposure <= high:
        raise FeatureNotSupported(f"camera {features.camera}: exposure_us = {exposure} is outside "
                                  f"its range {low:g}..{high:g} us")
    cam.set_exposure_time(exposure)


def _set_gain(cam, features: FeatureMap, gain: float | None, Aravis) -> None:
    if gain is None:
        if cam.is_gain_auto_available():
            cam.set_gain_auto(Aravis.Auto.CONTINUOUS)
        return
    if not cam.is_gain_available():
        features.require("gain", f"gain_db = {gain}")
    if features.get("gain") == "GainRaw":
        log.warning("camera has only GainRaw: gain_db is written in the camera's raw units",
                    camera=features.camera)
    if cam.is_gain_auto_available():
        cam.set_gain_auto(Aravis.Auto.OFF)
    low, high = cam.get_gain_bounds()
    if not low <= gain <= high:
        raise FeatureNotSupported(f"camera {features.camera}: gain_db = {gain} is outside its "
                                  f"range {low:g}..{high:g}")
    cam.set_gain(gain)


def read_settings(cam, requested: CameraSettings) -> CameraSettings:
    """The settings an open ``Aravis.Camera`` reports now (the trigger mode and the stream
    settings as requested)."""
    x, y, width, height = cam.get_region()
    return dataclasses.replace(requested,
        width=width, height=height, offset_x=x, offset_y=y,
        exposure_us=cam.get_exposure_time() if cam.is_exposure_time_available() else None,
        gain_db=cam.get_gain() if cam.is_gain_available() else None,
        frame_rate_hz=cam.get_frame_rate() if cam.is_frame_rate_available() else None,
        pixel_format=cam.get_pixel_format_as_string(),
    )
