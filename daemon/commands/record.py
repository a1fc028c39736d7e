"""``cubeloc record --out DIR [--mcap OUT.mcap] [--camera SOURCE] [--frames N] [--seconds S] [--odometry]``.

Records any camera source (``aravis[:ID]``, ``replay:DIR``, ``synthetic:NAME``) into a
sequence in the EuRoC layout, and with ``--mcap`` (or instead of it) the camera image
channel of the Foxglove viewer (``/camera/image``, scaled and rate-limited by ``[foxglove]``,
with ``/camera/calibration`` when the config's calibration file is readable) into an MCAP
file. ``--odometry`` also records the robot's wheel odometry, as the config's ``[odometry]``
names it (source and topic, over the config's Zenoh), to ``DIR/odometry.jsonl``
(``cubeloc.odometry/1`` rows with their arrival time: ``cubeloc track --odometry``,
``cubeloc calibrate-mount``). Ctrl-C or SIGTERM only set the stop event; the recording loop ends and the writers
close, so what is on disk is a valid sequence and a finished MCAP file.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "record",
        help="record the camera to a sequence directory (EuRoC layout)",
        description="Record a camera to DIR/mav0/cam0/{data.csv,data/<ns>.png}. Stop with Ctrl-C "
        "or SIGTERM at any time: the sequence stays valid.",
    )
    parser.add_argument("--out", metavar="DIR", help="new sequence directory")
    parser.add_argument("--mcap", metavar="OUT.mcap", help="also (or only) the camera image as an MCAP file for Foxglove")
    parser.add_argument("--camera", metavar="SOURCE",
                        help="camera source (default: camera.source from the config), e.g. "
                        "aravis, aravis:SERIAL, aravis:192.168.1.20, replay:DIR")
    parser.add_argument("--frames", type=int, metavar="N", help="stop after N frames")
    parser.add_argument("--seconds", type=float, metavar="S", help="stop after S seconds")
    parser.add_argument("--odometry", action="store_true",
                        help="also record the wheel odometry that [odometry] names (source, topic; over [zenoh]) to "
                             "DIR/odometry.jsonl, for cubeloc calibrate-mount and cubeloc track --odometry")
    parser.add_argument("--config", metavar="FILE", help="TOML config (camera settings, logging)")
    parser.set_defaults(func=run)


def run(args) -> int:
    from cubeloc.daemon.cameras import make_camera
    from cubeloc.daemon.config import load_config
    from cubeloc.daemon.logs import configure_logging
    from cubeloc.drivers.recorder import record_sequence
    from cubeloc.drivers.sequence import SequenceWriter, camera_dir
    from cubeloc.errors import ConfigError, InputFileError

    if args.frames is not None and args.frames <= 0:
        raise ConfigError(f"--frames {args.frames}: expected a positive number of frames")
    if args.seconds is not None and args.seconds <= 0:
        raise ConfigError(f"--seconds {args.seconds}: expected a positive duration")
    if args.out is None and args.mcap is None:
        raise ConfigError("record: give --out DIR (a sequence), --mcap OUT.mcap, or both")
    if args.odometry and args.out is None:
        raise ConfigError("record --odometry: give --out DIR; the odometry goes to DIR/odometry.jsonl")
    config = load_config(args.config)
    configure_logging(config.logging.level, config.logging.format, stream=sys.stderr)
    out = Path(args.out) if args.out else None
    if out is not None and (camera_dir(out) / "data.csv").exists():
        raise InputFileError(f"{out}: a sequence is already there (choose another --out)")

    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    odometry = None
    try:
        camera = make_camera(args.camera or config.camera.source, config.camera.settings())
        with camera, contextlib.ExitStack() as wheels:  # the camera opened before the directory is made
            if args.odometry:
                odometry = wheels.enter_context(_odometry_in(config))
            camera.start()
            with contextlib.ExitStack() as stack:
                writer = _Writers(stack.enter_context(SequenceWriter(out)) if out is not None else None,
                                  stack.enter_context(_mcap(Path(args.mcap), config)) if args.mcap else None)
                summary = record_sequence(camera, writer, stop=stop, max_frames=args.frames,
                                          max_seconds=args.seconds,
                                          frame_timeout_s=config.camera.frame_timeout_s)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    stats = summary.stats
    where = " and ".join(str(p) for p in (out, args.mcap) if p is not None)
    print(f"recorded {summary.frames} frames in {summary.seconds:.1f} s to {where} "
          f"({summary.reason}); dropped: {stats.incomplete} incomplete, {stats.bad_timestamp} bad "
          f"timestamps, {stats.frame_id_gaps} frame-id gaps; reconnects: {stats.reconnects}")
    if odometry is not None:
        from cubeloc.jsonlines import write_json_lines

        path = out / "odometry.jsonl"
        write_json_lines(path, odometry.rows)
        dropped = ", ".join(f"{n} {reason}" for reason, n in odometry.stats.dropped.items()) or "none"
        print(f"recorded {len(odometry.rows)} odometry samples to {path} (dropped: {dropped})")
        if not odometry.rows:
            print(f"warning: no odometry arrived on {odometry.key}: is the robot's odometry running, and are "
                  "[odometry] source and topic right?", file=sys.stderr)
    return 0


@contextlib.contextmanager
def _odometry_in(config):
    """The wheel odometry that ``[odometry]`` names, kept as it arrives (an ``OdometryLog``,
    with the Zenoh key it listens on as ``key``), while the recording runs."""
    from cubeloc.daemon.odometry_in import OdometryInput, OdometryLog
    from cubeloc.daemon.zenoh_session import open_session

    kept = OdometryLog(config.frames.odom_frame, config.frames.base_frame, capacity=1,
                       stale_s=config.odometry.stale_s)
    session = open_session(config.zenoh, purpose="record")
    try:
        subscriber = OdometryInput(session, config, kept)
        kept.key = subscriber.key
        yield kept
        subscriber.close()
    finally:
        session.close()


class _Writers:
    """The sequence and the MCAP file as one writer (``record_sequence`` writes to it)."""

    def __init__(self, sequence, mcap) -> None:
        self.sequence, self.mcap, self.frames = sequence, mcap, 0

    def write(self, stamp_ns: int, image) -> None:
        from cubeloc.positioning.estimator import FrameResult

        if self.sequence is not None:
            self.sequence.write(stamp_ns, image)
        if self.mcap is not None:
            self.mcap.frame(stamp_ns, image, FrameResult(None, "recorded"))
        self.frames += 1


def _mcap(path: Path, config):
    """The MCAP recording, with the config's calibration where it can be read (for the
    Image panel's overlay); a recording needs no target."""
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.daemon.viewer import McapRecording
    from cubeloc.errors import CubelocError

    try:
        calibration = read_camera_info(config.positioning.calibration)
    except CubelocError:
        calibration = None
    return McapRecording(path, None, calibration, config.frames.robot_frames(), config.foxglove)
