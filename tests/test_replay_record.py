"""Recording and replaying sequences: byte-for-byte round trip from the GigE Vision fake,
SIGTERM during ``cubeloc record``, and the user errors (exit 2, one line, no traceback)."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

import cv2
import numpy as np
import pytest

from cubeloc.daemon.cameras import make_camera
from cubeloc.drivers.aravis_camera import AravisCamera
from cubeloc.drivers.base import CameraSettings, EndOfStream, FrameTimeout
from cubeloc.drivers.fake_gige import GvFake
from cubeloc.drivers.recorder import record_sequence
from cubeloc.drivers.replay import ReplayCamera, parse_replay_argument
from cubeloc.drivers.sequence import SequenceWriter, camera_dir, read_image, read_sequence_index


@pytest.fixture(autouse=True)
def private_lock_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("CUBELOC_LOCK_DIR", str(tmp_path / "locks"))


@pytest.fixture
def gv_fake():
    fake = GvFake("GV02").start()
    yield fake
    fake.stop()


class KeepingCamera:
    """Delegates to a camera and keeps a copy of every frame it hands out."""

    def __init__(self, camera):
        self.camera = camera
        self.frames = []

    def __getattr__(self, name):
        return getattr(self.camera, name)

    def next_frame(self, timeout_s):
        frame = self.camera.next_frame(timeout_s)
        self.frames.append((frame.stamp_ns, frame.image.copy()))
        return frame


def replay_all(directory, paced=False):
    frames = []
    with ReplayCamera(directory, CameraSettings(), paced=paced) as replay:
        replay.start()
        while True:
            try:
                frames.append(replay.next_frame(5.0))
            except EndOfStream:
                return frames, replay.stats


def test_record_from_the_gv_fake_and_replay_byte_for_byte(gv_fake, tmp_path):
    out = tmp_path / "seq"
    with AravisCamera(gv_fake.device_id, CameraSettings(frame_rate_hz=50.0)) as camera:
        keeping = KeepingCamera(camera)
        camera.start()
        with SequenceWriter(out) as writer:
            summary = record_sequence(keeping, writer, stop=threading.Event(), max_frames=12)
    assert summary.frames == 12 and summary.reason == "frames"
    replayed, stats = replay_all(out)
    assert len(replayed) == 12 and stats.delivered == 12
    for (stamp_ns, image), frame in zip(keeping.frames, replayed, strict=True):
        assert frame.stamp_ns == stamp_ns
        assert frame.image.shape == (1024, 1280) and frame.image.dtype == np.uint8
        assert frame.image.tobytes() == image.tobytes()
    assert len({f.image.tobytes() for f in replayed}) > 1  # the fake's pattern moves


def test_replay_at_recorded_pace(tmp_path):
    out = tmp_path / "seq"
    image = np.arange(64 * 48, dtype=np.uint8).reshape(48, 64)
    with SequenceWriter(out) as writer:
        for offset_ms in (0, 1000, 1050, 1100, 1150):  # a 1 s pause, then 20 Hz
            writer.write(1_000_000_000 + offset_ms * 1_000_000, image)
    assert parse_replay_argument(f"{out}@pace") == (out, True)
    camera = make_camera(f"replay:{out}@pace")
    with camera:
        camera.start()
        started = time.monotonic()
        with pytest.raises(FrameTimeout):  # frame 1 is due 1 s after frame 0
            camera.next_frame(5.0)
            camera.next_frame(0.01)
        frames = [camera.next_frame(5.0) for _ in range(4)]
        elapsed = time.monotonic() - started
        with pytest.raises(EndOfStream):
            camera.next_frame(1.0)
    assert [f.frame_id for f in frames] == [1, 2, 3, 4]
    assert elapsed >= 1.15  # paced as recorded (no upper bound: the machine is shared)


def test_replay_drops_non_increasing_rows(tmp_path):
    out = tmp_path / "seq"
    data = camera_dir(out) / "data"
    data.mkdir(parents=True)
    for stamp in (10, 20, 30):
        cv2.imwrite(str(data / f"{stamp}.png"), np.full((8, 8), stamp, np.uint8))
    (camera_dir(out) / "data.csv").write_text("#timestamp [ns],filename\n10,10.png\n30,30.png\n20,20.png\n")
    frames, stats = replay_all(out)
    assert [f.stamp_ns for f in frames] == [10, 30] and stats.bad_timestamp == 1
    assert frames[1].image[0, 0] == 30


def wait_for_rows(csv_path, rows, timeout_s=60):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if csv_path.exists() and csv_path.read_text().count("\n") > rows:
            return
        time.sleep(0.05)
    raise AssertionError(f"{csv_path}: fewer than {rows} rows after {timeout_s} s")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_during_record_leaves_a_valid_sequence(gv_fake, tmp_path, sig):
    out = tmp_path / "seq"
    process = subprocess.Popen(
        [sys.executable, "-m", "cubeloc.daemon.cli", "record", "--camera", f"aravis:{gv_fake.serial}",
         "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for_rows(camera_dir(out) / "data.csv", 5)
        process.send_signal(sig)
        stdout, stderr = process.communicate(timeout=30)
    finally:
        process.kill()
    assert process.returncode == 0, stderr
    assert "Traceback" not in stderr
    entries = read_sequence_index(out)
    assert len(entries) >= 5 and f"recorded {len(entries)} frames" in stdout
    on_disk = sorted((camera_dir(out) / "data").iterdir())
    assert [p.name for p in on_disk] == sorted(e.path.name for e in entries)  # no .part, no orphan
    for entry in entries:
        assert read_image(entry.path).shape == (1024, 1280)


def test_record_frames_from_replay_cli(cli, tmp_path):
    source = tmp_path / "source"
    image = np.full((48, 64), 7, np.uint8)
    with SequenceWriter(source) as writer:
        for k in range(6):
            writer.write(1000 + k, image)
    result = cli("record", "--camera", f"replay:{source}", "--out", str(tmp_path / "copy"), "--frames", "4")
    assert result.returncode == 0, result.stderr
    assert [e.stamp_ns for e in read_sequence_index(tmp_path / "copy")] == [1000, 1001, 1002, 1003]


def assert_user_error(result, *fragments):
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def test_unknown_camera_id_is_a_one_line_error(cli, tmp_path):
    out = tmp_path / "never"
    result = cli("record", "--camera", "aravis:no-such-camera", "--out", str(out),
                 env={**_env(tmp_path), "CUBELOC_LOGGING__LEVEL": "error"})
    assert_user_error(result, "no camera 'no-such-camera'", "cubeloc devices")
    assert not out.exists()  # nothing half-written
    assert_user_error(cli("record", "--camera", "gopro:1", "--out", str(out)), "unknown camera source")


def test_unreadable_sequence_is_a_one_line_error(cli, tmp_path):
    bad = tmp_path / "bad"
    camera_dir(bad).mkdir(parents=True)
    (camera_dir(bad) / "data.csv").write_text("#timestamp [ns],filename\nsoon,1.png\n")
    assert_user_error(cli("record", "--camera", f"replay:{bad}", "--out", str(tmp_path / "o")),
                      "data.csv:2", "'soon' is not an integer")
    # a frame that cannot be read is a camera's bad frame: dropped, counted, named
    (camera_dir(bad) / "data.csv").write_text("#timestamp [ns],filename\n1,1.png\n")
    dropped = cli("record", "--camera", f"replay:{bad}", "--out", str(tmp_path / "o2"))
    assert dropped.returncode == 0 and "Traceback" not in dropped.stderr, dropped.stderr
    assert "1.png: image not found" in dropped.stderr and "1 incomplete" in dropped.stdout, dropped
    assert_user_error(cli("record", "--camera", f"replay:{tmp_path / 'nowhere'}", "--out", str(tmp_path / "o3")),
                      "sequence directory not found")
    existing = tmp_path / "existing"
    with SequenceWriter(existing) as writer:
        writer.write(1, np.zeros((4, 4), np.uint8))
    assert_user_error(cli("record", "--camera", f"replay:{existing}", "--out", str(existing)),
                      "a sequence is already there")


def _env(tmp_path):
    import os

    return {**os.environ, "CUBELOC_LOCK_DIR": str(tmp_path / "locks")}


def test_record_with_odometry_keeps_what_the_robot_sends_as_it_arrived(cli, tmp_path):
    """``--odometry``: the samples that arrive over Zenoh on [odometry]'s key while the
    frames are recorded go to DIR/odometry.jsonl, readable by calibrate-mount and track; an
    unreadable one is counted, not kept."""
    import json

    import zenoh

    from cubeloc.daemon.odometry_in import read_odometry_file
    from cubeloc.net import free_port

    source = tmp_path / "source"
    image = np.full((48, 64), 7, np.uint8)
    with SequenceWriter(source) as writer:
        for k in range(40):  # 2 s at the recorded pace
            writer.write(1_000_000_000 + k * 50_000_000, image)
    port = free_port()
    config = tmp_path / "cubeloc.toml"
    config.write_text(f'name = "rec"\n[zenoh]\nmulticast_scouting = false\nconnect = ["tcp/127.0.0.1:{port}"]\n'
                      '[odometry]\nenabled = true\nsource = "json"\n')
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    session = zenoh.open(conf)
    done = threading.Event()

    def wheels():  # 50 Hz, stamped as measured, one unreadable sample among them
        k = 0
        while not done.is_set():
            stamp = time.time_ns()
            session.put("cubeloc/rec/odometry", b"{broken" if k == 5 else json.dumps({
                "schema": "cubeloc.odometry/1", "stamp_ns": stamp, "frame_id": "odom", "child_frame_id": "base_link",
                "position": [0.01 * k, 0.0, 0.0], "orientation": [0.0, 0.0, 0.0, 1.0]}))
            k += 1
            time.sleep(0.02)

    sender = threading.Thread(target=wheels, daemon=True)
    sender.start()
    try:
        result = cli("record", "--camera", f"replay:{source}@pace", "--out", str(tmp_path / "drive"), "--odometry",
                     "--config", str(config))
    finally:
        done.set()
        sender.join()
        session.close()
    assert result.returncode == 0, result.stderr
    rows = read_odometry_file(tmp_path / "drive" / "odometry.jsonl")
    assert len(rows) >= 10, result.stdout
    assert f"recorded {len(rows)} odometry samples" in result.stdout
    stamps = [stamp for _, stamp, _, _ in rows]
    assert stamps == sorted(stamps) and all(arrival >= stamp for arrival, stamp, _, _ in rows)
    assert all(position[1:] == [0.0, 0.0] for _, _, position, _ in rows)
    assert len(read_sequence_index(tmp_path / "drive")) == 40


def test_record_odometry_needs_a_sequence(cli, tmp_path):
    assert_user_error(cli("record", "--mcap", str(tmp_path / "x.mcap"), "--odometry"), "record --odometry: give --out")
