"""Camera faults under the running daemon: one run of the real ``Daemon`` (capture thread,
frame processor, real Zenoh on loopback) on pre-rendered frames (``fakes.faulty``) with a
schedule of faults at the driver boundary, a subscriber checking every pose against the
ground truth. Each test below reads one fault's outcome from that run: logged, counted on
``status``, recovered from, and no wrong pose published."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
import structlog

from cubeloc.daemon.capture import STAMP_RESTART_FRAMES
from cubeloc.daemon.preflight import prepare_on_loopback
from cubeloc.daemon.sdnotify import SystemdNotifier
from cubeloc.daemon.service import Daemon
from cubeloc.fakes.faulty import CyclingCamera, Fault, FaultyCamera, orbit_frames
from cubeloc.net import free_port
from cubeloc.positioning.geometry import quaternion_angle_deg

FPS = 30.0
WRONG_POSITION_M = 0.02
WRONG_ANGLE_DEG = 1.0
SCHEDULE = {  # frame number -> fault
    10: Fault("incomplete", fraction=0.5),
    14: Fault("frame_id_jump", count=500),
    18: Fault("stamp_back", seconds=0.35),
    22: Fault("wrong_size"),
    26: Fault("wrong_format", format="mono16"),
    30: Fault("wrong_format", format="rgb8"),
    34: Fault("timeout", seconds=0.5),  # one timeout (frame_timeout_s 0.3): no reconnect
    44: Fault("timeout", seconds=1.6),  # three timeouts in a row: the camera is reopened
    60: Fault("unplug", seconds=1.0),  # StreamBroken, then no such device for a second
    80: Fault("wrong_format", count=50),  # 1.7 s of nothing usable: status says so
    150: Fault("clock_step", seconds=30.0),  # the host clock stepped back (NTP)
}
LAST_FRAME = 190


class Subscriber:
    """Poses and status as a robot sees them; every pose checked on arrival."""

    def __init__(self, port: int, camera: FaultyCamera, truth: CyclingCamera) -> None:
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        self.camera, self.truth = camera, truth
        self.poses: list[dict] = []
        self.status: list[dict] = []
        self.wrong: list[str] = []
        self.timeline = 0
        self.session = zenoh.open(conf)
        self.session.declare_subscriber("cubeloc/faults/pose", self._on_pose)
        self.session.declare_subscriber("cubeloc/faults/status", lambda s: self.status.append(json.loads(s.payload.to_bytes())))

    def _on_pose(self, sample) -> None:
        pose = json.loads(sample.payload.to_bytes())
        pose["received"] = time.monotonic()
        if self.poses and pose["stamp_ns"] <= self.poses[-1]["stamp_ns"]:
            self.timeline += 1  # only legitimate after a clock step; checked by the tests
        pose["timeline"] = self.timeline
        self.poses.append(pose)
        shifts = self.camera.shifts_ns
        shift = shifts[min(self.timeline, len(shifts) - 1)]
        truth = self.truth.ground_truth(pose["stamp_ns"] + shift)
        if pose["stamp_ns"] in self.camera.bad_stamps or truth is None:
            self.wrong.append(f"seq {pose['seq']}: stamp {pose['stamp_ns']} is no good frame's")
            return
        error_m = float(np.linalg.norm(np.array(pose["position"]) - truth.translation))
        error_deg = quaternion_angle_deg(pose["orientation"], truth.quaternion())
        if error_m > WRONG_POSITION_M or error_deg > WRONG_ANGLE_DEG:
            self.wrong.append(f"seq {pose['seq']}: {1000 * error_m:.1f} mm, {error_deg:.2f} deg off")


def fault_frame_time(camera: FaultyCamera, kind: str) -> float:
    """When (monotonic) the faulty camera delivered the first fault of ``kind``."""
    return next(entry[3] for entry in camera.timed_log if entry[1] == kind)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    images, poses = orbit_frames(6, room=False)
    truth = CyclingCamera(images, poses, fps=FPS, name="faults")
    camera = FaultyCamera(truth, dict(SCHEDULE))
    camera.timed_log = []
    original_inject = camera._inject

    def inject(fault, frame, timeout_s):  # note when each fault happened
        camera.timed_log.append(("fault", fault.kind, camera.frames, time.monotonic()))
        return original_inject(fault, frame, timeout_s)

    camera._inject = inject
    port = free_port()
    prepared = prepare_on_loopback(tmp_path_factory.mktemp("faults"), port, "faults",
                                   camera={"width": 1280, "height": 1024}, logging={"level": "warning"})
    config = prepared.config.model_copy(update={
        "camera": prepared.config.camera.model_copy(update={"frame_timeout_s": 0.3}),
        "daemon": prepared.config.daemon.model_copy(update={"status_period_s": 0.2, "timeout_streak": 3}),
    })
    prepared = type(prepared)(config, prepared.calibration, prepared.calibration_yaml, prepared.target)
    stop = threading.Event()
    daemon = Daemon(prepared, stop, camera_factory=camera, notifier=SystemdNotifier({}))
    outcome = {}
    thread = threading.Thread(target=lambda: outcome.setdefault("code", daemon.run()), daemon=True)
    subscriber = None
    with structlog.testing.capture_logs() as logs:
        thread.start()
        try:
            assert daemon.serving.wait(30)
            subscriber = Subscriber(port, camera, truth)
            deadline = time.monotonic() + 60
            while camera.frames < LAST_FRAME and thread.is_alive() and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.5)  # the last status and poses
        finally:
            stop.set()
            thread.join(5.0)
            if subscriber is not None:
                subscriber.session.close()
    assert not thread.is_alive() and outcome.get("code") == 0, outcome
    assert camera.frames >= LAST_FRAME, f"the run stalled at frame {camera.frames}"
    return {"camera": camera, "subscriber": subscriber, "logs": logs, "daemon": daemon}


def faults(run) -> dict:
    return run["subscriber"].status[-1]["extra"]["faults"]


def events(run) -> list[str]:
    return [entry["event"] for entry in run["logs"]]


def poses_after(run, kind: str) -> list[dict]:
    at = fault_frame_time(run["camera"], kind)
    return [p for p in run["subscriber"].poses if p["received"] > at]


def test_no_wrong_pose_published_under_any_fault(run):
    subscriber = run["subscriber"]
    assert len(subscriber.poses) >= 20
    assert subscriber.wrong == []
    # stamps strictly increase within a timeline; one new timeline, after the clock step
    assert max(p["timeline"] for p in subscriber.poses) <= 1
    seqs = [p["seq"] for p in subscriber.poses]
    assert seqs == sorted(set(seqs))


def test_incomplete_frame_gives_no_wrong_pose_and_poses_continue(run):
    assert poses_after(run, "incomplete")  # (the accuracy of every pose: test above)


def test_frame_id_jump_is_counted_and_logged(run):
    assert faults(run)["frame_id_jump"] >= 1
    assert "frame id jumped" in events(run)
    jump = next(e for e in run["logs"] if e["event"] == "frame id jumped")
    assert jump["frame_id"] - jump["previous"] == 501
    assert poses_after(run, "frame_id_jump")


def test_non_monotonic_timestamp_is_dropped_counted_and_logged(run):
    # the one injected, and the frames after the clock step until it counts as a step
    assert faults(run)["stamp_not_increasing"] == 1 + STAMP_RESTART_FRAMES - 1
    assert "frame dropped: timestamp not after the previous frame's" in events(run)
    assert run["camera"].bad_stamps and not {p["stamp_ns"] for p in run["subscriber"].poses} & run["camera"].bad_stamps


def test_wrong_size_frame_is_dropped_counted_and_logged(run):
    assert faults(run)["wrong_size"] == 1
    entry = next(e for e in run["logs"] if e["event"] == "frame dropped: size differs from the camera settings")
    assert entry["size"] == "640x512" and entry["expected"] == "1280x1024"


def test_wrong_pixel_format_is_dropped_counted_and_logged(run):
    # one Mono16 frame, one RGB8 frame, then 50 frames in a row
    assert faults(run)["bad_format"] == 52
    assert "frame dropped: not Mono8" in events(run)
    assert run["subscriber"].status[-1]["extra"]["processor_errors"] == 0  # never reached it


def test_only_bad_frames_shows_on_status_then_recovers(run):
    states = [s["state"] for s in run["subscriber"].status]
    assert "bad_frames" in states
    first_bad = states.index("bad_frames")
    assert any(state in ("target", "tracking") for state in states[first_bad:])
    bad = run["subscriber"].status[first_bad]
    assert bad["camera"]["state"] == "streaming" and "not Mono8" in bad["detail"]


def test_frame_timeouts_are_counted_and_a_streak_reopens_the_camera(run):
    counted = faults(run)
    assert counted["frame_timeout"] >= 4  # one alone, then a streak of three
    assert events(run).count("no frame within the timeout") >= 4
    reasons = [e["reason"] for e in run["logs"] if e["event"] == "camera lost, reconnecting"]
    assert "3 frame timeouts in a row" in reasons
    assert poses_after(run, "timeout")


def test_a_camera_gone_quiet_shows_at_its_first_timeout_with_a_rate_of_0(run):
    """From the first frame timeout status says ``no_frames`` and fps 0 (before: the last
    rate stayed on for the ~3 s of the rate's window, and the state said streaming until
    a streak of timeouts reopened the camera); frames back, ``streaming`` again."""
    status = run["subscriber"].status
    quiet = [s for s in status if s["camera"]["state"] == "no_frames"]
    assert quiet and all(s["state"] == "no_frames" and s["fps"] == 0.0 for s in quiet), quiet[:3]
    assert "no frame for 0.3 s" in {s["camera"]["detail"] for s in quiet}
    gone = [s for s in status if s["camera"]["state"] == "reconnecting"]
    assert gone and all(s["fps"] == 0.0 for s in gone), gone[:3]
    first = status.index(quiet[0])
    assert any(s["camera"]["state"] == "streaming" and s["fps"] > 0 for s in status[first:])


def test_unplug_reconnects_and_poses_resume(run):
    camera, subscriber = run["camera"], run["subscriber"]
    reasons = [e["reason"] for e in run["logs"] if e["event"] == "camera lost, reconnecting"]
    assert any("injected unplug" in r for r in reasons)
    assert camera.failed_opens >= 1  # it stayed away a while
    assert subscriber.status[-1]["camera"]["reconnects"] >= 2
    assert "reconnecting" in [s["camera"]["state"] for s in subscriber.status]
    assert len(poses_after(run, "unplug")) >= 5


def test_clock_step_back_restarts_the_timeline_and_resets_the_processor(run):
    counted = faults(run)
    assert counted["clock_restart"] == 1
    assert "processor reset: the frame timeline restarted" in events(run)
    after = poses_after(run, "clock_step")
    assert after and after[-1]["timeline"] == 1  # poses resumed, on the new timeline


def test_frame_checks_at_the_boundary_one_by_one():
    from cubeloc.daemon.capture import CaptureThread
    from cubeloc.daemon.frame_queue import LatestFrameSlot
    from cubeloc.drivers.base import CameraSettings, Frame

    capture = CaptureThread("test", CameraSettings(width=4, height=3), LatestFrameSlot(), threading.Event())
    good = np.zeros((3, 4), np.uint8)

    def frame(frame_id, stamp_ns, image=good):
        return Frame(image, frame_id, stamp_ns, stamp_ns, 1000.0)

    assert capture._accept(frame(65534, 100))
    assert capture._accept(frame(65535, 200))
    assert capture._accept(frame(1, 300))  # a GigE Vision 1 block id wrapping (skips 0): no jump
    assert capture._accept(frame(5, 400))  # ids 2-4 never came: a jump
    assert not capture._accept(frame(6, 400))  # same stamp: dropped
    assert not capture._accept(frame(7, 500, good.astype(np.float32)))
    assert not capture._accept(frame(8, 500, np.zeros((3, 4, 3), np.uint8)))
    assert not capture._accept(frame(9, 500, np.zeros((4, 3), np.uint8)))  # transposed
    assert capture._accept(frame(10, 500))
    assert capture.faults() == {"bad_format": 2, "frame_id_jump": 1, "stamp_not_increasing": 1, "wrong_size": 1}
    assert "size 3x4" in capture.last_fault[1] and "expected 4x3" in capture.last_fault[1]  # for status.detail
