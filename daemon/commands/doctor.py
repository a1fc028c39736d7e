"""``cubeloc doctor``: what a technician runs when something is wrong.

One line per check, ``OK``, ``WARN`` or ``FAIL``, with the fix where there is one:

* the configuration (``--config``, else ``$CUBELOC_CONFIG``, else /etc/cubeloc/cubeloc.toml);
* the Aravis typelib (PyGObject + gir1.2-aravis-0.8);
* cameras visible (Aravis: GigE Vision and USB3 Vision) and the configured one among them;
* USB cameras: permission on the device node, link speed (a USB3 camera on a USB2 port);
* GigE cameras: the packet size the path passes against the MTU of the interface that
  reaches the camera, and the sensor size against ``camera.width/height``;
* the calibration file: readable, valid, for ``camera.width x camera.height`` and for this
  camera's serial number (``calibration.camera_serial``, written by ``cubeloc calibrate``);
* the target file;
* Zenoh: each configured endpoint reachable with the configured Zenoh file (TLS, user and
  password apply), and the daemon's ``cubeloc/<name>/alive`` token seen there;
* the service: ``systemctl is-active cubeloc`` where systemd runs.

Exit code 0 when nothing fails (warnings allowed), 1 when a check fails. ``--json``
prints one JSON document ``{"ok": bool, "checks": [{"check", "level", "message", "fix", "command"}]}``
(``command``: the fix as one command that runs as printed, or "").
A camera another process holds (the running daemon) is not opened: its lock says who.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import socket
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

from cubeloc.daemon.commands.doctor_checks import (  # noqa: F401 - FAIL, OK, WARN and the verdict are this command's API
    FAIL,
    OK,
    WARN,
    CameraProbe,
    Check,
    check_gige,
    check_usb,
    check_usbfs,
    packet_size_verdict,
)

ZENOH_TIMEOUT_S = 3.0
SERVICE = "cubeloc"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "doctor", help="check this machine: Aravis, cameras, USB, GigE MTU, calibration, target, Zenoh, service",
        description="Check everything the daemon needs, one line per check (OK, WARN, FAIL) with the fix. "
                    "Exit code 1 when a check fails.",
    )
    parser.add_argument("--config", metavar="FILE", help="TOML config file (default: as `cubeloc run`)")
    parser.add_argument("--fake", action="store_true", help="also see Aravis' built-in fake camera (Fake_1)")
    parser.add_argument("--json", action="store_true", help="one JSON document instead of lines")
    parser.add_argument("--timeout", type=float, default=ZENOH_TIMEOUT_S, metavar="S",
                        help=f"how long to wait for each Zenoh endpoint and the daemon's answer (default {ZENOH_TIMEOUT_S:g} s)")
    parser.set_defaults(func=run)


def run(args) -> int:
    from cubeloc.daemon.logs import configure_logging
    from cubeloc.errors import ConfigError

    configure_logging("error", "console", stream=sys.stderr)
    if not 0 < args.timeout <= 60:
        raise ConfigError(f"--timeout {args.timeout}: give 0 < S <= 60 seconds")
    checks = diagnose(args.config, include_fake=args.fake, timeout_s=args.timeout)
    failed = any(c.level == FAIL for c in checks)
    if args.json:
        print(json.dumps({"ok": not failed, "checks": [asdict(c) for c in checks]}, indent=1))
    else:
        for check in checks:
            print(check.line())
        print(f"{sum(c.level == FAIL for c in checks)} failed, {sum(c.level == WARN for c in checks)} warnings")
    return 1 if failed else 0


def diagnose(config_path: str | None, include_fake: bool = False, timeout_s: float = ZENOH_TIMEOUT_S) -> list[Check]:
    """Every check, in the order a technician would go."""
    from cubeloc.daemon.cameras import parse_source
    from cubeloc.errors import CubelocError

    config, checks = check_config(config_path)
    aravis_check, aravis_ok = check_aravis()
    checks.append(aravis_check)
    backend, argument = ("", "")
    if config is not None:
        try:
            backend, argument = parse_source(config.camera.source)
        except CubelocError as exc:  # CameraNotFound: an unknown backend
            checks.append(Check("camera", FAIL, str(exc), "set camera.source (see systemd/cubeloc.toml)"))
    include_fake = include_fake or argument.startswith("Fake_")
    devices, camera_checks = check_cameras(aravis_ok, include_fake, backend, argument)
    checks += camera_checks
    checks += check_usb()
    device = find_device(devices, argument) if backend == "aravis" else None
    if config is not None and backend == "aravis" and (device is None or device.transport in ("usb3", "usb")):
        checks.append(check_usbfs(config))  # a USB3 Vision camera, or one not found yet
    probe = probe_camera(device) if device is not None else None
    if probe is not None and probe.busy:
        checks.append(Check("camera", OK, f"in use, not opened: {probe.busy}"))
    elif probe is not None and probe.error:
        checks.append(Check("camera", FAIL, probe.error, "check power and cable; 'cubeloc devices' lists what is seen",
                            "cubeloc devices"))
    if device is not None and device.transport == "gige" and probe is not None:
        checks.append(check_gige(device, probe))
    if config is None:
        return checks + [check_service()]
    checks += check_calibration(config, config_path, device, probe)
    checks.append(check_target(config))
    checks += check_zenoh(config, timeout_s)
    checks.append(check_service())
    return checks


# -- configuration ---------------------------------------------------------------------------
def check_config(path: str | None):
    from cubeloc.daemon.config import DEFAULT_CONFIG_PATH, load_config
    from cubeloc.errors import CubelocError

    try:
        config = load_config(path)
    except CubelocError as exc:
        return None, [Check("config", FAIL, str(exc), "correct the file (every key: systemd/cubeloc.toml)")]
    if path is None and not os.environ.get("CUBELOC_CONFIG") and not DEFAULT_CONFIG_PATH.exists():
        return config, [Check("config", WARN, f"no {DEFAULT_CONFIG_PATH}: checking the built-in defaults",
                              f"sudo install -m 0644 systemd/cubeloc.toml {DEFAULT_CONFIG_PATH}, then edit it")]
    where = path or os.environ.get("CUBELOC_CONFIG") or DEFAULT_CONFIG_PATH
    return config, [Check("config", OK, f"{where} is valid (name {config.name}, camera {config.camera.source})")]


# -- Aravis and cameras ------------------------------------------------------------------
def check_aravis() -> tuple[Check, bool]:
    try:
        from cubeloc.drivers.aravis_camera import _aravis

        Aravis, _ = _aravis()
    except (ImportError, ValueError) as exc:  # no PyGObject, or no typelib
        return Check("aravis", FAIL, f"the Aravis typelib does not load ({exc})",
                     "sudo apt-get install gir1.2-aravis-0.8 (or: make install)"), False
    return Check("aravis", OK, f"Aravis {getattr(Aravis, '_version', '0.8')} typelib loads"), True


def check_cameras(aravis_ok: bool, include_fake: bool, backend: str, argument: str):
    from cubeloc.drivers.discovery import discover

    found = discover(include_fake=include_fake) if aravis_ok else None
    devices = found.devices if found is not None else []
    checks = [Check("cameras", WARN, note) for note in (found.notes if found is not None else [])
              if not note.startswith("Aravis is not available")]
    openable = [d for d in devices if d.device_id]
    if openable:
        listing = ", ".join(f"{d.device_id.removeprefix('aravis:')} ({d.transport}, {d.vendor} {d.model})".strip()
                            for d in openable)
        checks.append(Check("cameras", OK, f"{len(openable)} camera(s): {listing}"))
    elif aravis_ok:
        level = FAIL if backend == "aravis" else WARN
        checks.append(Check("cameras", level, "no GigE Vision or USB3 Vision camera found",
                            "check power and cable; GigE: same subnet as this machine; USB: see the usb lines"))
    if backend in ("replay", "synthetic"):
        checks.append(Check("camera", OK, f"camera.source is {backend}:{argument}: no camera hardware needed"))
    elif backend == "aravis" and openable:
        device = find_device(devices, argument)
        if device is None:
            known = ", ".join(d.device_id for d in openable)
            checks.append(Check("camera", FAIL, f"camera.source aravis:{argument} is not among the cameras found",
                                f"check the camera, or set camera.source to one of: {known}"))
        else:
            checks.append(Check("camera", OK, f"camera.source {'aravis:' + argument if argument else 'aravis'} is "
                                f"{device.vendor} {device.model} serial {device.serial or '?'} ({device.transport})"))
    return devices, checks


def find_device(devices, argument: str):
    """The device ``aravis[:argument]`` opens (the first openable one for a bare ``aravis``)."""
    openable = [d for d in devices if d.device_id]
    if not argument:
        return openable[0] if openable else None
    return next((d for d in openable if argument in (d.device_id.removeprefix("aravis:"), d.serial, d.address)), None)


def probe_camera(device) -> CameraProbe:
    """Open the camera briefly (unless someone holds it): sensor size, GigE packet size."""
    from cubeloc.drivers.aravis_camera import _aravis, camera_lock_key
    from cubeloc.drivers.ownership import CameraLock
    from cubeloc.errors import CubelocError

    aravis_id = device.device_id.removeprefix("aravis:")
    lock = CameraLock(camera_lock_key(device))
    try:
        lock.acquire()
    except CubelocError as exc:  # CameraBusy: the running daemon, usually
        return CameraProbe(busy=str(exc))
    try:
        Aravis, GLib = _aravis()
        if aravis_id.startswith("Fake_"):
            Aravis.enable_interface("Fake")
        try:
            camera = Aravis.Camera.new(aravis_id)
        except GLib.Error as exc:
            return CameraProbe(error=f"cannot open {aravis_id} ({exc.message})")
        sensor = tuple(camera.get_sensor_size())
        packet = None
        if camera.is_gv_device():
            try:
                packet = int(camera.gv_auto_packet_size())  # what the path passes, as the driver negotiates
            except GLib.Error:
                packet = int(camera.gv_get_packet_size())
        del camera
        return CameraProbe(sensor=(int(sensor[0]), int(sensor[1])), packet_size=packet)
    finally:
        lock.release()


# -- files -------------------------------------------------------------------------------
def check_calibration(config, config_path: str | None, device, probe: CameraProbe | None) -> list[Check]:
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.errors import CubelocError

    path = config.positioning.calibration
    words = ["cubeloc", "calibrate", "--camera", config.camera.source]
    if config_path or os.environ.get("CUBELOC_CONFIG"):
        words += ["--config", config_path or os.environ["CUBELOC_CONFIG"]]  # the daemon's camera settings
    words += ["--out", str(path)] + (["--force"] if Path(path).exists() else [])
    command = shlex.join(words)
    fix = ("calibrate this camera: show it the board (the default ChArUco; --board SPEC for another) "
           "until the coverage is complete")
    try:
        calibration = read_camera_info(path)
    except CubelocError as exc:
        return [Check("calibration", FAIL, str(exc), fix, command)]
    checks = []
    size = (config.camera.width, config.camera.height)
    if calibration.size != size:
        checks.append(Check("calibration", FAIL, f"{path} is for {calibration.width}x{calibration.height} images but "
                            f"the camera is set to {size[0]}x{size[1]}",
                            f"calibrate at {size[0]}x{size[1]}, or set camera.width/height to match the calibration"))
    if probe is not None and probe.sensor is not None and (size[0] > probe.sensor[0] or size[1] > probe.sensor[1]):
        checks.append(Check("calibration", FAIL, f"camera.width/height {size[0]}x{size[1]} exceed the sensor "
                            f"{probe.sensor[0]}x{probe.sensor[1]}", "set camera.width/height within the sensor"))
    serial = str(calibration.metadata.get("camera_serial") or "")
    if device is not None and device.serial and serial and serial != device.serial:
        checks.append(Check("calibration", FAIL, f"{path} was made for camera serial {serial}, the configured "
                            f"camera is serial {device.serial}", fix, command))
    elif not serial:
        checks.append(Check("calibration", WARN, f"{path} does not say which camera it is for "
                            "(no calibration.camera_serial)", "make sure it is this camera's; cubeloc calibrate records it"))
    if not any(c.level == FAIL for c in checks):
        rms = calibration.metadata.get("rms_px")
        detail = f", RMS {rms} px" if rms is not None else ""
        checks.append(Check("calibration", OK, f"{path}: {calibration.width}x{calibration.height}"
                            f"{', serial ' + serial if serial else ''}{detail}"))
    return checks


def check_target(config) -> Check:
    from cubeloc.errors import CubelocError
    from cubeloc.positioning.target import load_target

    path = config.positioning.target
    try:
        target = load_target(path)
    except CubelocError as exc:
        return Check("target", FAIL, str(exc), "correct it, or write one (cubeloc generate cube)",
                     "cubeloc generate cube --help")
    if target.cube is not None:
        what = (f"{target.family} cube {target.cube.side_m * 1000:.0f} mm, tags {target.cube.tag_size_m * 1000:.0f} mm, "
                f"ids {list(target.ids)}")
    else:
        what = f"{target.family}, {len(target.tags)} tags, ids {list(target.ids)}"
    return Check("target", OK, f"{path}: {what}")


# -- Zenoh and the service ---------------------------------------------------------------
def _probe_endpoints(settings) -> list[tuple[str, str, str]]:
    """(endpoint to try, where it came from, as configured): the connect endpoints, and the
    daemon's own listen endpoints seen from this machine (0.0.0.0 becomes 127.0.0.1)."""
    out = [(e, "connect", e) for e in settings.connect]
    for endpoint in settings.listen:
        protocol, _, rest = endpoint.partition("/")
        address = rest.split("?")[0].split("#")[0]
        host, _, port = address.rpartition(":")
        if host in ("0.0.0.0", "[::]"):
            host = "127.0.0.1" if host == "0.0.0.0" else "[::1]"
        out.append((f"{protocol}/{host}:{port}", "listen", endpoint))
    return out


def _port_free(endpoint: str) -> bool:
    """Could the daemon bind ``endpoint`` (a listen endpoint) now?"""
    protocol, _, rest = endpoint.partition("/")
    address = rest.split("?")[0].split("#")[0]
    host, _, port = address.rpartition(":")
    kind = socket.SOCK_DGRAM if protocol in ("udp", "quic") else socket.SOCK_STREAM
    family = socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET
    with socket.socket(family, kind) as probe:
        try:
            probe.bind((host.strip("[]"), int(port)))
        except OSError:
            return False
    return True


def check_zenoh(config, timeout_s: float = ZENOH_TIMEOUT_S) -> list[Check]:
    import zenoh

    from cubeloc.daemon.zenoh_session import build_zenoh_config, zenoh_error_text
    from cubeloc.errors import CubelocError

    settings = config.zenoh
    try:
        build_zenoh_config(settings)
    except CubelocError as exc:
        return [Check("zenoh", FAIL, str(exc), "correct the [zenoh] section or the Zenoh config file")]
    alive_key = f"cubeloc/{config.name}/alive"
    targets = _probe_endpoints(settings) or [("", "scouting", "")]
    checks = []
    for endpoint, origin, configured in targets:
        probe = settings.model_copy(update={"listen": (), "connect": (endpoint,) if endpoint else (),
                                            "mode": "client" if endpoint else "peer"})
        conf = build_zenoh_config(probe)
        try:
            conf.insert_json5("listen/endpoints", "[]")  # never take the daemon's port
            # The daemon's own access-control rules would filter what it sends us (its
            # liveliness token): they are the daemon's business, not this probe's.
            conf.insert_json5("access_control/enabled", "false")
            if endpoint:
                conf.insert_json5("mode", '"client"')
                conf.insert_json5("connect/timeout_ms", str(int(timeout_s * 1000)))
            session = zenoh.open(conf)
        except zenoh.ZError as exc:
            checks.append(_unreachable(endpoint, origin, configured, zenoh_error_text(exc)))
            continue
        try:
            alive = [r for r in session.liveliness().get(alive_key, timeout=timeout_s) if r.ok is not None]
        finally:
            session.close()
        if not endpoint:
            found = "found" if alive else "did not find"
            checks.append(Check("zenoh", OK if alive else WARN, f"no endpoints configured: multicast scouting {found} "
                                f"{alive_key}", "" if alive else "is the daemon running, with this name, on this LAN?"))
        elif alive:
            checks.append(Check("zenoh", OK, f"{endpoint} ({origin}): reachable, the daemon's {alive_key} is there"))
        else:
            checks.append(Check("zenoh", WARN, f"{endpoint} ({origin}): reachable, but no {alive_key}",
                                "is the daemon running with this name? systemctl status cubeloc"))
    return checks


def _unreachable(endpoint: str, origin: str, configured: str, error: str) -> Check:
    if not endpoint:
        return Check("zenoh", FAIL, f"cannot open a Zenoh session ({error})", "check the Zenoh config file")
    if origin == "listen":
        if _port_free(configured):
            return Check("zenoh", WARN, f"{endpoint} (listen): nothing listens there: the daemon is not running",
                         "start it: sudo systemctl start cubeloc")
        return Check("zenoh", FAIL, f"{endpoint} (listen): the port is taken, but not by a Zenoh peer that lets "
                     f"us in ({error})", "find the other process (ss -ltnup), or fix TLS/credentials in the Zenoh file")
    return Check("zenoh", FAIL, f"{endpoint} (connect): unreachable ({error})",
                 "check the router/peer at that address, the network, and TLS/credentials in the Zenoh file")


def check_service() -> Check:
    if shutil.which("systemctl") is None or not Path("/run/systemd/system").is_dir():
        return Check("service", WARN, "systemd is not running on this machine: the service state is not checked")
    try:
        state = subprocess.run(["systemctl", "is-active", SERVICE], capture_output=True, text=True,
                               timeout=10).stdout.strip()
        known = subprocess.run(["systemctl", "cat", SERVICE], capture_output=True, text=True, timeout=10).returncode == 0
    except (OSError, subprocess.SubprocessError) as exc:
        return Check("service", WARN, f"systemctl failed ({exc})")
    if not known:
        return Check("service", WARN, "cubeloc.service is not installed", "see systemd/README.md")
    if state == "active":
        return Check("service", OK, "cubeloc.service is active")
    if state == "activating":
        return Check("service", WARN, "cubeloc.service is starting (waiting for the camera?)",
                     "systemctl status cubeloc shows what it waits for")
    if state == "failed":
        return Check("service", FAIL, "cubeloc.service has failed",
                     "journalctl -u cubeloc -n 50 shows why; then sudo systemctl restart cubeloc")
    return Check("service", WARN, f"cubeloc.service is {state}", "sudo systemctl enable --now cubeloc")
