"""The hardware link checks of ``cubeloc doctor``: USB (permissions, link speed, the
kernel's usbfs budget) and GigE Vision (packet size against the interface MTU), and the
``Check`` record every check returns."""

from __future__ import annotations

import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

OK, WARN, FAIL = "OK", "WARN", "FAIL"


@dataclass(frozen=True)
class Check:
    check: str  # what was checked: config, aravis, cameras, usb, gige, calibration, target, zenoh, service
    level: str  # OK, WARN or FAIL
    message: str
    fix: str = ""
    command: str = ""  # the fix as one command that runs as printed (tests/test_doctor.py runs them)

    def line(self) -> str:
        fix = f" -- fix: {self.fix}" if self.fix else ""
        run = f"; run: {self.command}" if self.command else ""
        return f"{self.level:<4}  {self.check}: {self.message}{fix}{run}"


@dataclass(frozen=True)
class CameraProbe:
    """What opening the configured Aravis camera told (or why it was not opened)."""

    sensor: tuple[int, int] | None = None
    packet_size: int | None = None  # bytes per GVSP packet the path passes (GigE only)
    busy: str = ""  # who holds the camera, when someone does
    error: str = ""


USBFS_PARAMETER = "module/usbcore/parameters/usbfs_memory_mb"
USBFS_SUGGESTED_MB = 1000


def check_usbfs(config, sysfs: Path = Path("/sys")) -> Check:
    """The kernel's budget for USB transfers in flight (usbfs_memory_mb, 16 MB by default;
    0 is no limit) against what the stream needs: ``stream_buffers`` x the frame (Mono8).
    Too small, and a USB3 Vision camera drops or truncates frames at full rate."""
    path = sysfs / USBFS_PARAMETER
    try:
        budget_mb = int(path.read_text().strip())
    except (OSError, ValueError):
        return Check("usbfs", OK, f"no {path}: usbcore not loaded, nothing to check")
    camera = config.camera
    frame_mb = camera.width * camera.height / 2**20
    need_mb = camera.stream_buffers * frame_mb
    what = (f"{camera.stream_buffers} buffers x {frame_mb:.2f} MB ({camera.width}x{camera.height} Mono8) "
            f"= {need_mb:.1f} MB")
    if budget_mb == 0:
        return Check("usbfs", OK, f"usbfs_memory_mb is 0 (no limit); the stream needs {what}")
    if budget_mb >= need_mb:
        return Check("usbfs", OK, f"usbfs_memory_mb {budget_mb} MB holds {what}")
    return Check(
        "usbfs", FAIL,
        f"usbfs_memory_mb is {budget_mb} MB but the stream needs {what}: a USB3 camera will drop or truncate frames",
        f"at once: echo {USBFS_SUGGESTED_MB} | sudo tee {path}; for good: add usbcore.usbfs_memory_mb="
        f"{USBFS_SUGGESTED_MB} to GRUB_CMDLINE_LINUX in /etc/default/grub and run sudo update-grub (where "
        f"usbcore is a module: 'options usbcore usbfs_memory_mb={USBFS_SUGGESTED_MB}' in "
        "/etc/modprobe.d/usbfs.conf); or lower camera.stream_buffers",
    )


def check_usb() -> list[Check]:
    from cubeloc.drivers.usb import PERMISSION_FIX, SPEED_NAMES, SPEED_SUPER, is_camera

    try:
        import usb.core

        from cubeloc.drivers.usb import _facts
    except ImportError:
        return [Check("usb", WARN, "pyusb is not installed: USB permissions and link speed not checked",
                      "pip install pyusb (make install)")]
    try:
        devices = list(usb.core.find(find_all=True))
    except usb.core.NoBackendError:
        return [Check("usb", WARN, "libusb not found: USB cameras not checked", "sudo apt-get install libusb-1.0-0")]
    except (usb.core.USBError, OSError) as exc:
        return [Check("usb", WARN, f"USB enumeration failed ({exc})")]
    checks = []
    for device in devices:
        try:
            facts = _facts(device)
        except (usb.core.USBError, OSError, ValueError):
            continue
        if not is_camera(facts):
            continue
        name = f"{facts.manufacturer or f'{facts.vendor_id:04x}'} {facts.product or f'{facts.product_id:04x}'} at usb {facts.port_path}"
        if not facts.accessible:
            checks.append(Check("usb", FAIL, f"{name}: no read/write permission on /dev/bus/usb/"
                                f"{facts.bus:03d}/{facts.address:03d}", PERMISSION_FIX))
        if facts.bcd_usb >= 0x0300 and facts.speed is not None and facts.speed < SPEED_SUPER:
            checks.append(Check("usb", WARN, f"{name}: USB3 camera on a {SPEED_NAMES.get(facts.speed, 'slow')} link",
                                "plug it into a USB3 port (often blue) with a USB3 cable"))
        elif facts.accessible:
            checks.append(Check("usb", OK, f"{name}: {SPEED_NAMES.get(facts.speed, 'link speed unknown')}, permissions OK"))
    return checks


def route_interface(address: str) -> str | None:
    """The network interface that reaches ``address`` (``ip route get``), or None."""
    if shutil.which("ip") is None:
        return None
    try:
        out = subprocess.run(["ip", "-o", "route", "get", address], capture_output=True, text=True, timeout=5).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    words = out.split()
    return words[words.index("dev") + 1] if "dev" in words[:-1] else None


def interface_mtu(interface: str) -> int | None:
    try:
        return int(Path(f"/sys/class/net/{interface}/mtu").read_text().strip())
    except (OSError, ValueError):
        return None


def packet_size_verdict(camera: str, packet_size: int, interface: str | None, mtu: int | None) -> Check:
    """GevSCPSPacketSize (IP + UDP + GVSP headers and data) against the interface MTU."""
    if interface is None or mtu is None:
        return Check("gige", WARN, f"{camera}: packets of {packet_size} bytes; the interface towards the camera "
                     "and its MTU are unknown", "check with: ip route get CAMERA_IP; ip link")
    if packet_size > mtu:
        return Check("gige", FAIL, f"{camera}: packets of {packet_size} bytes exceed the MTU {mtu} of {interface}: "
                     "frames arrive incomplete", f"sudo ip link set dev {interface} mtu {max(packet_size, 9000)} "
                     "(and jumbo frames on the switch), or lower the camera's packet size")
    if mtu >= 8000 and packet_size <= 1500:
        return Check("gige", WARN, f"{camera}: {interface} has jumbo frames (MTU {mtu}) but only {packet_size}-byte "
                     "packets are used: the camera, or something on the path, does not take jumbo frames",
                     "enable jumbo frames on the switch and the camera's NIC; meanwhile it works at higher CPU load")
    hint = " (jumbo frames, MTU 9000, would lower the CPU load)" if mtu <= 1500 else ""
    return Check("gige", OK, f"{camera}: packets of {packet_size} bytes fit the MTU {mtu} of {interface}{hint}")


def check_gige(device, probe: CameraProbe) -> Check:
    name = device.device_id.removeprefix("aravis:")
    if probe.busy:
        return Check("gige", OK, f"{name}: packet size not checked while the camera is in use")
    if probe.error or probe.packet_size is None:
        return Check("gige", FAIL, f"{name}: {probe.error or 'no packet size'}", "check power, cable and network")
    interface = route_interface(device.address) if device.address else None
    return packet_size_verdict(name, probe.packet_size, interface, interface_mtu(interface) if interface else None)
