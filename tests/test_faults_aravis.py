"""Camera faults at the Aravis driver boundary under the running daemon (in-process, real
Zenoh-free status reports), on Aravis' GigE Vision fake camera (real GVCP/GVSP packets on
127.0.0.1): incomplete buffers (the stream hands back buffers whose status is not SUCCESS,
as with lost packets), and a USB unplug as Aravis reports it (the device's ``control-lost``
signal, which a USB3 Vision device emits when libusb loses it). The GigE fake stopped and
restarted under ``cubeloc run`` is test_daemon_aravis.py; the backend alone,
test_aravis_camera.py. Only one GigE Vision fake can own 127.0.0.1:3956: ``GvFake.start``
waits for the port, so these tests never overlap with the others that use it."""

from __future__ import annotations

import shutil
import threading

import pytest
from helpers import wait_until

from cubeloc.daemon.preflight import prepare_on_loopback
from cubeloc.daemon.sdnotify import SystemdNotifier
from cubeloc.daemon.service import Daemon
from cubeloc.drivers.aravis_camera import AravisCamera
from cubeloc.drivers.fake_gige import FAKE_GV_CAMERA, GvFake
from cubeloc.net import free_port

pytestmark = pytest.mark.skipif(shutil.which(FAKE_GV_CAMERA) is None, reason=f"{FAKE_GV_CAMERA} not installed (aravis-tools)")


class StreamWithBadBuffers:
    """The real Aravis stream, except that the next ``bad`` buffers it hands back carry
    the status ``status`` (MISSING_PACKETS by default: their data is the frame's, only the
    status is what a lossy link, or SIZE_MISMATCH what a wrong setting, gives)."""

    def __init__(self, stream, Aravis) -> None:
        self._stream, self._Aravis = stream, Aravis
        self.bad = 0
        self.marked = 0
        self.status = Aravis.BufferStatus.MISSING_PACKETS

    def __getattr__(self, name):
        return getattr(self._stream, name)

    def timeout_pop_buffer(self, timeout_us):
        buffer = self._stream.timeout_pop_buffer(timeout_us)
        if buffer is None or self.bad <= 0:
            return buffer
        self.bad -= 1
        self.marked += 1
        return BadBuffer(buffer, self.status)

    def push_buffer(self, buffer):
        self._stream.push_buffer(buffer.buffer if isinstance(buffer, BadBuffer) else buffer)


class BadBuffer:
    def __init__(self, buffer, status) -> None:
        self.buffer, self._status = buffer, status

    def __getattr__(self, name):
        return getattr(self.buffer, name)

    def get_status(self):
        return self._status


class FaultyAravisCamera(AravisCamera):
    """The real backend; after each open its stream is wrapped (see above)."""

    cameras: list[FaultyAravisCamera] = []

    def open(self) -> None:
        super().open()
        from cubeloc.drivers.aravis_camera import _aravis

        Aravis, _ = _aravis()
        self._stream = StreamWithBadBuffers(self._stream, Aravis)
        FaultyAravisCamera.cameras.append(self)

    def unplug_usb(self) -> None:
        """What Aravis does when a USB3 Vision device vanishes: emit control-lost."""
        self._camera.get_device().emit("control-lost")


def thread_names() -> list[str]:
    return sorted(t.name for t in threading.enumerate())


def test_incomplete_buffers_and_usb_unplug_at_the_aravis_boundary(tmp_path, monkeypatch):
    monkeypatch.setenv("CUBELOC_LOCK_DIR", str(tmp_path / "locks"))
    fake = GvFake("GV08").start()
    prepared = prepare_on_loopback(tmp_path, free_port(), "aravisfaults", camera={"width": 1280, "height": 1024},
                                   logging={"level": "warning"})
    config = prepared.config.model_copy(update={
        "camera": prepared.config.camera.model_copy(update={
            "source": "aravis:127.0.0.1", "exposure_us": 5000.0, "frame_rate_hz": 20.0, "frame_timeout_s": 0.5}),
    })
    prepared = type(prepared)(config, prepared.calibration, prepared.calibration_yaml, prepared.target)
    FaultyAravisCamera.cameras = []
    stop = threading.Event()
    daemon = Daemon(prepared, stop, notifier=SystemdNotifier({}),
                    camera_factory=lambda source, settings: FaultyAravisCamera(source.partition(":")[2], settings))
    outcome = {}
    runner = threading.Thread(target=lambda: outcome.setdefault("code", daemon.run()), daemon=True)
    try:
        runner.start()
        assert wait_until(lambda: daemon.report().camera.state == "streaming" and daemon.stats.frames >= 3)
        threads_before = thread_names()
        camera = FaultyAravisCamera.cameras[-1]

        # Incomplete buffers: dropped and counted by the driver, the stream goes on.
        frames = daemon.stats.frames
        camera._stream.bad = 3
        assert wait_until(lambda: camera._stream.marked == 3 and daemon.stats.frames >= frames + 5)
        report = daemon.report()
        assert report.extra["faults"]["camera_incomplete"] == 3
        assert report.camera.dropped >= 3 and report.camera.state == "streaming"
        # ...and by cause: a cable (missing packets) told apart from a setting (size mismatch)
        from cubeloc.drivers.aravis_camera import _aravis

        camera._stream.status = _aravis()[0].BufferStatus.SIZE_MISMATCH
        camera._stream.bad = 2
        assert wait_until(lambda: camera._stream.marked == 5 and daemon.stats.frames >= frames + 8)
        faults = daemon.report().extra["faults"]
        assert faults["camera_incomplete_missing_packets"] == 3 and faults["camera_incomplete_size_mismatch"] == 2
        assert faults["camera_incomplete"] == 5

        # A USB unplug as Aravis reports it; the device is back at once (replugged).
        camera.unplug_usb()
        assert wait_until(lambda: daemon.report().camera.reconnects == 1 and daemon.report().camera.state == "streaming")
        frames = daemon.stats.frames
        assert wait_until(lambda: daemon.stats.frames >= frames + 5)  # frames flow again
        assert len(FaultyAravisCamera.cameras) == 2  # a fresh camera object, same device
        assert FaultyAravisCamera.cameras[-1].info.serial == "GV08"
        # the counts survive the reconnect (a restarted stream may lose its first frame
        # too); the dead camera's objects were released
        old, new = FaultyAravisCamera.cameras
        assert old.stats.incomplete >= 5
        assert daemon.report().extra["faults"]["camera_incomplete"] == old.stats.incomplete + new.stats.incomplete
        assert wait_until(lambda: thread_names() == threads_before, 20), (threads_before, thread_names())
        assert daemon.stats.poses == 0  # the fake's test pattern has no cube: no pose, and none wrong
    finally:
        stop.set()
        runner.join(10)
        fake.stop()
    assert not runner.is_alive() and outcome.get("code") == 0
