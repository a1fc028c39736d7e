"""``cubeloc devices``: every camera found (Aravis: GigE and USB3 Vision; USB facts), one a line.

Notes (a USB3 camera on a USB2 link, a device without permission, and their fixes) follow
the camera they concern, indented. With no camera it says so and exits 0.
"""

from __future__ import annotations


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "devices",
        help="list cameras (GigE Vision, USB3 Vision; USB link speed and permission problems)",
        description="List the cameras Aravis and libusb find, one per line: the source to give "
        "--camera / camera.source, vendor, model, serial, transport, address.",
    )
    parser.add_argument("--fake", action="store_true", help="also list Aravis' built-in fake camera")
    parser.add_argument("--json", action="store_true", help="one JSON object per camera")
    parser.set_defaults(func=run)


def run(args) -> int:
    import dataclasses
    import json
    import sys

    from cubeloc.daemon.logs import configure_logging
    from cubeloc.drivers.discovery import discover

    configure_logging("warning", stream=sys.stderr)

    found = discover(include_fake=args.fake)
    for note in found.notes:
        print(f"note: {note}")
    if args.json:
        for device in found.devices:
            print(json.dumps(dataclasses.asdict(device)))
        return 0
    if not found.devices:
        print("no cameras found (GigE Vision: same subnet and powered? USB: plugged in and "
              "permitted? see 'USB permissions' in docs/cameras.md)")
        return 0
    for device in found.devices:
        source = device.device_id or "(not openable)"
        print(f"{source}  {device.vendor} {device.model}  serial {device.serial or '?'}  "
              f"{device.transport}  {device.address}".rstrip())
        for note in device.notes:
            print(f"    {note}")
    return 0
