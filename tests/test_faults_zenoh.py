"""Zenoh faults under the running daemon: the router it connects to is killed and restarted on
the same port, a slow subscriber (a process that stops reading) and a crowd of subscribers.
Real Zenoh sessions on loopback, the router and the slow subscriber in their own processes.
The frame loop must never wait for the network: frames processed during each fault are
counted against the same run's rate before the fault, with a margin for a loaded machine
(a publication that waited, as with congestion control BLOCK, costs most of them). The single-frame target-pose processor (milliseconds a frame) keeps the loop at the
camera's rate, so a publication that waited would show as missing frames, not as noise
from a tracker's bundle adjustment on a loaded machine."""

from __future__ import annotations

import json
import signal
import threading
import time

import pytest
import structlog
from helpers import ROUTER, end_process, helper_process, wait_until

from cubeloc.daemon.preflight import prepare_on_loopback
from cubeloc.daemon.sdnotify import SystemdNotifier
from cubeloc.daemon.service import Daemon
from cubeloc.fakes.faulty import CyclingCamera, FaultyCamera, orbit_frames
from cubeloc.net import free_port
from cubeloc.positioning.single_frame import TargetPoseProcessor
from cubeloc.positioning.target_pose import PoseOptions

FPS = 10.0

# A subscriber that reads slowly, in a process of its own (helpers.helper_process).
SLOW_SUBSCRIBER = """
import json, sys, time, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
conf.insert_json5("transport/link/tcp/so_rcvbuf", "4096")  # a small window fills fast
session = zenoh.open(conf)
def slow(sample):
    time.sleep(0.5)  # a subscriber that cannot keep up
session.declare_subscriber("cubeloc/**", slow)
print("ready", flush=True)
sys.stdin.read()
"""


def session_to(endpoint: str, mode: str = "peer"):
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(conf)


class RunningDaemon:
    def __init__(self, tmp_path, zenoh_settings: dict, wait_serving: bool = True) -> None:
        images, poses = orbit_frames(6, room=False)
        self.camera = CyclingCamera(images, poses, fps=FPS, name="zenoh")
        port = free_port()
        prepared = prepare_on_loopback(tmp_path, port, "zfault", camera={"width": 1280, "height": 1024},
                                       logging={"level": "warning"})
        config = prepared.config.model_copy(update={
            "zenoh": prepared.config.zenoh.model_validate({"multicast_scouting": False, **zenoh_settings}),
            "daemon": prepared.config.daemon.model_copy(update={"status_period_s": 0.25}),
        })
        prepared = type(prepared)(config, prepared.calibration, prepared.calibration_yaml, prepared.target)
        self.endpoint = f"tcp/127.0.0.1:{port}"
        self.stop = threading.Event()
        processor = TargetPoseProcessor(prepared.target, prepared.calibration, PoseOptions())
        self.daemon = Daemon(prepared, self.stop, camera_factory=FaultyCamera(self.camera), notifier=SystemdNotifier({}),
                             processor=processor)
        self.outcome: dict = {}
        self.thread = threading.Thread(target=lambda: self.outcome.setdefault("code", self.daemon.run()), daemon=True)
        self.thread.start()
        if wait_serving:
            assert self.daemon.serving.wait(30)

    @staticmethod
    def starting(running, zenoh_settings: dict) -> RunningDaemon:
        """A daemon not expected to serve yet (``running`` builds and cleans it up)."""
        return running(zenoh_settings, wait_serving=False)

    def frames_during(self, seconds: float, action=None) -> int:
        """Frames the loop processed in ``seconds`` (after ``action``, if any)."""
        if action is not None:
            action()
        before = self.daemon.stats.frames
        time.sleep(seconds)
        return self.daemon.stats.frames - before

    def close(self) -> int:
        self.stop.set()
        self.thread.join(5.0)
        assert not self.thread.is_alive()
        return self.outcome.get("code")


@pytest.fixture
def running(tmp_path):
    made = []

    def start(zenoh_settings, wait_serving=True):
        made.append(RunningDaemon(tmp_path, zenoh_settings, wait_serving))
        return made[-1]

    yield start
    for daemon in made:
        if daemon.thread.is_alive():
            daemon.close()


def test_router_killed_and_restarted_poses_resume_and_the_loop_never_waits(running):
    router_endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = helper_process(ROUTER, router_endpoint)
    daemon = running({"mode": "peer", "connect": [router_endpoint]})
    robot = session_to(router_endpoint, mode="client")
    poses: list[tuple[float, dict]] = []
    robot.declare_subscriber("cubeloc/zfault/pose", lambda s: poses.append((time.monotonic(), json.loads(s.payload.to_bytes()))))
    try:
        assert wait_until(lambda: len(poses) >= 5), "no poses through the router"
        baseline = daemon.frames_during(1.5)
        assert baseline >= 5
        router.kill()  # the robot's router dies: every link through it drops at once
        router.wait(10)
        # a pose already in the robot's socket when the router died may still be handed over
        lost_at = time.monotonic() + 0.5
        poses_before = daemon.daemon.stats.poses
        during = daemon.frames_during(1.5)
        assert during >= 0.5 * baseline, (baseline, during)  # the loop did not wait for the network
        assert daemon.daemon.stats.poses > poses_before  # and kept positioning (publishing into the void)
        router = helper_process(ROUTER, router_endpoint)  # back, on the same port
        back_at = time.monotonic()
        assert wait_until(lambda: poses[-1][0] > back_at, 40), "poses did not resume after the router came back"
        gap = [p for t, p in poses if lost_at <= t <= back_at]
        assert not gap  # nothing can arrive while the router is down
        seqs = [p["seq"] for _, p in poses]
        assert seqs == sorted(seqs)
        assert daemon.daemon.stats.frames > poses[-1][1]["seq"] - 200  # the loop ran on throughout
    finally:
        robot.close()
        end_process(router)
        assert daemon.close() == 0


def test_client_daemon_waits_for_a_router_that_is_not_up_yet(running):
    # Client mode: Zenoh will not open a session without a router. Exiting would be exit
    # 2, which the systemd unit does not restart (RestartPreventExitStatus=2): at boot the
    # daemon would stay down for good. It waits for the router instead.
    router_endpoint = f"tcp/127.0.0.1:{free_port()}"
    with structlog.testing.capture_logs() as logs:
        daemon = RunningDaemon.starting(running, {"mode": "client", "connect": [router_endpoint]})
        assert wait_until(lambda: sum(e["event"] == "zenoh router unreachable, retrying" for e in logs) >= 2, 20)
    assert daemon.thread.is_alive()  # waiting, not failed
    router = helper_process(ROUTER, router_endpoint)
    robot = session_to(router_endpoint, mode="client")
    poses: list[dict] = []
    robot.declare_subscriber("cubeloc/zfault/pose", lambda s: poses.append(json.loads(s.payload.to_bytes())))
    try:
        assert daemon.daemon.serving.wait(30)
        assert wait_until(lambda: len(poses) >= 3), "no poses once the router was up"
    finally:
        robot.close()
        assert daemon.close() == 0
        end_process(router)


def test_client_daemon_stopped_while_waiting_for_the_router_exits_0(running):
    daemon = RunningDaemon.starting(running, {"mode": "client", "connect": [f"tcp/127.0.0.1:{free_port()}"]})
    assert not daemon.daemon.serving.wait(1.0)
    assert daemon.close() == 0


def test_stalled_subscriber_never_blocks_the_loop(running, tmp_path):
    # Small send buffers on the daemon's side so that a reader that stopped fills them
    # within a second or two (with the defaults it takes minutes at a few kB/s).
    small = tmp_path / "small-buffers.json5"
    small.write_text('{transport: {link: {tx: {batch_size: 2048}, tcp: {so_sndbuf: 4096}}}}')
    daemon = running({"listen": [f"tcp/127.0.0.1:{free_port()}"], "config_file": small})
    daemon_endpoint = daemon.daemon.config.zenoh.listen[0]
    slow = helper_process(SLOW_SUBSCRIBER, daemon_endpoint)
    healthy = session_to(daemon_endpoint)
    poses: list[float] = []
    healthy.declare_subscriber("cubeloc/zfault/pose", lambda s: poses.append(time.monotonic()))
    try:
        assert wait_until(lambda: len(poses) >= 5)
        baseline = daemon.frames_during(1.5)
        assert baseline >= 5
        slow.send_signal(signal.SIGSTOP)  # it stops reading altogether: its window fills
        stalled_at = time.monotonic()
        during = daemon.frames_during(3.0)
        assert during >= 0.5 * 2 * baseline, (baseline, during)
        # the healthy subscriber kept getting poses all along
        assert sum(1 for t in poses if t > stalled_at) >= 0.5 * during
        slow.send_signal(signal.SIGCONT)
    finally:
        healthy.close()
        end_process(slow)
        assert daemon.close() == 0


def test_a_crowd_of_subscribers_all_get_poses_and_the_loop_keeps_its_rate(running):
    daemon = running({"listen": [f"tcp/127.0.0.1:{free_port()}"]})
    endpoint = daemon.daemon.config.zenoh.listen[0]
    baseline = daemon.frames_during(1.5)
    assert baseline >= 5
    sessions, counts = [], []
    try:
        for i in range(12):
            session = session_to(endpoint)
            sessions.append(session)
            for key in ("cubeloc/zfault/pose", "cubeloc/**", "cubeloc/*/status", "cubeloc/zfault/*"):
                counts.append(0)
                index = len(counts) - 1

                def bump(_sample, index=index) -> None:
                    counts[index] += 1

                session.declare_subscriber(key, bump)
            assert i < 11 or wait_until(lambda: min(counts) > 0)
        during = daemon.frames_during(1.5)
        assert during >= 0.5 * baseline, (baseline, during)
        before = list(counts)
        assert wait_until(lambda: all(c > b for c, b in zip(counts, before, strict=True)))  # all still served
    finally:
        for session in sessions:
            session.close()
        assert daemon.close() == 0
