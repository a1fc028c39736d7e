"""End to end, as on a robot: ``cubeloc run`` on the synthetic camera in one process, the
README's subscriber example in another, a real Zenoh session on loopback between them,
and systemd's notify socket bound in a temporary directory."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
from helpers import wait_until

from cubeloc.calib.camera_info import paper_camera, write_camera_info
from cubeloc.fakes.trajectories import make_trajectory
from cubeloc.net import free_port
from cubeloc.positioning.target import default_cube_yaml

REPO = Path(__file__).resolve().parents[1]
SECONDS, FPS = 3.0, 5.0  # the start of the paper's path: the cube in view, ~2.3 m away


def write_config(tmp_path, port: int) -> str:
    write_camera_info(tmp_path / "camera.yaml", paper_camera())
    (tmp_path / "target.yaml").write_text(default_cube_yaml())
    config = tmp_path / "cubeloc.toml"
    config.write_text(
        'name = "e2e"\n'
        "[camera]\n"
        f'source = "synthetic:paper?seconds={SECONDS:g}&fps={FPS:g}&seed=3&loop=1"\n'
        "[positioning]\n"
        f'calibration = "{tmp_path / "camera.yaml"}"\ntarget = "{tmp_path / "target.yaml"}"\n'
        "[zenoh]\n"
        f'mode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
        "[logging]\n"
        'format = "json"\n'
    )
    return str(config)


def test_synthetic_camera_to_subscriber_process(tmp_path):
    port = free_port()
    config = write_config(tmp_path, port)
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify.sock"))
    notify.settimeout(90)
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify.sock"), "PYTHONUNBUFFERED": "1"}
    daemon = subprocess.Popen(
        [sys.executable, "-m", "cubeloc.daemon.cli", "run", "--config", config],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO,
    )
    notes: list[str] = []

    def read_notifications() -> None:
        # Drain the socket as systemd would (the daemon never blocks on it either way).
        with contextlib.suppress(OSError):
            while True:
                notes.append(notify.recv(4096).decode())

    reader = threading.Thread(target=read_notifications, daemon=True)
    reader.start()
    try:
        subscriber = subprocess.run(
            [sys.executable, str(REPO / "examples" / "subscriber.py"),
             "--connect", f"tcp/127.0.0.1:{port}", "--count", "12", "--timeout", "150"],
            capture_output=True, text=True, timeout=180,
        )
        daemon.send_signal(signal.SIGTERM)
        out, err = daemon.communicate(timeout=10)
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.communicate()
        notify.close()
    assert daemon.returncode == 0, err[-2000:]
    assert any(n.startswith("READY=1") for n in notes) and "STOPPING=1\nSTATUS=stopping" in notes, notes
    assert subscriber.returncode == 0, subscriber.stderr
    lines = subscriber.stdout.split("\n")[:-1]
    assert len(lines) == 12, subscriber.stdout

    truth = make_trajectory("paper", SECONDS, FPS)
    period_ns = truth[1].stamp_ns - truth[0].stamp_ns
    errors_mm = []
    for line in lines:
        seconds, *values = line.split()
        whole, frac = seconds.split(".")
        stamp_ns = int(whole) * 10**9 + int(frac)
        # The stamp is the frame's capture time: exactly on the camera's frame grid.
        k, remainder = divmod(stamp_ns - truth[0].stamp_ns, period_ns)
        assert remainder == 0, f"stamp {stamp_ns} is not a frame time"
        expected = truth[k % len(truth)].T_world_camera
        errors_mm.append(1000 * np.linalg.norm(np.array(values[:3], float) - expected.translation))
        q = np.array(values[3:], float)
        assert abs(np.linalg.norm(q) - 1) < 1e-5 and q[3] >= 0
    assert np.median(errors_mm) <= 2.0, errors_mm
    assert max(errors_mm) < 20.0, errors_mm

    log = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    events = [entry["event"] for entry in log]
    assert "zenoh settings" in events and "daemon started" in events and "daemon stopped" in events
    settings = next(entry for entry in log if entry["event"] == "zenoh settings")
    assert settings["scouting.multicast.enabled"] is False
    assert settings["listen.endpoints"] == [f"tcp/127.0.0.1:{port}"]
    stopped = next(entry for entry in log if entry["event"] == "daemon stopped")
    assert stopped["camera_closed"] is True
    assert "Traceback" not in err


def test_sighup_reloads_the_calibration_and_keeps_the_old_one_when_the_new_is_bad(tmp_path):
    """``systemctl reload`` (SIGHUP): a junk calibration is refused, logged and said on
    status while the daemon goes on with the old one; a good one is swapped in (the
    ``calibration`` queryable serves it) without a restart. Before: SIGHUP killed it, rc 129."""
    import zenoh

    from cubeloc.calib.camera_info import CameraCalibration

    port = free_port()
    config = write_config(tmp_path, port)
    daemon = subprocess.Popen([sys.executable, "-m", "cubeloc.daemon.cli", "run", "--config", config],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"})
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    statuses: list[dict] = []
    poses = threading.Semaphore(0)
    session = zenoh.open(conf)
    try:
        session.declare_subscriber("cubeloc/e2e/status", lambda s: statuses.append(json.loads(s.payload.to_bytes())))
        session.declare_subscriber("cubeloc/e2e/pose", lambda s: poses.release())

        def reload_state() -> dict | None:
            return statuses[-1]["extra"]["reload"] if statuses and "extra" in statuses[-1] else None

        def calibration_served() -> str:
            replies = list(session.get("cubeloc/e2e/calibration", timeout=5.0))
            return replies[0].ok.payload.to_bytes().decode() if replies and replies[0].ok else ""

        assert poses.acquire(timeout=120), "no pose before the reload"
        before = calibration_served()
        (tmp_path / "camera.yaml").write_bytes(bytes(range(256)))  # a technician's bad copy
        daemon.send_signal(signal.SIGHUP)
        assert wait_until(lambda: (reload_state() or {}).get("failed") == 1, 30), statuses[-1:]
        assert reload_state()["ok"] == 0 and "camera.yaml" in reload_state()["last"]["detail"]
        assert daemon.poll() is None and calibration_served() == before
        for _ in range(3):  # poses go on, on the old calibration
            assert poses.acquire(timeout=30)
        k = paper_camera().camera_matrix.copy()
        k[0, 0] += 1.5  # a recalibration: fx 1.5 px more
        write_camera_info(tmp_path / "camera.yaml", CameraCalibration(1280, 1024, k, paper_camera().distortion))
        daemon.send_signal(signal.SIGHUP)
        assert wait_until(lambda: (reload_state() or {}).get("ok") == 1, 30), statuses[-1:]
        assert reload_state()["last"]["ok"] is True
        served = calibration_served()
        assert served != before and served == (tmp_path / "camera.yaml").read_text()
        for _ in range(3):
            assert poses.acquire(timeout=30)
    finally:
        session.close()
        daemon.send_signal(signal.SIGTERM)
        out, err = daemon.communicate(timeout=20)
    assert daemon.returncode == 0, err[-2000:]
    events = [json.loads(line)["event"] for line in out.splitlines() if line.startswith("{")]
    assert "reload refused: the files in use stay" in events and "reloaded" in events and "processor swapped in" in events
    assert "Traceback" not in err
