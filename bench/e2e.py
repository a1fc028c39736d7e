"""End to end: capture -> daemon -> Zenoh -> a subscriber process, at 1280x1024.

The real daemon (daemon/service.py: capture thread, newest-frame slot, target-pose
processor, Zenoh publisher) runs in this process. Its camera plays pre-rendered
1280x1024 frames of the cube (the synthetic camera's renderer is slower than a real
camera, so frames are rendered first) at a fixed rate, stamping each with the host clock
when it is delivered, as a real camera's driver does. A separate subscriber process
connected over loopback TCP notes when each pose arrives: latency = arrival - stamp_ns.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bench.common import markdown_table
from cubeloc.net import free_port

TITLE = "End to end: capture -> subscriber latency and sustained frame rate (1280x1024)"

RUN_SECONDS = 10.0
RATES_HZ = (10.0, 30.0, 100.0)  # the paper's rate, a typical industrial camera, flat out
FRAMES = 24

SUBSCRIBER = r"""
import json, sys, time, zenoh
conf = zenoh.Config()
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
def on_pose(sample):
    now = time.time_ns()
    doc = json.loads(sample.payload.to_bytes())
    print(doc["stamp_ns"], now, flush=True)
with zenoh.open(conf) as session:
    session.declare_subscriber("cubeloc/bench/pose", on_pose)
    print("ready", flush=True)
    sys.stdin.read()  # until the bench closes our stdin
"""


class PacedFrames:
    """A camera (the drivers.base protocol) that loops over frames at ``rate_hz``."""

    def __init__(self, images: list[np.ndarray], rate_hz: float) -> None:
        from cubeloc.drivers.base import CaptureStats, DeviceInfo

        self._images, self._period_s = images, 1.0 / rate_hz
        self.info = DeviceInfo("bench", "cubeloc", "paced frames", "0", "synthetic")
        self.settings = None
        self.stats = CaptureStats()
        self._next = 0.0
        self._index = 0

    def open(self) -> None: ...

    def start(self) -> None:
        self._next = time.monotonic()

    def next_frame(self, timeout_s: float):
        from cubeloc.drivers.base import Frame, FrameTimeout

        wait = self._next - time.monotonic()
        if wait > timeout_s:
            time.sleep(timeout_s)
            raise FrameTimeout("bench: next frame not due yet")
        if wait > 0:
            time.sleep(wait)
        # Like a camera: frames due while we were busy are gone (counted), not queued.
        now = time.monotonic()
        missed = int((now - self._next) / self._period_s)
        self.stats.frame_id_gaps += missed
        self._next += (missed + 1) * self._period_s
        self._index += 1 + missed
        self.stats.delivered += 1
        stamp = time.time_ns()
        image = self._images[self._index % len(self._images)]
        return Frame(image, self._index, stamp, stamp, 5000.0)

    def stop(self) -> None: ...

    def close(self) -> None: ...


def render_frames() -> list[np.ndarray]:
    from cubeloc.fakes import render_view
    from cubeloc.fakes.trajectories import make_trajectory

    trajectory = make_trajectory("orbit", seconds=FRAMES / 10.0, fps=10.0)
    return [render_view(p.T_world_camera, seed=i, noise_sigma=2.0) for i, p in enumerate(trajectory)]


def start_daemon(images: list[np.ndarray], rate_hz: float, workdir: Path, **sections):
    """The real daemon in this process on ``images`` played at ``rate_hz``, Zenoh on a
    loopback port, ``sections`` added to its config. Returns (daemon, stop, thread,
    camera, Zenoh endpoint)."""
    from cubeloc.calib.camera_info import paper_camera, write_camera_info
    from cubeloc.daemon.config import Config
    from cubeloc.daemon.logs import configure_logging
    from cubeloc.daemon.preflight import prepare
    from cubeloc.daemon.service import Daemon
    from cubeloc.positioning.target import default_cube_yaml

    configure_logging("warning", "console", stream=sys.stderr)
    write_camera_info(workdir / "camera.yaml", paper_camera())
    (workdir / "target.yaml").write_text(default_cube_yaml())
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = Config.model_validate({
        "name": "bench",
        "camera": {"source": "synthetic:orbit"},  # checked by preflight; PacedFrames streams
        "positioning": {"calibration": workdir / "camera.yaml", "target": workdir / "target.yaml"},
        "zenoh": {"listen": [endpoint], "multicast_scouting": False},
        **sections,
    })
    stop = threading.Event()
    camera = PacedFrames(images, rate_hz)
    daemon = Daemon(prepare(config), stop, camera_factory=lambda source, settings: camera)
    thread = threading.Thread(target=daemon.run, daemon=True)
    thread.start()
    return daemon, stop, thread, camera, endpoint


def measure(images: list[np.ndarray], rate_hz: float, workdir: Path) -> dict:
    daemon, stop, thread, camera, endpoint = start_daemon(images, rate_hz, workdir)
    subscriber = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, endpoint], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True)
    assert subscriber.stdout.readline().strip() == "ready"
    time.sleep(2.0)  # warm-up: the detector's first full-frame passes, the connection
    frames_before, started = daemon.stats.frames, time.monotonic()
    time.sleep(RUN_SECONDS)
    frames = daemon.stats.frames - frames_before
    elapsed = time.monotonic() - started
    stop.set()
    thread.join(5.0)
    produced = camera.stats.delivered + camera.stats.frame_id_gaps  # what the camera made
    out, _ = subscriber.communicate(input="", timeout=10)
    arrivals = [tuple(int(v) for v in line.split()) for line in out.splitlines() if line.strip()]
    latencies_ms = np.array([(now - stamp) / 1e6 for stamp, now in arrivals[len(arrivals) // 5:]])
    return {
        "rate_hz": rate_hz,
        "fps": frames / elapsed,
        "poses": daemon.stats.poses,
        "received": len(arrivals),
        "processed_share": daemon.stats.frames / max(1, produced),
        "p50": float(np.percentile(latencies_ms, 50)) if latencies_ms.size else float("nan"),
        "p99": float(np.percentile(latencies_ms, 99)) if latencies_ms.size else float("nan"),
    }


def run() -> str:
    images = render_frames()
    rows = []
    with tempfile.TemporaryDirectory(prefix="cubeloc-bench-e2e-") as tmp:
        for rate in RATES_HZ:
            r = measure(images, rate, Path(tmp))
            print(json.dumps(r), flush=True)
            rows.append([
                f"{r['rate_hz']:g}", f"{r['fps']:.1f}", f"{r['p50']:.1f}", f"{r['p99']:.1f}",
                f"{r['received']}/{r['poses']}", f"{100 * (1 - r['processed_share']):.0f}%",
            ])
    table = markdown_table(
        ["camera rate (Hz)", "processed (frames/s)", "latency p50 (ms)", "latency p99 (ms)",
         "poses received/published", "frames dropped"],
        rows,
    )
    return (
        table
        + f"\nThe daemon in-process on pre-rendered 1280x1024 frames of the cube ({FRAMES} views of the "
        "`orbit` trajectory, three faces in view) played at each camera rate for "
        f"{RUN_SECONDS:g} s after a 2 s warm-up; latency is from the frame's capture stamp (host "
        "clock at delivery by the camera) to its arrival in a separate subscriber process over "
        "loopback TCP, first fifth of arrivals excluded. Dropped: the share of the camera's "
        "frames never processed, because a newer one replaced it in the newest-frame queue "
        "or it was due while the capture thread was busy (never a backlog).\n"
    )


if __name__ == "__main__":  # pragma: no cover
    print(run())
