"""GenICam feature probing: which names this camera uses for what we need to set.

Vendors follow the SFNC (Standard Features Naming Convention) loosely: the frame rate is
``AcquisitionFrameRate`` on most cameras but ``AcquisitionFrameRateAbs`` on older Basler
and Allied Vision models, sometimes behind an ``AcquisitionFrameRateEnable`` (or
``...Enabled``) switch; exposure is ``ExposureTime`` or ``ExposureTimeAbs``; gain is
``Gain`` (dB) or only ``GainRaw`` (vendor units). So we ask the device which names it
implements instead of assuming, once per connection, and a missing feature becomes
FeatureNotSupported naming what was looked for.

``device`` is anything with ``is_feature_available(name) -> bool`` (an ``Aravis.Device``),
so this module does not import ``gi`` and is tested without a camera.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from cubeloc.drivers.base import FeatureNotSupported

# What we need -> candidate feature names, preferred first.
CANDIDATES: dict[str, tuple[str, ...]] = {
    "frame_rate": ("AcquisitionFrameRate", "AcquisitionFrameRateAbs"),
    "frame_rate_enable": ("AcquisitionFrameRateEnable", "AcquisitionFrameRateEnabled"),
    "exposure": ("ExposureTime", "ExposureTimeAbs"),
    "exposure_auto": ("ExposureAuto",),
    "gain": ("Gain", "GainRaw"),
    "gain_auto": ("GainAuto",),
    "trigger_mode": ("TriggerMode",),
    "trigger_source": ("TriggerSource",),
    "trigger_software": ("TriggerSoftware",),
    "pixel_format": ("PixelFormat",),
    "region": ("Width", "Height"),
    "offset": ("OffsetX", "OffsetY"),
    "packet_size": ("GevSCPSPacketSize",),
}


class FeatureDevice(Protocol):
    def is_feature_available(self, feature: str) -> bool: ...


@dataclass(frozen=True)
class FeatureMap:
    """The feature name this camera offers for each need (None: not offered)."""

    camera: str
    names: dict[str, str | None]

    def get(self, need: str) -> str | None:
        return self.names.get(need)

    def require(self, need: str, setting: str) -> str:
        """The feature name for ``need``, or FeatureNotSupported naming what was wanted."""
        name = self.names.get(need)
        if name is None:
            looked_for = " or ".join(CANDIDATES[need])
            raise FeatureNotSupported(
                f"camera {self.camera} does not offer {looked_for}, needed for {setting}; "
                "leave that setting unset (camera default) or use a camera that has it"
            )
        return name


def probe_features(device: FeatureDevice, camera: str) -> FeatureMap:
    """Ask the device which candidate names it implements (and are available now)."""
    names: dict[str, str | None] = {}
    for need, candidates in CANDIDATES.items():
        names[need] = next((c for c in candidates if _available(device, c)), None)
    return FeatureMap(camera=camera, names=names)


def _available(device: FeatureDevice, feature: str) -> bool:
    try:
        return bool(device.is_feature_available(feature))
    except Exception:  # a broken node in a vendor XML means "not usable"
        return False
