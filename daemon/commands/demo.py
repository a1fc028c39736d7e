"""``cubeloc demo``: the whole daemon on the synthetic camera, no camera or network needed.

The real daemon (daemon/service.py) runs on ``synthetic:TRAJECTORY`` in real time with an
embedded Zenoh peer listening on a loopback port; a second Zenoh session in the same
process subscribes to ``cubeloc/demo/pose`` and prints every pose as it arrives. At the
end the received poses are compared with the synthetic camera's ground truth.
"""

from __future__ import annotations

import math
import queue
import sys
import tempfile
import threading
import time
from pathlib import Path

from cubeloc.net import free_port


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="the daemon on the synthetic camera, poses printed live, accuracy against ground truth",
    )
    parser.add_argument("--trajectory", default="paper", help="synthetic trajectory: paper (default), static, orbit, room_walk")
    parser.add_argument("--seconds", type=float, default=20.0, help="length of the run (default 20)")
    parser.add_argument("--fps", type=float, default=10.0, help="camera frame rate (default 10, as in the paper)")
    parser.add_argument("--port", type=int, default=0, help="loopback TCP port of the embedded Zenoh peer (default: a free one)")
    parser.add_argument("--mode", choices=("tracker", "target"), default="tracker",
                        help="positioning.mode: the tracker (default) or the single-frame target pose")
    parser.add_argument("--quiet", action="store_true", help="only the summary, not one line per pose")
    parser.set_defaults(func=run)


class _RecordingFactory:
    """Builds cameras like the registry does, and keeps the last one for its ground truth."""

    def __init__(self) -> None:
        self.camera = None

    def __call__(self, source, settings):
        from cubeloc.daemon.cameras import make_camera

        self.camera = make_camera(source, settings)
        return self.camera


def _warm_up(source: str) -> None:
    """Render one frame before the clock starts: the first render builds the ray grid and
    the room's textures (seconds), which would otherwise eat the start of a real-time run."""
    from cubeloc.daemon.cameras import make_camera

    with make_camera(source) as camera:
        camera.start()
        camera.next_frame(60.0)
        camera.stop()


def run(args) -> int:
    import json

    import zenoh

    from cubeloc.calib.camera_info import paper_camera, write_camera_info
    from cubeloc.daemon.commands.echo import format_pose
    from cubeloc.daemon.config import Config
    from cubeloc.daemon.logs import configure_logging
    from cubeloc.daemon.preflight import prepare
    from cubeloc.daemon.service import Daemon
    from cubeloc.errors import ConfigError
    from cubeloc.positioning.target import default_cube_yaml

    if not (0 < args.seconds <= 600 and 0 < args.fps <= 100):
        raise ConfigError(f"--seconds {args.seconds:g} must be in (0, 600] and --fps {args.fps:g} in (0, 100]")
    # stdout is for the poses and the summary; the daemon's own logs: warnings, on stderr.
    configure_logging("warning", "console", stream=sys.stderr)
    port = args.port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with tempfile.TemporaryDirectory(prefix="cubeloc-demo-") as tmp:
        write_camera_info(Path(tmp) / "camera.yaml", paper_camera())
        (Path(tmp) / "target.yaml").write_text(default_cube_yaml())
        source = f"synthetic:{args.trajectory}?seconds={args.seconds:g}&fps={args.fps:g}&seed=1&realtime=1"
        config = Config.model_validate({
            "name": "demo",
            "camera": {"source": source},
            "positioning": {"calibration": Path(tmp) / "camera.yaml", "target": Path(tmp) / "target.yaml",
                            "mode": args.mode},
            "zenoh": {"mode": "peer", "listen": [endpoint], "multicast_scouting": False},
        })
        prepared = prepare(config)
        print("cubeloc demo: preparing the synthetic scene (the first render fills caches) ...", flush=True)
        _warm_up(source.replace("&realtime=1", ""))
        stop = threading.Event()
        factory = _RecordingFactory()
        daemon = Daemon(prepared, stop, camera_factory=factory)
        print(f"cubeloc demo: the daemon on {source}\n"
              f"  Zenoh peer on {endpoint}; from another terminal: cubeloc echo --connect {endpoint} --no-scouting",
              flush=True)
        outcome: dict = {}

        def run_daemon() -> None:
            try:
                outcome["code"] = daemon.run()
            except BaseException as exc:  # handed to the main thread, which re-raises it
                outcome["error"] = exc

        thread = threading.Thread(target=run_daemon, name="daemon", daemon=True)
        started = time.monotonic()
        thread.start()
        while not daemon.serving.wait(0.1) and thread.is_alive():
            pass  # the subscriber connects once the daemon's session listens
        if "error" in outcome:
            raise outcome["error"]

        # The subscriber: a separate session connected to the daemon's, as on a robot.
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        inbox: queue.Queue = queue.Queue()
        received = []
        with zenoh.open(conf) as session:
            session.declare_subscriber("cubeloc/demo/pose", lambda s: inbox.put(json.loads(s.payload.to_bytes())))
            try:
                while thread.is_alive() or not inbox.empty():
                    try:
                        doc = inbox.get(timeout=0.2)
                    except queue.Empty:
                        continue
                    received.append(doc)
                    if not args.quiet:
                        print(format_pose("demo", doc, daemon.stats.fps()), flush=True)
            except KeyboardInterrupt:
                stop.set()
                thread.join(3.0)
        elapsed = time.monotonic() - started
    if "error" in outcome:
        raise outcome["error"]
    print(summary(received, daemon, factory.camera, elapsed), flush=True)
    return 0


def summary(received: list[dict], daemon, camera, elapsed_s: float) -> str:
    """Accuracy against the synthetic camera's ground truth, and rates."""
    import numpy as np

    from cubeloc.positioning.geometry import Transform

    stats = daemon.stats
    errors_mm, angles_deg = [], []
    by_state: dict[str, list[float]] = {}
    for doc in received:
        truth = camera.ground_truth_at(doc["stamp_ns"]) if camera is not None else None
        if truth is None:
            continue
        errors_mm.append(1000 * float(np.linalg.norm(np.array(doc["position"]) - truth.translation)))
        by_state.setdefault(doc.get("state", "?"), []).append(errors_mm[-1])
        estimate = Transform.from_quaternion(np.array(doc["position"]), np.array(doc["orientation"]))
        angles_deg.append(math.degrees(estimate.rotation_angle_to(truth)))
    states = ", ".join(f"{state} {len(v)}" for state, v in sorted(by_state.items()))
    delivered = camera.stats.delivered if camera is not None else 0
    skipped = camera.stats.frame_id_gaps if camera is not None else 0
    latency = stats.latency_percentiles()
    lines = [
        "",
        "cubeloc demo: summary",
        f"  frames: {delivered} rendered by the synthetic camera ({skipped} skipped because rendering fell behind), "
        f"{stats.frames} processed, {daemon.slot.dropped} dropped by the newest-frame queue",
        f"  poses:  {len(received)} received by the subscriber ({stats.poses} published) "
        f"= {100 * len(received) / max(1, stats.frames):.0f}% of processed frames"
        f"{'; by state: ' + states if states else ''}",
        f"  rate:   {stats.frames / max(elapsed_s, 1e-9):.1f} frames/s processed over {elapsed_s:.1f} s wall time",
    ]
    if latency["p50"] is not None:
        lines.append(f"  latency (frame from the driver -> published): p50 {latency['p50']:.1f} ms, p99 {latency['p99']:.1f} ms")
    if errors_mm:
        e = np.array(errors_mm)
        lines.append(
            f"  position error vs ground truth: RMS {np.sqrt(np.mean(e ** 2)):.2f} mm, "
            f"median {np.median(e):.2f} mm, max {e.max():.2f} mm over {len(e)} poses"
        )
        lines.append(f"  orientation error: median {np.median(angles_deg):.3f} deg, max {max(angles_deg):.3f} deg")
        for state, values in sorted(by_state.items()):
            v = np.array(values)
            lines.append(f"    {state}: RMS {np.sqrt(np.mean(v ** 2)):.2f} mm over {len(v)} poses")
    else:
        lines.append("  position error: no pose to compare (was the cube ever in view?)")
    return "\n".join(lines)
