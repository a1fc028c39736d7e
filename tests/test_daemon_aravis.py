"""``cubeloc run`` against Aravis' GigE Vision fake camera on 127.0.0.1: the camera is
stopped and restarted under the running daemon, which reconnects and keeps publishing
``status`` all along."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from gv_fake import FAKE_GV_CAMERA, GvFake
from helpers import wait_until

from cubeloc.calib.camera_info import paper_camera, write_camera_info
from cubeloc.net import free_port
from cubeloc.positioning.target import default_cube_yaml

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(shutil.which(FAKE_GV_CAMERA) is None, reason=f"{FAKE_GV_CAMERA} not installed (aravis-tools)")


def test_daemon_reconnects_when_the_gige_camera_restarts(tmp_path):
    import zenoh

    port = free_port()
    write_camera_info(tmp_path / "camera.yaml", paper_camera())
    (tmp_path / "target.yaml").write_text(default_cube_yaml())
    config = tmp_path / "cubeloc.toml"
    config.write_text(
        'name = "gige"\n'
        '[camera]\nsource = "aravis:127.0.0.1"\nexposure_us = 5000.0\nframe_rate_hz = 20.0\nframe_timeout_s = 0.5\n'
        f'[positioning]\ncalibration = "{tmp_path / "camera.yaml"}"\ntarget = "{tmp_path / "target.yaml"}"\n'
        f'[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
        "[daemon]\nreconnect_initial_s = 0.2\nreconnect_max_s = 1.0\n"
        '[logging]\nformat = "json"\n'
    )
    fake = GvFake("GV07").start()
    env = {"CUBELOC_LOCK_DIR": str(tmp_path / "locks")}
    daemon = subprocess.Popen(
        [sys.executable, "-m", "cubeloc.daemon.cli", "run", "--config", str(config)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
        env={**os.environ, **env},
    )
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    status: list[tuple[float, dict]] = []
    try:
        with zenoh.open(conf) as session:
            session.declare_subscriber(
                "cubeloc/gige/status", lambda s: status.append((time.monotonic(), json.loads(s.payload.to_bytes())))
            )

            def streaming_with_frames(reconnects: int) -> bool:
                return any(d["camera"]["state"] == "streaming" and d["camera"]["reconnects"] >= reconnects
                           and d["frames"] > 0 and d["fps"] > 0 for _, d in status[-2:])

            assert wait_until(lambda: streaming_with_frames(0), 60), status[-1:]
            assert status[-1][1]["camera"]["serial"] == "GV07"
            frames_before = status[-1][1]["frames"]
            fake.stop()  # the camera vanishes
            assert wait_until(lambda: status[-1][1]["state"] == "reconnecting", 30), status[-1:]
            lost_at = len(status)
            # it stays away a while: status must keep coming meanwhile (two more, however
            # slow the machine)
            assert wait_until(lambda: len(status) - lost_at >= 2, 30), status[-1:]
            assert all(d["state"] == "reconnecting" for _, d in status[lost_at:]), [d["state"] for _, d in status]
            fake.start()  # power is back
            assert wait_until(lambda: streaming_with_frames(1), 60), status[-1:]
            assert status[-1][1]["frames"] > frames_before
            assert status[-1][1]["camera"]["serial"] == "GV07"  # the same camera, back
            # status never paused for long, before, during or after the outage
            times = [t for t, _ in status]
            assert max(b - a for a, b in zip(times, times[1:], strict=False)) < 4.0
            assert daemon.poll() is None
    finally:
        daemon.send_signal(signal.SIGTERM)
        try:
            out, err = daemon.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            daemon.kill()
            out, err = daemon.communicate()
        fake.stop()
    assert daemon.returncode == 0, err[-2000:]
    events = [json.loads(line)["event"] for line in out.splitlines() if line.startswith("{")]
    assert "camera lost, reconnecting" in events and events.count("camera streaming") >= 2
