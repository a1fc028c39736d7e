"""Every camera on this machine: Aravis (GigE Vision, USB3 Vision) merged with USB facts.

Aravis knows how to open a camera; pyusb knows the link speed and whether the device node
is accessible. A USB camera both see becomes one entry (matched by serial number) with
pyusb's notes; a USB camera only pyusb sees (typically: no permission, so Aravis could not
open it to list it) is listed with the fix. Aravis' fake camera is listed only on request.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import structlog

from cubeloc.drivers.base import DeviceInfo
from cubeloc.drivers.usb import list_usb_cameras

log = structlog.get_logger()


@dataclass(frozen=True)
class Discovery:
    devices: list[DeviceInfo]
    notes: list[str]  # about discovery itself (Aravis or libusb missing, ...)


def merge(aravis: list[DeviceInfo], usb: list[DeviceInfo]) -> list[DeviceInfo]:
    """Aravis entries first, USB facts folded into the matching one (same serial)."""
    merged = list(aravis)
    for usb_device in usb:
        match = next((i for i, d in enumerate(merged)
                      if usb_device.serial and d.serial == usb_device.serial and d.transport in ("usb3", "usb")), None)
        if match is None:
            merged.append(usb_device)
        else:
            found = merged[match]
            merged[match] = replace(found, address=found.address or usb_device.address,
                                    notes=found.notes + usb_device.notes)
    return merged


def discover(include_fake: bool = False) -> Discovery:
    notes: list[str] = []
    aravis: list[DeviceInfo] = []
    try:
        from cubeloc.drivers.aravis_camera import list_aravis_devices

        aravis = list_aravis_devices(include_fake=include_fake)
    except (ImportError, ValueError) as exc:  # no PyGObject, or no Aravis typelib
        notes.append(f"Aravis is not available ({exc}); install gir1.2-aravis-0.8 (make install)")
    usb, usb_notes = list_usb_cameras()
    return Discovery(devices=merge(aravis, usb), notes=notes + usb_notes)


def list_devices(include_fake: bool = False) -> list[DeviceInfo]:
    """Every camera found, Aravis and USB merged (see ``discover`` for the notes)."""
    return discover(include_fake).devices
