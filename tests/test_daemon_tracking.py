"""The daemon with the tracker (``positioning.mode = "tracker"``, the default) on the
synthetic camera in real time: target poses while the cube is in view, then ``tracking``
poses from the map after the paper's trolley has turned away from it. Half resolution
(640x512) and 5 fps keep it light on a shared machine."""

from __future__ import annotations

import threading

import numpy as np
from helpers import half_resolution

from cubeloc.calib.camera_info import write_camera_info
from cubeloc.daemon.cameras import make_camera
from cubeloc.daemon.config import Config
from cubeloc.daemon.preflight import prepare
from cubeloc.daemon.sdnotify import SystemdNotifier
from cubeloc.daemon.service import Daemon
from cubeloc.net import free_port
from cubeloc.positioning.target import default_cube_yaml

SECONDS, FPS = 9.0, 5.0  # the paper's path: the cube leaves the view after ~5 s


class Recording:
    """Builds the camera like the registry does and keeps it, for its ground truth."""

    camera = None

    def __call__(self, source, settings):
        self.camera = make_camera(source, settings)
        return self.camera


def test_tracking_poses_are_published_after_the_cube_leaves_the_view(tmp_path, listeners):  # noqa: F811
    write_camera_info(tmp_path / "camera.yaml", half_resolution())
    (tmp_path / "target.yaml").write_text(default_cube_yaml())
    port = free_port()
    source = f"synthetic:paper?seconds={SECONDS:g}&fps={FPS:g}&seed=3&realtime=1&calib={tmp_path / 'camera.yaml'}"
    prepared = prepare(Config.model_validate({
        "name": "trk",
        "camera": {"source": source, "width": 640, "height": 512},
        "positioning": {"calibration": tmp_path / "camera.yaml", "target": tmp_path / "target.yaml"},
        "zenoh": {"multicast_scouting": False, "listen": [f"tcp/127.0.0.1:{port}"]},
        "daemon": {"status_period_s": 0.25},
    }))
    assert prepared.config.positioning.mode == "tracker"
    stop, factory = threading.Event(), Recording()
    daemon = Daemon(prepared, stop, camera_factory=factory, notifier=SystemdNotifier({}))
    thread = threading.Thread(target=daemon.run, daemon=True)
    thread.start()
    assert daemon.serving.wait(30)
    listener = listeners(port)
    try:
        thread.join(SECONDS + 60)  # the finite source ends the run
    finally:
        stop.set()
        thread.join(5)
    assert not thread.is_alive()

    states = [p["state"] for p in listener.poses]
    assert states and states[0] == "target", states
    first_tracking = states.index("tracking") if "tracking" in states else None
    assert first_tracking is not None, states
    tracking = [p for p in listener.poses[first_tracking:] if p["state"] == "tracking"]
    assert len(tracking) >= 10, states  # the last ~4 s of the run, without the cube
    assert all(p["planes"] == 0 for p in tracking)
    errors_mm = [1000 * np.linalg.norm(np.array(p["position"])
                                       - factory.camera.ground_truth_at(p["stamp_ns"]).translation)
                 for p in listener.poses]
    # half resolution and 5 fps: centimetres at worst after 1.5 m away from the cube
    assert np.median(errors_mm) < 10 and max(errors_mm) < 40, errors_mm
    assert any(s["state"] == "tracking" for s in listener.status), [s["state"] for s in listener.status]
