"""The Aravis backend against Aravis' own fake cameras: the in-process Fake interface and the
GigE Vision fake on 127.0.0.1 (real GVCP/GVSP packets over loopback)."""

from __future__ import annotations

import contextlib
import os
import threading
import time

import numpy as np
import pytest

from cubeloc.drivers.aravis_camera import AravisCamera
from cubeloc.drivers.base import (
    CameraBusy,
    CameraNotFound,
    CameraSettings,
    FeatureNotSupported,
    FrameTimeout,
    StreamBroken,
)
from cubeloc.drivers.fake_gige import GvFake
from cubeloc.drivers.genicam import probe_features
from cubeloc.drivers.reconnect import reopen_with_backoff


@pytest.fixture(autouse=True)
def private_lock_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("CUBELOC_LOCK_DIR", str(tmp_path / "locks"))


@pytest.fixture
def gv_fake():
    fake = GvFake("GV01").start()
    yield fake
    fake.stop()


def test_the_gige_tests_cannot_see_or_reach_a_network_beyond_loopback(gv_fake):
    """make test runs these in a network namespace with loopback alone: Aravis' discovery
    broadcasts on every interface it sees, and here it sees only lo; a broadcast or a
    packet to another host cannot leave."""
    import socket

    assert [name for _, name in socket.if_nameindex()] == ["lo"]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        for destination in (("255.255.255.255", 3956), ("192.0.2.1", 3956)):  # GVCP discovery, TEST-NET-1
            with pytest.raises(OSError, match="unreachable"):
                probe.sendto(b"\x42\x11\x00\x02\x00\x00\x00\x01", destination)
    assert gv_fake.process.poll() is None  # and the fake camera runs there, on lo


def grab(camera, n, timeout_s=2.0):
    return [camera.next_frame(timeout_s) for _ in range(n)]


def test_fake_interface_grabs_1280x1024_mono8():
    with AravisCamera("Fake_1", CameraSettings(frame_rate_hz=25)) as camera:
        assert camera.info.transport == "fake"
        camera.start()
        frames = grab(camera, 5)
        camera.stop()
    for frame in frames:
        assert frame.image.shape == (1024, 1280) and frame.image.dtype == np.uint8
        assert frame.image.flags.c_contiguous
        assert frame.stamp_ns <= time.time_ns()
    ids = [f.frame_id for f in frames]
    assert all(np.diff(ids) > 0)
    assert camera.stats.frame_id_gaps == ids[-1] - ids[0] - 4  # 0 unless the host stalled
    assert all(np.diff([f.stamp_ns for f in frames]) > 0)
    assert np.ptp(frames[0].image) > 0  # a real test pattern, not a blank buffer
    assert camera.stats.delivered == 5 and camera.stats.incomplete == camera.stats.bad_timestamp == 0


def test_a_16_bit_stream_arrives_as_its_top_8_bits():
    """``pixel_format = "Mono16"`` (Aravis' fake offers it; Mono10/12 are read the same way,
    two bytes a pixel): Mono8 frames of the stream's top 8 bits, and the camera says which
    format it streams. A format it lacks is refused by name, with those it has."""
    with AravisCamera("Fake_1", CameraSettings(frame_rate_hz=25, pixel_format="Mono16")) as camera:
        assert camera.read_settings().pixel_format == "Mono16"
        camera.start()
        frames = grab(camera, 3)
    for frame in frames:
        assert frame.image.shape == (1024, 1280) and frame.image.dtype == np.uint8 and np.ptp(frame.image) > 0
    with (pytest.raises(FeatureNotSupported, match=r"no PixelFormat Mono12 \(it offers .*Mono16"),
          AravisCamera("Fake_1", CameraSettings(pixel_format="Mono12")) as camera):
        camera.start()


def test_software_trigger_gives_one_frame_per_request():
    with AravisCamera("Fake_1", CameraSettings(trigger="software")) as camera:
        camera.start()
        frames = grab(camera, 3)
    assert len({f.frame_id for f in frames}) == 3


def test_gv_fake_settings_round_trip(gv_fake):
    wanted = CameraSettings(width=1280, height=1024, offset_x=0, offset_y=0, exposure_us=5000.0,
                            gain_db=3.0, frame_rate_hz=40.0)
    with AravisCamera("127.0.0.1", wanted) as camera:
        assert camera.read_settings() == wanted
        assert (camera.info.transport, camera.info.serial) == ("gige", "GV01")
        assert camera.features.get("exposure") == "ExposureTimeAbs"  # probed, not assumed
        camera.start()
        frame = camera.next_frame(2.0)
        assert frame.image.shape == (1024, 1280) and frame.exposure_us == 5000.0
    # A region with an offset, opened by serial this time.
    offset = CameraSettings(width=640, height=480, offset_x=64, offset_y=32, exposure_us=8000.0)
    with AravisCamera("GV01", offset) as camera:
        got = camera.read_settings()
        assert (got.width, got.height, got.offset_x, got.offset_y, got.exposure_us) == (640, 480, 64, 32, 8000.0)
        camera.start()
        assert camera.next_frame(2.0).image.shape == (480, 640)


def test_unsupported_settings_name_the_feature(gv_fake):
    with pytest.raises(FeatureNotSupported, match=r"region 4096x4096\+0\+0 does not fit"):
        AravisCamera(gv_fake.device_id, CameraSettings(width=4096, height=4096)).open()
    with pytest.raises(FeatureNotSupported, match="exposure_us = 1e-05 is outside"):
        AravisCamera(gv_fake.device_id, CameraSettings(exposure_us=1e-5)).open()
    # The failed opens released the camera.
    with AravisCamera(gv_fake.device_id, CameraSettings()) as camera:
        assert camera.info.serial == "GV01"


def test_missing_features_are_named():
    class Device:
        def __init__(self, features):
            self.features = features

        def is_feature_available(self, name):
            return name in self.features

    old_basler = probe_features(Device({"AcquisitionFrameRateAbs", "ExposureTimeAbs", "GainRaw"}), "cam7")
    assert old_basler.get("frame_rate") == "AcquisitionFrameRateAbs"
    assert old_basler.get("exposure") == "ExposureTimeAbs"
    sfnc = probe_features(Device({"AcquisitionFrameRate", "AcquisitionFrameRateAbs", "TriggerMode"}), "cam8")
    assert sfnc.get("frame_rate") == "AcquisitionFrameRate"
    with pytest.raises(FeatureNotSupported, match="camera cam8 does not offer TriggerSoftware.*trigger = 'software'"):
        sfnc.require("trigger_software", "trigger = 'software'")


def test_second_opener_is_told_who_holds_the_camera(gv_fake):
    with AravisCamera("127.0.0.1", CameraSettings()) as first:
        first.start()
        with pytest.raises(CameraBusy, match=rf"camera {gv_fake.device_id} is held by pid {os.getpid()}"):
            AravisCamera("GV01", CameraSettings()).open()
        first.next_frame(2.0)  # the holder is undisturbed


def test_the_lock_keeps_its_name_when_a_reconnect_reaches_the_camera_by_address(gv_fake, monkeypatch):
    """The daemon makes a new camera object on each reconnect; a camera just plugged back
    in may miss the discovery broadcast and be opened by its IP address, where it names
    itself "GV01" rather than discovery's "Aravis-Fake-GV01". One camera, one lock: a
    second opener is still told who holds it (before: it got past the lock and failed on
    a register write timeout)."""
    import cubeloc.drivers.aravis_camera as backend

    with AravisCamera("127.0.0.1", CameraSettings()) as first:  # discovered
        first.start()
        first.next_frame(2.0)
        lock_file = first._lock.path
    monkeypatch.setattr(backend, "list_aravis_devices", lambda include_fake=False: [])  # discovery misses it
    with AravisCamera("127.0.0.1", CameraSettings()) as again:
        again.start()
        again.next_frame(2.0)
        assert again._lock.path == lock_file
        monkeypatch.undo()
        monkeypatch.setenv("CUBELOC_LOCK_DIR", str(lock_file.parent))
        with pytest.raises(CameraBusy, match=rf"camera {gv_fake.device_id} is held by pid {os.getpid()}"):
            AravisCamera(gv_fake.device_id, CameraSettings()).open()
        again.next_frame(2.0)


def test_unknown_camera_lists_what_was_found(gv_fake):
    with pytest.raises(CameraNotFound, match=rf"no camera 'nope'.*found: .*{gv_fake.device_id}"):
        AravisCamera("nope", CameraSettings()).open()


def test_gv_fake_restarted_mid_stream_and_the_backend_recovers(gv_fake):
    settings = CameraSettings(exposure_us=5000.0, frame_rate_hz=50.0)  # the fake's default is 10 ms
    camera = AravisCamera("127.0.0.1", settings, watchdog_s=1.0)
    camera.open()
    camera.start()
    grab(camera, 3)
    gv_fake.stop()  # the camera vanishes mid-stream
    deadline = time.monotonic() + 15
    with pytest.raises(StreamBroken, match="no frame for|control lost"):
        while time.monotonic() < deadline:
            with contextlib.suppress(FrameTimeout):
                camera.next_frame(0.5)
    restarter = threading.Timer(1.0, gv_fake.start)  # power comes back a second later
    restarter.start()
    try:
        assert reopen_with_backoff(camera, give_up_after_s=30, first_delay_s=0.2)
        frames = grab(camera, 5)
        assert camera.read_settings().exposure_us == 5000.0  # settings restored
        assert all(f.exposure_us == 5000.0 for f in frames)
        assert camera.stats.reconnects == 1 and camera.stats.delivered == 8
        assert camera.info.device_id == f"aravis:{gv_fake.device_id}"  # same device, same lock
    finally:
        restarter.join()
        camera.close()


def test_frame_id_gaps_counted_when_frames_are_lost(gv_fake):
    # Two buffers and a consumer slower than the camera: Aravis has nowhere to put most
    # frames, so the camera's frame ids jump; the backend counts the frames never seen.
    # (How many are lost depends on how fast the fake camera runs on a busy machine: 6
    # gaps in 8 frames under the suite's load, 30 on an idle one. So frames are read until
    # some are lost, 20 s at most, and every id missing from the span must be counted.)
    with AravisCamera(gv_fake.device_id, CameraSettings(frame_rate_hz=50.0), buffers=2) as camera:
        camera.start()
        ids = []
        deadline = time.monotonic() + 20.0
        while len(ids) < 8 or (camera.stats.frame_id_gaps == 0 and time.monotonic() < deadline):
            ids.append(camera.next_frame(2.0).frame_id)
            time.sleep(0.1)
        stats = camera.stats
    span = ids[-1] - ids[0] + 1
    detail = f"ids {ids}, {stats}"
    assert stats.frame_id_gaps > 0, detail
    assert stats.delivered + stats.frame_id_gaps <= span <= stats.delivered + stats.frame_id_gaps + stats.incomplete, detail


def test_reconnect_gives_up_at_its_deadline_and_stops_on_request(gv_fake):
    camera = AravisCamera(gv_fake.device_id, CameraSettings(), watchdog_s=1.0)
    camera.open()
    camera.start()
    camera.next_frame(2.0)
    gv_fake.stop()  # and it never comes back
    time.sleep(1.2)  # past the watchdog: closing does not wait for the dead camera
    with pytest.raises(StreamBroken, match=rf"camera aravis:{gv_fake.device_id} did not come back within 2 s"):
        reopen_with_backoff(camera, give_up_after_s=2.0, first_delay_s=0.2)
    stop = threading.Event()
    threading.Timer(0.5, stop.set).start()
    assert reopen_with_backoff(camera, stop=stop, first_delay_s=0.2) is False  # shutdown wins
    assert camera.stats.reconnects == 0
    camera.close()

