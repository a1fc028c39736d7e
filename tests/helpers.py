"""Small helpers the test modules share (import as ``from helpers import ...``, like gv_fake)."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(predicate: Callable[[], object], timeout_s: float = 30.0, poll_s: float = 0.05) -> bool:
    """Poll ``predicate`` until it is true (True) or ``timeout_s`` has passed (False)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return False


def half_resolution():
    """The paper's camera at 640x512 (fx 833 px): the tracker tests' camera, 4x cheaper to
    render and track than the full 1280x1024 the bench uses."""
    from calib.camera_info import CameraCalibration, paper_camera

    full = paper_camera()
    k = full.camera_matrix.copy()
    k[:2] /= 2.0
    k[0, 2], k[1, 2] = (640 - 1) / 2.0, (512 - 1) / 2.0
    return CameraCalibration(640, 512, k, full.distortion, "plumb_bob", "half")
