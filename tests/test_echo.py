"""``cubeloc echo`` against the daemon's real Zenoh publisher on loopback."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from cubeloc.daemon.messages import CameraStatus, StatusReport, pose_message, status_message
from cubeloc.daemon.publisher import ZenohPublisher
from cubeloc.net import free_port
from cubeloc.positioning.estimator import PoseEstimate, PoseState
from cubeloc.positioning.geometry import look_at


@pytest.fixture
def publisher():
    import zenoh

    port = free_port()
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    session = zenoh.open(conf)
    publisher = ZenohPublisher(session, "echotest", "image_width: 1280\n", lambda: True)
    yield port, publisher
    publisher.close()
    session.close()


def _status(poses: int) -> bytes:
    camera = CameraStatus("synthetic:paper", "streaming", model="cubeloc synthetic camera")
    return status_message(StatusReport(
        name="echotest", state="target", detail="", stamp_ns=time.time_ns(), fps=9.87, frames=poses,
        poses=poses, dropped_frames=1, rejected_poses=0, latency_ms={"p50": 12.5, "p99": 40.25},
        camera=camera, uptime_s=61.0, version="0.1.0",
    ))


def _run_echo(port: int, publisher: ZenohPublisher, *extra: str) -> str:
    echo = subprocess.Popen(
        [sys.executable, "-m", "cubeloc.daemon.cli", "echo", "--connect", f"tcp/127.0.0.1:{port}", "--no-scouting",
         "--count", "3", "--duration", "60", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    estimate = PoseEstimate(look_at(np.array([1.5, -1.5, 0.91]), np.zeros(3)), PoseState.TARGET, 3, (0, 1, 4), 0.25)
    seq = 0
    # Publish until echo has had its three poses (it may connect after the first few).
    while echo.poll() is None and seq < 600:
        publisher.publish_pose(pose_message(seq, 1_700_000_000_000_000_000 + seq * 100_000_000, estimate))
        if seq % 5 == 0:
            publisher.publish_status(_status(seq))
        seq += 1
        time.sleep(0.05)
    out, err = echo.communicate(timeout=30)
    assert echo.returncode == 0, err
    return out


def test_echo_prints_readable_lines(publisher):
    port, pub = publisher
    out = _run_echo(port, pub)
    lines = out.splitlines()
    poses = [line for line in lines if "  pose  " in line]
    assert len(poses) == 3
    assert "xyz [ +1.5000  -1.5000  +0.9100] m" in poses[0] and "target 3 faces" in poses[0]
    assert any(line == "echotest  alive" for line in lines)
    statuses = [line for line in lines if "  status  " in line]
    for line in statuses:
        assert "echotest  status  target" in line and "9.9 fps" in line and "p50 12.5 p99 40.2 ms" in line


def test_echo_json_prints_the_payloads(publisher):
    port, pub = publisher
    out = _run_echo(port, pub, "--json", "--no-status")
    docs = [json.loads(line) for line in out.splitlines()]
    assert len(docs) == 3 and all(d["schema"] == "cubeloc.pose/3" for d in docs)
    assert docs[0]["position"] == pytest.approx([1.5, -1.5, 0.91])


def test_echo_says_when_no_daemon_answers_and_exits_1():
    """A dead port (nothing listens): one line saying so, exit 1 (before: nothing printed,
    exit 0, as if all were well)."""
    port = free_port()
    done = subprocess.run([sys.executable, "-m", "cubeloc.daemon.cli", "echo", "--connect", f"tcp/127.0.0.1:{port}",
                           "--no-scouting", "--wait", "1.5"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 1, (done.stdout, done.stderr)
    assert done.stdout == ""
    assert f"no cubeloc daemon seen on tcp/127.0.0.1:{port} within 1.5 s" in done.stderr
    assert "Traceback" not in done.stderr


def test_the_first_pose_shows_no_rate_rather_than_0_hz(publisher):
    port, pub = publisher
    poses = [line for line in _run_echo(port, pub).splitlines() if "  pose  " in line]
    assert poses[0].endswith("- Hz") and "0.0 Hz" not in poses[0], poses[0]
    assert poses[-1].endswith(" Hz") and not poses[-1].endswith("- Hz")


def test_the_example_subscriber_takes_a_zenoh_file_and_says_when_nothing_answers(publisher, tmp_path):
    """examples/subscriber.py: ``--zenoh-config FILE`` (the shipped ACL or TLS set-ups need
    one) and, with nobody there, one line and exit 1."""
    from pathlib import Path

    subscriber = Path(__file__).resolve().parents[1] / "examples" / "subscriber.py"
    dead = free_port()
    done = subprocess.run([sys.executable, str(subscriber), "--connect", f"tcp/127.0.0.1:{dead}", "--wait", "1.5"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 1 and f"no cubeloc daemon seen on tcp/127.0.0.1:{dead} within 1.5 s" in done.stderr

    port, pub = publisher
    zenoh_file = tmp_path / "client.json5"
    zenoh_file.write_text(f'{{ mode: "client", connect: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, '
                          'scouting: { multicast: { enabled: false } } }\n')
    reader = subprocess.Popen([sys.executable, str(subscriber), "--zenoh-config", str(zenoh_file), "--count", "2",
                               "--timeout", "60"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    estimate = PoseEstimate(look_at(np.array([1.5, -1.5, 0.91]), np.zeros(3)), PoseState.TARGET, 3, (0, 1, 4), 0.25)
    seq = 0
    while reader.poll() is None and seq < 600:
        pub.publish_pose(pose_message(seq, 1_700_000_000_000_000_000 + seq * 100_000_000, estimate))
        seq += 1
        time.sleep(0.05)
    out, err = reader.communicate(timeout=30)
    assert reader.returncode == 0, err
    assert len(out.splitlines()) == 2 and out.split()[1] == "1.500000", out


def test_echo_names_the_source_where_it_says_more_than_the_state():
    from cubeloc.daemon.commands.echo import format_pose
    from cubeloc.daemon.messages import pose_payload
    from cubeloc.positioning.estimator import PoseSource

    where = look_at(np.array([1.5, -1.5, 0.91]), np.zeros(3))
    held = pose_payload(5, 1_700_000_000_000_000_000, PoseEstimate(where, PoseState.TRACKING, 0, (), 0.0, None,
                                                                   PoseSource.HELD))
    assert "tracking (held) 0 faces" in format_pose("r", held, None)
    target = pose_payload(6, 1_700_000_000_000_000_000, PoseEstimate(where, PoseState.TARGET, 3, (0, 1, 4), 0.2))
    assert "  target 3 faces" in format_pose("r", target, None)
    del target["source"]  # a daemon of schema /1
    assert "  target 3 faces" in format_pose("r", target, None)
