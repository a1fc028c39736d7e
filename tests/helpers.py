"""Small helpers the test modules share (import as ``from helpers import ...``, like gv_fake)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable

# A Zenoh router in a process of its own, listening on the endpoint given as its argument.
ROUTER = """
import json, sys, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"router"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("listen/endpoints", json.dumps([sys.argv[1]]))
session = zenoh.open(conf)
print("ready", flush=True)
sys.stdin.read()
"""


def helper_process(script: str, endpoint: str) -> subprocess.Popen:
    """``script`` in a Python process of its own with ``endpoint`` as its argument; returns
    once it printed "ready"; it runs until its stdin closes (``end_process``)."""
    process = subprocess.Popen([sys.executable, "-c", script, endpoint], stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "ready"
    return process


def end_process(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGCONT)
        process.kill()
    process.wait(10)


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
    from cubeloc.fakes.lenses import lens_calibration

    return lens_calibration("paper_half")


class Listener:
    """A second Zenoh session, as a subscriber on the robot would have."""

    def __init__(self, port: int) -> None:
        import json

        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        self.session = zenoh.open(conf)
        self.poses, self.status, self.base_poses = [], [], []
        self.session.declare_subscriber("cubeloc/*/pose", lambda s: self.poses.append(json.loads(s.payload.to_bytes())))
        self.session.declare_subscriber("cubeloc/*/base_pose",
                                        lambda s: self.base_poses.append(json.loads(s.payload.to_bytes())))
        self.session.declare_subscriber("cubeloc/*/status", lambda s: self.status.append(json.loads(s.payload.to_bytes())))

    def wait_for(self, predicate, timeout_s=20.0):
        return wait_until(predicate, timeout_s)

    def query(self, key):
        return [r.ok.payload.to_bytes() for r in self.session.get(key, timeout=5.0) if r.ok is not None]

    def alive(self):
        return [str(r.ok.key_expr) for r in self.session.liveliness().get("cubeloc/*/alive", timeout=2.0) if r.ok is not None]
