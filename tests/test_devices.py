"""Discovery (Aravis + USB facts), camera ownership and ``cubeloc devices``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

import cubeloc.drivers.ownership as ownership
from cubeloc.drivers.base import CameraBusy, DeviceInfo
from cubeloc.drivers.discovery import merge
from cubeloc.drivers.ownership import CameraLock
from cubeloc.drivers.usb import UsbFacts, describe, is_camera, list_usb_cameras

U3V = (0xEF, 0x05)


def usb_facts(**changes) -> UsbFacts:
    facts = dict(vendor_id=0x2676, product_id=0xBA02, bcd_usb=0x0300, speed=4,
                 interfaces=(U3V, (0xEF, 0x05)), bus=2, address=7, port_path="2-1.3",
                 manufacturer="Basler", product="acA1300-200um", serial="22334455")
    facts.update(changes)
    return UsbFacts(**facts)


def test_usb3_vision_camera_on_a_usb3_link_has_no_warning():
    info = describe(usb_facts())
    assert is_camera(usb_facts())
    assert (info.device_id, info.transport, info.serial) == ("aravis:22334455", "usb3", "22334455")
    assert info.notes == ("link: USB3 SuperSpeed (5 Gb/s)",)


def test_usb3_camera_on_a_usb2_link_is_warned_about():
    info = describe(usb_facts(speed=3))
    assert any("USB3 camera on a USB2 high speed (480 Mb/s) link" in n and "USB3 port" in n for n in info.notes)


def test_permission_problem_comes_with_the_fix():
    info = describe(usb_facts(accessible=False, serial="", manufacturer="", product=""))
    note = next(n for n in info.notes if "no permission" in n)
    assert "/dev/bus/usb/002/007" in note and "99-cubeloc-cameras.rules" in note and "udevadm" in note
    assert info.vendor == "vendor 0x2676" and info.device_id == ""


def test_hikvision_without_usb3_vision_interface_is_listed_with_a_note():
    facts = usb_facts(vendor_id=0x2BDF, interfaces=((0xFF, 0x00),))
    assert is_camera(facts)
    assert any("vendor's SDK" in n for n in describe(facts).notes)
    assert not is_camera(usb_facts(vendor_id=0x046D, interfaces=((0x0E, 0x01),)))  # a webcam


def test_usb_listing_never_crashes_here():
    cameras, notes = list_usb_cameras()  # this machine may have no USB at all
    assert isinstance(cameras, list) and all(isinstance(n, str) for n in notes)


def test_merge_folds_usb_facts_into_the_aravis_entry():
    aravis = [DeviceInfo("aravis:Basler-22334455", "Basler", "acA1300", "22334455", "usb3"),
              DeviceInfo("aravis:Aravis-Fake-GV01", "Aravis", "Fake", "GV01", "gige", "127.0.0.1")]
    usb = [describe(usb_facts(speed=3)), describe(usb_facts(serial="999", accessible=False))]
    merged = merge(aravis, usb)
    assert [d.device_id for d in merged] == ["aravis:Basler-22334455", "aravis:Aravis-Fake-GV01", "aravis:999"]
    assert any("USB2" in n for n in merged[0].notes) and merged[0].address.startswith("usb 2-1.3")
    assert any("no permission" in n for n in merged[2].notes)


def test_lock_is_exclusive_and_names_the_holder_across_processes(tmp_path, monkeypatch):
    monkeypatch.setenv("CUBELOC_LOCK_DIR", str(tmp_path))
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent("""
            import logging, sys
            import structlog
            structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
            from cubeloc.drivers.ownership import CameraLock
            lock = CameraLock("Basler-22334455"); lock.acquire()
            print("held", flush=True); sys.stdin.read()
        """)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env={**os.environ})
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(CameraBusy, match=rf"camera Basler-22334455 is held by pid {holder.pid} .*'systemctl stop cubeloc' or 'kill {holder.pid}'"):
            CameraLock("Basler-22334455").acquire()
        with CameraLock("another-camera"):  # other cameras are free
            pass
    finally:
        holder.communicate("", timeout=10)
    with CameraLock("Basler-22334455") as lock:  # released when its holder exits
        assert lock.held and lock.path.read_text().startswith(f"{os.getpid()}\n")
    assert lock.path.read_text() == ""  # no stale pid left behind


def test_busy_message_names_the_cubeloc_verb():
    message = ownership.busy_message("cam", 42, "/usr/bin/python3 /opt/cubeloc/.venv/bin/cubeloc run --config x")
    assert "held by pid 42 (cubeloc run)" in message
    message = ownership.busy_message("cam", 43, "/usr/bin/python3 -m cubeloc.daemon.cli record --out d")
    assert "(cubeloc record)" in message


def test_lock_dir_falls_back_when_run_lock_is_not_usable(monkeypatch, tmp_path):
    monkeypatch.delenv("CUBELOC_LOCK_DIR", raising=False)
    monkeypatch.setattr(ownership, "SYSTEM_LOCK_DIR", tmp_path / "no-such-dir")
    monkeypatch.setattr(ownership.tempfile, "gettempdir", lambda: str(tmp_path))
    assert ownership.lock_dir() == tmp_path / "cubeloc-locks"
    with CameraLock("x") as lock:
        assert lock.path.parent == tmp_path / "cubeloc-locks"


def test_devices_cli_lists_the_fake_camera_and_exits_0(cli):
    result = cli("devices", "--fake")
    assert result.returncode == 0, result.stderr
    assert any(line.startswith("aravis:Fake_1  Aravis Fake  serial 1  fake") for line in result.stdout.splitlines())
    result = cli("devices", "--fake", "--json")
    entries = [json.loads(line) for line in result.stdout.splitlines() if line.startswith("{")]
    assert {"device_id": "aravis:Fake_1", "transport": "fake"}.items() <= entries[0].items()


def test_devices_cli_without_cameras_says_so(cli):
    result = cli("devices")
    assert result.returncode == 0 and "Traceback" not in result.stderr
    # Whatever is plugged in here: either a line per camera or the "no cameras" line.
    assert result.stdout.strip(), result.stderr
    assert "no cameras found" in result.stdout or result.stdout.startswith(("aravis:", "note:", "("))
