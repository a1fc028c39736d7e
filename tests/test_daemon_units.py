"""The daemon's parts on their own: newest-frame slot, wire payloads, sd_notify, stats,
and bad configurations failing with one line before anything starts."""

from __future__ import annotations

import json
import math
import os
import socket
import threading
import time

import numpy as np
import pytest

from cubeloc.calib.camera_info import paper_camera, write_camera_info
from cubeloc.daemon.frame_queue import CapturedFrame, LatestFrameSlot
from cubeloc.daemon.loop_stats import LoopStats
from cubeloc.daemon.messages import UnpublishablePose, pose_message, pose_payload
from cubeloc.daemon.sdnotify import SystemdNotifier
from cubeloc.drivers.base import Frame
from cubeloc.positioning.estimator import PoseEstimate, PoseSource, PoseState
from cubeloc.positioning.geometry import Transform, look_at
from cubeloc.positioning.target import default_cube_yaml


def _frame(seq: int) -> CapturedFrame:
    image = np.zeros((4, 4), np.uint8)
    return CapturedFrame(Frame(image, seq, seq, 1_000 + seq, 100.0), seq, time.monotonic_ns())


def _estimate(transform: Transform, covariance=None) -> PoseEstimate:
    return PoseEstimate(transform, PoseState.TARGET, 3, (0, 1, 4), 0.21, covariance)


# -- newest-frame slot ------------------------------------------------------------------
def test_slot_keeps_the_newest_frame_and_counts_the_dropped():
    slot = LatestFrameSlot()
    for seq in range(5):
        slot.put(_frame(seq))
    assert slot.get(0.01).seq == 4
    assert slot.dropped == 4
    assert slot.get(0.01) is None  # taken: no backlog to drain


def test_slot_get_wakes_on_put_and_on_close():
    slot = LatestFrameSlot()
    threading.Timer(0.05, lambda: slot.put(_frame(7))).start()
    assert slot.get(5.0).seq == 7
    threading.Timer(0.05, slot.close).start()
    started = time.monotonic()
    assert slot.get(5.0) is None
    assert time.monotonic() - started < 4.0


# -- cubeloc.pose/3 ---------------------------------------------------------------------
def test_pose_payload_follows_the_schema():
    T = look_at(np.array([2.0, -1.0, 0.8]), np.zeros(3))
    doc = json.loads(pose_message(42, 1_790_000_000_123_456_789, _estimate(T, np.eye(6) * 1e-6),
                                  1_790_000_000_150_000_000))
    assert doc["schema"] == "cubeloc.pose/3"
    assert doc["seq"] == 42 and doc["stamp_ns"] == 1_790_000_000_123_456_789
    assert doc["frame_id"] == "world" and doc["child_frame_id"] == "camera"
    assert doc["state"] == "target" and doc["source"] == "target" and doc["planes"] == 3
    assert doc["latency_ns"] == 26_543_211  # published - captured
    np.testing.assert_allclose(doc["position"], [2.0, -1.0, 0.8], atol=1e-12)
    q = np.array(doc["orientation"])
    assert abs(np.linalg.norm(q) - 1) < 1e-9 and q[3] >= 0
    back = Transform.from_quaternion(np.array(doc["position"]), q)
    assert back.rotation_angle_to(T) < 1e-9
    assert len(doc["covariance"]) == 36


@pytest.mark.parametrize(
    "transform, why",
    [
        (Transform(np.eye(3), [np.nan, 0, 1]), "position"),
        (Transform(np.eye(3), [np.inf, 0, 1]), "position"),
        (Transform(np.eye(3) * 1.5, [0, 0, 1]), "rotation"),
        (Transform(np.diag([1.0, 1.0, -1.0]), [0, 0, 1]), "rotation"),
        (Transform(np.full((3, 3), np.nan), [0, 0, 1]), "rotation"),
        (Transform(np.eye(3), [1e6, 0, 0]), "position"),
    ],
)
def test_untrustworthy_poses_are_refused(transform, why):
    with pytest.raises(UnpublishablePose, match=why):
        pose_payload(1, 10, _estimate(transform))


def test_nan_covariance_and_zero_stamp_are_refused():
    T = look_at(np.array([2.0, 0.0, 0.5]), np.zeros(3))
    bad = np.eye(6)
    bad[2, 2] = math.nan
    with pytest.raises(UnpublishablePose, match="covariance"):
        pose_payload(1, 10, _estimate(T, bad))
    with pytest.raises(UnpublishablePose, match="stamp_ns"):
        pose_payload(1, 0, _estimate(T))


# -- sd_notify over a real datagram socket ----------------------------------------------
def _bind_notify_socket(tmp_path):
    path = str(tmp_path / "notify.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(path)
    server.settimeout(2.0)
    return server, path


def test_sdnotify_sends_ready_status_watchdog(tmp_path):
    server, path = _bind_notify_socket(tmp_path)
    with server:
        notifier = SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "4000000", "WATCHDOG_PID": str(os.getpid())})
        assert notifier.enabled and notifier.watchdog_interval_s == 4.0
        notifier.watchdog()  # progress before READY: the start timeout moves on
        assert server.recv(4096) == b"EXTEND_TIMEOUT_USEC=30000000"
        notifier._last_watchdog = float("-inf")  # (skip the rate limit)
        notifier.ready(status="streaming")
        assert server.recv(4096) == b"READY=1\nSTATUS=streaming"
        notifier.ready(status="streaming")  # READY goes once
        notifier.watchdog()
        assert server.recv(4096) == b"WATCHDOG=1"
        notifier.watchdog()  # rate-limited to a quarter of the interval: nothing sent
        notifier.status("reconnecting")
        assert server.recv(4096) == b"STATUS=reconnecting"
        notifier.stopping()
        assert server.recv(4096) == b"STOPPING=1\nSTATUS=stopping"
        notifier.close()


def test_sdnotify_never_blocks_on_a_full_socket(tmp_path):
    server, path = _bind_notify_socket(tmp_path)
    with server:
        notifier = SystemdNotifier({"NOTIFY_SOCKET": path})
        sent = [notifier.notify(status=str(i)) for i in range(100)]  # nobody reads: it fills up
        assert sent[0] and not all(sent)
        notifier.ready(status="streaming")
        assert not notifier.ready_sent  # dropped, so it will be sent again
        server.setblocking(False)
        while True:
            try:
                server.recv(4096)
            except BlockingIOError:
                break
        server.settimeout(2.0)
        notifier.ready(status="streaming")
        assert notifier.ready_sent and server.recv(4096) == b"READY=1\nSTATUS=streaming"


def test_sdnotify_abstract_socket_and_absent_socket(tmp_path):
    name = f"cubeloc-test-{os.getpid()}"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(b"\0" + name.encode())
    server.settimeout(2.0)
    with server:
        SystemdNotifier({"NOTIFY_SOCKET": "@" + name}).notify(status="x")
        assert server.recv(100) == b"STATUS=x"
    silent = SystemdNotifier({})
    assert not silent.enabled and silent.notify(ready=1) is False
    silent.watchdog()
    silent.ready("x")
    # A watchdog meant for another process is not ours.
    assert SystemdNotifier({"NOTIFY_SOCKET": "/nonexistent", "WATCHDOG_USEC": "1000", "WATCHDOG_PID": "1"}).watchdog_interval_s is None


# -- loop statistics --------------------------------------------------------------------
def test_loop_stats_percentiles_and_summary():
    stats = LoopStats()
    assert stats.latency_percentiles() == {"p50": None, "p99": None}
    for i in range(100):
        stats.record_frame(i, "target", "", (0, 1))
        stats.record_pose(float(i + 1))
    lat = stats.latency_percentiles()
    assert 49 <= lat["p50"] <= 52 and 98 <= lat["p99"] <= 100
    summary = stats.take_summary()
    assert summary["frames"] == 100 and summary["poses"] == 100 and summary["status:target"] == 100
    assert not stats.take_summary()


def test_loop_stats_count_the_time_without_a_pose_once_there_was_one_and_the_held_frames():
    stats = LoopStats()
    stats.record_frame(0, "initialising", "waiting for the target", ())
    time.sleep(0.05)
    stats.record_frame(1, "target", "", (0,), PoseSource.TARGET)
    assert stats.lost_s == 0.0 and stats.lost_now_s() == 0.0  # waiting at the start is not lost
    stats.record_frame(2, "tracking", "held: orientation from rays", (), PoseSource.HELD)
    assert stats.source_now() == "held"
    time.sleep(0.05)
    stats.record_frame(3, "lost", "", ())
    time.sleep(0.05)
    stats.record_frame(4, "lost", "", ())
    assert 0.09 <= stats.lost_s <= 0.5 and stats.lost_now_s() >= 0.09
    assert stats.source_now() is None
    stats.record_frame(5, "relocalised", "", (), PoseSource.RELOCALISED)
    assert stats.lost_now_s() == 0.0 and stats.held_frames == 1
    assert stats.source_counts() == {"target": 1, "held": 1, "relocalised": 1}


# -- configuration errors: one line, exit 2, nothing started ------------------------------
def _write_files(tmp_path, width=1280, height=1024):
    write_camera_info(tmp_path / "camera.yaml", paper_camera(width, height))
    (tmp_path / "target.yaml").write_text(default_cube_yaml())


def _config(tmp_path, extra: str = "", calibration: str | None = None) -> str:
    """The text of a config for the synthetic camera with files in tmp_path."""
    calibration = calibration or str(tmp_path / "camera.yaml")
    return (
        'name = "unit"\n'
        "[camera]\nsource = \"synthetic:paper\"\n"
        f"[positioning]\ncalibration = \"{calibration}\"\ntarget = \"{tmp_path / 'target.yaml'}\"\n"
        "[zenoh]\nmulticast_scouting = false\nlisten = [\"tcp/127.0.0.1:0\"]\n" + extra
    )


@pytest.mark.parametrize(
    "case, expect",
    [
        ("unknown_key", "unknown key 'camera.exposure'"),
        ("bad_endpoint", "tcp/127.0.0.1"),
        ("bad_endpoint_host", "neither an IP address nor a host name"),
        ("missing_calibration", "calibration file not found"),
        ("wrong_resolution", "640x512"),
        ("unknown_source", "unknown camera source"),
        ("missing_zenoh_file", "zenoh config file"),
        ("bad_source_option", "unknown option(s) bogus"),
        ("bad_mount", "frames.base_from_camera.quaternion = [0, 0, 0.5, 0.5]: Value error, not a unit quaternion"),
        ("bad_ros2_namespace", "ros2.namespace = 'robot7': Value error, a namespace is absolute"),
        ("bad_ros2_topic", "ros2.topics.pose = 'cubeloc//pose': Value error, not a ROS 2 topic name"),
        ("bad_ros2_distro", "ros2.distro = 'humble'"),
    ],
)
def test_bad_config_exits_2_with_one_line(tmp_path, cli, case, expect):
    _write_files(tmp_path)
    write_camera_info(tmp_path / "small.yaml", paper_camera(640, 512))
    good = _config(tmp_path)
    config_text = {
        "unknown_key": good.replace("[camera]\n", "[camera]\nexposure = 5\n"),
        "bad_endpoint": good.replace("tcp/127.0.0.1:0", "tcp/127.0.0.1"),
        "bad_endpoint_host": good.replace("tcp/127.0.0.1:0", "tcp/300.1.2.3:7447"),
        "missing_calibration": _config(tmp_path, calibration=str(tmp_path / "nope.yaml")),
        "wrong_resolution": _config(tmp_path, calibration=str(tmp_path / "small.yaml")),
        "unknown_source": good.replace("synthetic:paper", "webcam:0"),
        "missing_zenoh_file": _config(tmp_path, f"config_file = \"{tmp_path / 'zenoh.json5'}\"\n"),
        "bad_source_option": good.replace("synthetic:paper", "synthetic:paper?bogus=1"),
        "bad_mount": good + "[frames.base_from_camera]\nxyz = [0.3, 0, 1.1]\nquaternion = [0, 0, 0.5, 0.5]\n",
        "bad_ros2_namespace": good + "[ros2]\nenabled = true\nnamespace = \"robot7\"\n",
        "bad_ros2_topic": good + "[ros2.topics]\npose = \"cubeloc//pose\"\n",
        "bad_ros2_distro": good + "[ros2]\ndistro = \"humble\"\n",
    }[case]
    path = tmp_path / "case.toml"
    path.write_text(config_text)
    result = cli("run", "--config", str(path), timeout=60)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("cubeloc run: error:") and expect in lines[0], lines[0]
    assert "Traceback" not in result.stderr
    assert "daemon started" not in result.stdout and "zenoh session open" not in result.stdout


def test_good_config_passes_the_check(tmp_path, cli):
    _write_files(tmp_path)
    (tmp_path / "good.toml").write_text(_config(tmp_path))
    result = cli("run", "--config", str(tmp_path / "good.toml"), "--check", timeout=60)
    assert result.returncode == 0, result.stderr
    assert "config OK" in result.stdout


def test_port_in_use_exits_2_with_one_line(tmp_path, cli):
    _write_files(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        (tmp_path / "busy.toml").write_text(_config(tmp_path).replace("tcp/127.0.0.1:0", f"tcp/127.0.0.1:{port}"))
        result = cli("run", "--config", str(tmp_path / "busy.toml"), timeout=60)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Address already in use" in lines[0] and f"tcp/127.0.0.1:{port}" in lines[0], lines
    assert ".rs:" not in lines[0]  # no Rust source locations in a user's message


def test_the_zenoh_start_up_line_shows_this_modes_listeners():
    """A client listens on nothing; the log showed Zenoh's per-mode defaults, among them a
    router's tcp/[::]:7447 that this session never opened."""
    from cubeloc.daemon.config import ZenohConfig
    from cubeloc.daemon.zenoh_session import build_zenoh_config, effective_settings

    client = effective_settings(build_zenoh_config(ZenohConfig(mode="client", connect=("tcp/127.0.0.1:7447",))))
    assert client["listen/endpoints"] == [] and client["connect/endpoints"] == ["tcp/127.0.0.1:7447"]
    peer = effective_settings(build_zenoh_config(ZenohConfig(mode="peer")))
    assert peer["listen/endpoints"] == ["tcp/[::]:0"]
    explicit = effective_settings(build_zenoh_config(ZenohConfig(mode="peer", listen=("tcp/127.0.0.1:7999",))))
    assert explicit["listen/endpoints"] == ["tcp/127.0.0.1:7999"]


def test_the_config_turns_the_trackers_loop_closure_off(tmp_path):
    """``[positioning] loop_closure`` reaches the tracker the daemon builds (default off)."""
    from cubeloc.daemon.config import load_config
    from cubeloc.daemon.preflight import make_processor, prepare

    _write_files(tmp_path)
    for text, expected in (("", False), ("loop_closure = true\n", True)):
        path = tmp_path / "loop.toml"
        path.write_text(_config(tmp_path).replace("[zenoh]", text + "[zenoh]"))
        processor = make_processor(prepare(load_config(path, environ={})))
        try:
            assert processor.tracker.options.loop.enabled is expected
        finally:
            processor.close()


def test_the_trackers_options_come_from_the_configuration_in_one_place():
    """preflight.processor_options: [positioning]'s face and residual limits and loop
    closure, the keyframe budget and bundle adjustment's changes, for the daemon, cubeloc
    track and the benchmarks alike; the defaults are the tracker's own."""
    from cubeloc.daemon.config import Config, PositioningConfig
    from cubeloc.daemon.preflight import processor_options
    from cubeloc.positioning.tracking import ProcessorOptions

    assert processor_options(Config(), background=False) == ProcessorOptions.in_frame_loop()
    config = Config(positioning=PositioningConfig(allow_two_faces=False, max_reproj_rms_px=0.8, loop_closure=True))
    options = processor_options(config, 400, solver="scipy")
    assert not options.pose.allow_two_faces and options.pose.max_reproj_rms_px == 0.8
    assert options.tracker.loop.enabled and options.tracker.keyframes.max_kept == 400
    assert options.tracker.bundle.solver == "scipy" and options.tracker.bundle.background
    assert options.tracker.init == ProcessorOptions().tracker.init
