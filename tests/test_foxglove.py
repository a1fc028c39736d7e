"""The Foxglove viewer (issue 19): a real WebSocket client speaking the protocol as the
Foxglove app does (tests/foxglove_client.py, protobuf decoded from the advertised
schemas) against the real daemon; MCAP files read back with the ``mcap`` library, also
after a kill -9; the plot of ``cubeloc track``; the live calibration."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from foxglove_client import FoxgloveClient
from helpers import half_resolution, wait_until
from mcap.exceptions import EndOfFile
from mcap.reader import NonSeekingReader, make_reader
from test_daemon_loop import CAMERA_POSITION, Script, make_prepared, start_daemon

from cubeloc.calib.camera_info import write_camera_info
from cubeloc.daemon.config import FoxgloveConfig
from cubeloc.daemon.frame_queue import CapturedFrame
from cubeloc.daemon.viewer import LiveViewer
from cubeloc.drivers.base import Frame
from cubeloc.fakes import render_view
from cubeloc.fakes.sequence import write_synthetic_sequence
from cubeloc.net import free_port
from cubeloc.positioning.camera_model import project
from cubeloc.positioning.estimator import FrameResult
from cubeloc.positioning.frames import RobotFrames
from cubeloc.positioning.geometry import Transform, look_at
from cubeloc.positioning.target import default_cube_yaml, make_cube

REPO = Path(__file__).resolve().parents[1]
TOPICS = {
    "/camera/image": "foxglove.CompressedImage",
    "/camera/calibration": "foxglove.CameraCalibration",
    "/camera/annotations": "foxglove.ImageAnnotations",
    "/pose": "foxglove.PoseInFrame",
    "/tf": "foxglove.FrameTransforms",
    "/trajectory": "foxglove.PosesInFrame",
    "/target": "foxglove.SceneUpdate",
    "/status": "foxglove.Log",
}


@pytest.fixture(scope="module")
def cube_image():
    return render_view(look_at(CAMERA_POSITION, np.zeros(3)), room=False)


def _viewer_daemon(tmp_path, cube_image, **frames):
    prepared = make_prepared(tmp_path, free_port(), **({"frames": frames} if frames else {}))
    port = free_port()
    config = prepared.config.model_copy(update={"foxglove": FoxgloveConfig(listen=f"127.0.0.1:{port}")})
    daemon, stop, thread, outcome = start_daemon(dataclasses.replace(prepared, config=config),
                                                 Script(cube_image, [10**6], period_s=0.05))
    assert wait_until(lambda: daemon.serving.is_set() and daemon.stats.poses >= 3, 60)
    return daemon, stop, thread, port


def test_a_foxglove_client_sees_the_image_the_tags_and_the_pose_and_no_client_costs_nothing(tmp_path, cube_image):
    frames = {"base_from_camera": {"xyz": [0.1, 0.0, 0.3], "rpy_deg": [-90, 0, -90]}}
    daemon, stop, thread, port = _viewer_daemon(tmp_path, cube_image, **frames)
    try:
        # nobody connected: every frame reached the viewer, and it built nothing
        assert daemon.report().extra["foxglove"]["frames"] == 0
        assert daemon.report().extra["foxglove"]["images"] == 0
        with FoxgloveClient(port) as client:
            client.wait_for_topics(TOPICS)
            assert {t: client.channels[t]["schemaName"] for t in TOPICS} == TOPICS
            assert all(client.channels[t]["encoding"] == "protobuf" for t in TOPICS)
            client.subscribe(*TOPICS)
            got = client.messages({"/camera/image": 2, "/camera/annotations": 2, "/pose": 3, "/tf": 1,
                                   "/trajectory": 1, "/target": 1, "/status": 1, "/camera/calibration": 1})
        image = got["/camera/image"][-1][1]
        assert image.format == "jpeg" and image.frame_id == "camera_optical"
        picture = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_GRAYSCALE)
        assert picture.shape == (512, 640)  # 1280 x 1024 scaled to the default 640 wide
        # the tags decoded, outlined where the full-resolution detector put them (scaled by 1/2)
        annotations = got["/camera/annotations"][-1][1]
        labels = [t.text for t in annotations.texts]
        assert sorted(labels[:-1]) == ["0", "3", "4"] and labels[-1] == "target"
        T_camera_world = look_at(CAMERA_POSITION, np.zeros(3)).inverse()
        for k, tag_id in enumerate(labels[:-1]):
            outline = np.array([(p.x, p.y) for p in annotations.points[k].points])
            truth = project(T_camera_world.apply(make_cube().tag(int(tag_id)).corners), daemon.prepared.calibration)
            assert np.abs(outline - (truth + 0.5) / 2).max() < 0.5  # Foxglove's pixel centres at +0.5
        # the base in the map: the camera's pose through the mount ([frames])
        pose = got["/pose"][-1][1]
        assert pose.frame_id == "map"
        T_base_camera = daemon.config.frames.robot_frames().T_base_camera
        T_map_camera = Transform.from_quaternion(
            np.array([pose.pose.position.x, pose.pose.position.y, pose.pose.position.z]),
            np.array([pose.pose.orientation.x, pose.pose.orientation.y, pose.pose.orientation.z,
                      pose.pose.orientation.w])) @ T_base_camera
        assert np.linalg.norm(T_map_camera.translation - CAMERA_POSITION) < 0.005
        transforms = got["/tf"][-1][1].transforms
        assert [(t.parent_frame_id, t.child_frame_id) for t in transforms] == [
            ("map", "target"), ("map", "base_link"), ("base_link", "camera_optical")]
        assert len(got["/trajectory"][-1][1].poses) >= 1
        scene = got["/target"][-1][1].entities[0]
        assert scene.frame_id == "target" and len(scene.triangles) == 6 and len(scene.cubes) == 1
        assert json.loads(got["/status"][-1][1].message)["name"] == "looptest"
        calibration = got["/camera/calibration"][-1][1]
        assert (calibration.width, calibration.height) == (640, 512)
        assert calibration.K[0] == pytest.approx(daemon.prepared.calibration.fx / 2)
        report = daemon.report().extra["foxglove"]
        assert report["frames"] > 0 and report["images"] >= 2
    finally:
        stop.set()
        thread.join(10)
    assert not thread.is_alive()


def test_a_client_that_speaks_garbage_is_dropped_or_told_and_the_daemon_goes_on(tmp_path, cube_image):
    """Not WebSocket at all: dropped at the handshake. WebSocket with messages that mean
    nothing: each answered with an error status by the SDK, which has no call to drop a
    client (foxglove-sdk 0.30); nothing it sends reaches the daemon (no client publishing,
    services or parameters are offered). Either way the daemon and the next client go on."""
    daemon, stop, thread, port = _viewer_daemon(tmp_path, cube_image)
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as raw:  # not even HTTP
            raw.sendall(os.urandom(4096) + b"\r\n\r\n")
            reply = b""
            with contextlib.suppress(ConnectionResetError):
                while chunk := raw.recv(4096):
                    reply += chunk
            assert b"101 Switching Protocols" not in reply  # closed by the server, never upgraded
        from websockets.sync.client import connect

        junk = ["{not json", json.dumps({"op": "subscribe", "subscriptions": "all"}), json.dumps({"op": "no-such-op"}),
                json.dumps({"op": "advertise", "channels": [{"id": 1, "topic": "/pose", "encoding": "json",
                                                              "schemaName": "x"}]}),
                b"\x02" + os.urandom(64)]
        with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"]) as ws:
            info = json.loads(ws.recv(timeout=5))
            assert info["op"] == "serverInfo" and info["capabilities"] == []  # nothing a client may send in
            for message in junk:
                ws.send(message)
            errors = 0
            with contextlib.suppress(TimeoutError):
                while errors < len(junk):
                    reply = ws.recv(timeout=5)
                    if isinstance(reply, str) and json.loads(reply)["op"] == "status":
                        errors += json.loads(reply)["level"] == 2  # error
            assert errors >= 4
        poses = daemon.stats.poses
        with FoxgloveClient(port) as client:  # and the next client is served
            client.wait_for_topics(["/pose"])
            client.subscribe("/pose")
            assert len(client.messages({"/pose": 2})["/pose"]) >= 2
        assert daemon.stats.poses > poses and daemon.stats.processor_errors == 0
    finally:
        stop.set()
        thread.join(10)


def test_a_viewer_stuck_on_a_frame_never_holds_up_the_loop_it_drops_and_counts(monkeypatch):
    from cubeloc.calib.camera_info import paper_camera

    viewer = LiveViewer(FoxgloveConfig(listen=f"127.0.0.1:{free_port()}"), make_cube(), paper_camera(),
                        RobotFrames(Transform.identity(), Transform.identity()))
    release, entered = threading.Event(), threading.Event()

    def stuck(*_args, **_kwargs):
        entered.set()
        release.wait(30)

    monkeypatch.setattr(viewer.channels, "frame", stuck)
    image = np.zeros((1024, 1280), np.uint8)
    try:
        offer = lambda seq: viewer.offer(CapturedFrame(Frame(image, seq, seq, seq, 1000.0), seq, seq),  # noqa: E731
                                         FrameResult(None, "no_target"))
        offer(0)
        assert entered.wait(10)
        for seq in range(1, 101):  # the viewer is stuck: each offer returns at once, replacing the last
            offer(seq)
        assert viewer.report()["dropped"] == 99  # all but the one waiting
    finally:
        release.set()
        viewer.close()


def _config_file(tmp_path: Path, listen: str) -> Path:
    from cubeloc.calib.camera_info import paper_camera

    write_camera_info(tmp_path / "camera.yaml", paper_camera())
    (tmp_path / "target.yaml").write_text(default_cube_yaml())
    config = tmp_path / "cubeloc.toml"
    config.write_text(f"""
name = "fgtest"
[camera]
source = "synthetic:static?seconds=2"
[positioning]
calibration = "{tmp_path / 'camera.yaml'}"
target = "{tmp_path / 'target.yaml'}"
[zenoh]
multicast_scouting = false
listen = ["tcp/127.0.0.1:{free_port()}"]
[foxglove]
listen = "{listen}"
""")
    return config


@pytest.mark.parametrize("listen, words", [
    ("in-use", "cannot listen there"),
    ("192.0.2.1:8765", "cannot listen there"),  # TEST-NET: not this machine's (bind only, nothing sent)
    ("localhost", "not HOST:PORT"),
    ("127.0.0.1:99999", "not HOST:PORT"),
])
def test_a_listen_address_in_use_or_not_ours_is_one_line_and_exit_2(tmp_path, cli, listen, words):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        if listen == "in-use":
            listen = f"127.0.0.1:{busy.getsockname()[1]}"
        done = cli("run", "--config", str(_config_file(tmp_path, "127.0.0.1:1")), "--foxglove", listen, timeout=60)
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if "error" in line.lower()]
    assert len(lines) == 1 and words in lines[0] and "Traceback" not in done.stderr


def _sequence(tmp_path: Path, seconds: float) -> Path:
    sequence = tmp_path / "seq"
    write_synthetic_sequence(sequence, "orbit", seconds=seconds, fps=10.0, seed=3, calibration=half_resolution())
    return sequence


def _read_mcap(path: Path) -> dict:
    with open(path, "rb") as handle:
        reader = make_reader(handle)
        summary = reader.get_summary()
        counts = summary.statistics.channel_message_counts
        return {c.topic: (summary.schemas[c.schema_id].name, counts.get(c.id, 0)) for c in summary.channels.values()}


def test_track_writes_the_viewers_channels_to_mcap_and_a_plot(tmp_path, cli):
    from foxglove_client import message_class

    sequence = _sequence(tmp_path, 3.0)
    out, mcap = tmp_path / "out.tum", tmp_path / "out.mcap"
    args = ("track", "--target", str(sequence / "target.yaml"), "--calib", str(sequence / "camera.yaml"),
            "--sequence", str(sequence), "--out", str(out))
    done = cli(*args, "--mcap", str(mcap))
    assert done.returncode == 0, done.stderr
    topics = _read_mcap(mcap)
    assert {t: name for t, (name, _) in topics.items()} == TOPICS
    assert topics["/camera/image"][1] == 30 and topics["/pose"][1] == 30  # 10 Hz: every frame's image
    assert topics["/status"][1] >= 1  # a line for each change of state
    with open(mcap, "rb") as handle:
        reader = make_reader(handle)
        for schema, channel, message in reader.iter_messages(topics=["/pose", "/camera/image"]):
            decoded = message_class(schema.name, schema.data).FromString(message.data)
            if channel.topic == "/camera/image":
                picture = cv2.imdecode(np.frombuffer(decoded.data, np.uint8), cv2.IMREAD_GRAYSCALE)
                assert picture.shape == (512, 640)  # the half-resolution camera is 640 wide: not scaled
            else:
                stamp = decoded.timestamp.seconds * 10**9 + decoded.timestamp.nanos
                assert message.log_time == stamp  # timed by the frames' stamps
    # the plot beside the trajectory: labelled axes, the error panel (the sequence has ground truth)
    picture = cv2.imread(str(tmp_path / "out.png"))
    assert picture is not None and picture.shape == (550, 1200, 3)
    assert "plot:" in done.stdout
    # an existing MCAP file is not overwritten
    again = cli(*args, "--mcap", str(mcap), "--no-plot")
    assert again.returncode == 2 and "already exists" in again.stderr


def test_a_kill_9_leaves_an_mcap_file_readable_up_to_its_last_chunk(tmp_path):
    sequence = _sequence(tmp_path, 20.0)
    mcap = tmp_path / "killed.mcap"
    process = subprocess.Popen(
        [sys.executable, "-m", "cubeloc.daemon.cli", "track", "--target", str(sequence / "target.yaml"), "--calib",
         str(sequence / "camera.yaml"), "--sequence", str(sequence), "--out", str(tmp_path / "out.tum"),
         "--mcap", str(mcap)], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        # a chunk is finished each second: wait for three flushes' worth
        assert wait_until(lambda: mcap.is_file() and mcap.stat().st_size > 0, 60)
        grown = mcap.stat().st_size
        assert wait_until(lambda: mcap.stat().st_size > grown, 30)
        time.sleep(2.5)
        process.send_signal(signal.SIGKILL)
        process.wait(10)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == -signal.SIGKILL
    with open(mcap, "rb") as handle, pytest.raises(Exception):  # noqa: B017 - no summary to index it by
        list(make_reader(handle).iter_messages())
    images, stamps = 0, []
    with open(mcap, "rb") as handle:
        try:
            for _, channel, message in NonSeekingReader(handle).iter_messages(log_time_order=False):
                images += channel.topic == "/camera/image"
                stamps.append(message.log_time)
        except EndOfFile:
            pass  # the record cut by the kill, after every chunk that was finished
    assert images >= 5 and stamps == sorted(stamps)


def test_live_calibration_shows_the_board_the_coverage_and_the_hint_in_foxglove(tmp_path):
    from test_calib_cli import CAMERA, CHARUCO

    from cubeloc.calib.boards import parse_board
    from cubeloc.fakes.board_views import write_board_sequence

    sequence = tmp_path / "seq"
    write_board_sequence(sequence, parse_board(CHARUCO), CAMERA, count=30, seed=6)
    port = free_port()
    process = subprocess.Popen(
        [sys.executable, "-m", "cubeloc.daemon.cli", "calibrate", "--camera", f"replay:{sequence}@pace", "--board", CHARUCO,
         "--out", str(tmp_path / "live.yaml"), "--foxglove", f"127.0.0.1:{port}"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        client = None
        deadline = time.monotonic() + 30
        while client is None and time.monotonic() < deadline:
            try:
                client = FoxgloveClient(port, timeout_s=2)
            except OSError:
                time.sleep(0.1)
        assert client is not None, "the calibration's Foxglove server did not come up"
        with client:
            client.wait_for_topics(["/camera/image", "/calibration/annotations", "/calibration/hint"])
            client.subscribe("/camera/image", "/calibration/annotations", "/calibration/hint")
            got = client.messages({"/camera/image": 3, "/calibration/annotations": 3, "/calibration/hint": 1},
                                  timeout_s=30)
    finally:
        stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 0, stderr
    texts = [[t.text for t in a.texts] for _, a in got["/calibration/annotations"]]
    assert any(any(t.startswith("X ") and t.endswith("%") for t in ts) for ts in texts)  # the coverage bars
    assert any(any(t.startswith("skew ") for t in ts) for ts in texts)
    assert any(any(t.startswith("views ") for t in ts) for ts in texts)  # the count and the next hint
    boards = [a for _, a in got["/calibration/annotations"] if len(a.points) > 9 + 8]  # cells, bars, + points
    assert boards, "no frame showed the board's points"
    assert got["/calibration/hint"][0][1].message.startswith("views")
