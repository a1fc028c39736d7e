"""USB discovery with pyusb: what Aravis does not tell (link speed, permissions).

A USB3 Vision camera has an interface of class 0xEF (miscellaneous), subclass 0x05
(USB3 Vision; protocol 0 control, 1 event, 2 streaming). Hikvision (vendor 0x2bdf) is
listed whatever its descriptors say, as some of its models need a vendor driver.

Two problems are reported with their fix, as notes on the device:

* a USB3 camera (bcdUSB >= 3.0) on a high-speed (USB2, 480 Mb/s) link: it will run at a
  fraction of its frame rate or drop frames;
* no read/write access to ``/dev/bus/usb/BBB/DDD``: Aravis cannot open it; the udev rule
  in ``systemd/99-cubeloc-cameras.rules`` gives the ``cubeloc`` group access.

A machine without USB (no ``/dev/bus/usb``, no libusb) gives an empty list or a note,
never an exception: discovery must not stop ``cubeloc devices``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import structlog

from cubeloc.drivers.base import DeviceInfo

log = structlog.get_logger()

USB3_VISION_CLASS = 0xEF
USB3_VISION_SUBCLASS = 0x05
HIKVISION_VENDOR = 0x2BDF
SPEED_HIGH = 3  # usb.util.SPEED_HIGH: USB2, 480 Mb/s
SPEED_SUPER = 4  # usb.util.SPEED_SUPER: USB3, 5 Gb/s
SPEED_NAMES = {1: "low speed (1.5 Mb/s)", 2: "full speed (12 Mb/s)", 3: "USB2 high speed (480 Mb/s)",
               4: "USB3 SuperSpeed (5 Gb/s)", 5: "USB3 SuperSpeed+ (10 Gb/s)"}
RULE_FILE = "systemd/99-cubeloc-cameras.rules"
PERMISSION_FIX = (f"install the udev rule: sudo cp {RULE_FILE} /etc/udev/rules.d/ && sudo udevadm "
                  "control --reload && sudo udevadm trigger; then sudo groupadd -f cubeloc && "
                  "sudo usermod -aG cubeloc $USER and log in again")


@dataclass(frozen=True)
class UsbFacts:
    """What the descriptors and /dev say about one USB device."""

    vendor_id: int
    product_id: int
    bcd_usb: int  # 0x0300 and above: a USB3 device
    speed: int | None  # usb.util.SPEED_*; None when unknown
    interfaces: tuple[tuple[int, int], ...]  # (class, subclass) of every interface
    bus: int
    address: int
    port_path: str  # "2-1.3" as in /sys/bus/usb/devices
    manufacturer: str = ""
    product: str = ""
    serial: str = ""
    accessible: bool = True  # read/write access to the device node


def is_camera(facts: UsbFacts) -> bool:
    return facts.vendor_id == HIKVISION_VENDOR or (USB3_VISION_CLASS, USB3_VISION_SUBCLASS) in facts.interfaces


def describe(facts: UsbFacts) -> DeviceInfo:
    """One camera as ``cubeloc devices`` shows it, with notes on problems and fixes."""
    notes = []
    if facts.bcd_usb >= 0x0300 and facts.speed is not None and facts.speed < SPEED_SUPER:
        notes.append(f"USB3 camera on a {SPEED_NAMES.get(facts.speed, 'slow')} link: expect a "
                     "low frame rate and dropped frames; use a USB3 port (often blue) and a USB3 cable")
    if facts.speed is not None:
        notes.append(f"link: {SPEED_NAMES.get(facts.speed, 'unknown speed')}")
    if not facts.accessible:
        notes.append(f"no permission to open /dev/bus/usb/{facts.bus:03d}/{facts.address:03d}; "
                     + PERMISSION_FIX)
    if (USB3_VISION_CLASS, USB3_VISION_SUBCLASS) not in facts.interfaces:
        notes.append("no USB3 Vision interface: this model needs the vendor's SDK, Aravis cannot use it")
    return DeviceInfo(
        device_id=f"aravis:{facts.serial}" if facts.serial else "",
        vendor=facts.manufacturer or f"vendor 0x{facts.vendor_id:04x}",
        model=facts.product or f"product 0x{facts.product_id:04x}",
        serial=facts.serial,
        transport="usb3" if facts.bcd_usb >= 0x0300 else "usb",
        address=f"usb {facts.port_path} ({facts.vendor_id:04x}:{facts.product_id:04x})",
        notes=tuple(notes),
    )


def list_usb_cameras() -> tuple[list[DeviceInfo], list[str]]:
    """(USB3 Vision / Hikvision cameras, notes about USB discovery itself)."""
    try:
        import usb.core
    except ImportError:
        return [], ["pyusb is not installed: USB link speed and permissions not checked"]
    try:
        devices = list(usb.core.find(find_all=True))
    except usb.core.NoBackendError:
        return [], ["libusb not found (Debian: apt-get install libusb-1.0-0): USB cameras not checked"]
    except (usb.core.USBError, OSError) as exc:
        return [], [f"USB enumeration failed ({exc}): USB cameras not checked"]
    cameras = []
    for device in devices:
        try:
            facts = _facts(device)
        except (usb.core.USBError, OSError, ValueError) as exc:
            log.debug("skipping a USB device", error=str(exc))
            continue
        if is_camera(facts):
            cameras.append(describe(facts))
    return cameras, []


def _facts(device) -> UsbFacts:
    interfaces = []
    for configuration in device:
        for interface in configuration:
            interfaces.append((interface.bInterfaceClass, interface.bInterfaceSubClass))
    node = f"/dev/bus/usb/{device.bus:03d}/{device.address:03d}"
    accessible = os.access(node, os.R_OK | os.W_OK)
    ports = getattr(device, "port_numbers", None) or ()
    strings = _strings(device) if accessible else ("", "", "")
    return UsbFacts(
        vendor_id=device.idVendor, product_id=device.idProduct, bcd_usb=device.bcdUSB,
        speed=device.speed, interfaces=tuple(interfaces), bus=device.bus, address=device.address,
        port_path=f"{device.bus}-{'.'.join(str(p) for p in ports)}" if ports else str(device.bus),
        manufacturer=strings[0], product=strings[1], serial=strings[2], accessible=accessible,
    )


def _strings(device) -> tuple[str, str, str]:
    """Manufacturer, product, serial: reading them opens the device, which may fail."""
    import usb.core
    import usb.util

    values = []
    for index in (device.iManufacturer, device.iProduct, device.iSerialNumber):
        try:
            values.append(usb.util.get_string(device, index) or "" if index else "")
        except (usb.core.USBError, ValueError, NotImplementedError):
            values.append("")
    return values[0], values[1], values[2]
