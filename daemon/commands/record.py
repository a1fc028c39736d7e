"""``cubeloc record --out DIR [--camera SOURCE] [--frames N] [--seconds S]``.

Records any camera source (``aravis[:ID]``, ``replay:DIR``, ``synthetic:NAME``) into a
sequence in the EuRoC layout. Ctrl-C or SIGTERM only set the stop event; the recording
loop ends and the writer closes, so what is on disk is a valid sequence.
"""

from __future__ import annotations

import signal
import sys
import threading


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "record",
        help="record the camera to a sequence directory (EuRoC layout)",
        description="Record a camera to DIR/mav0/cam0/{data.csv,data/<ns>.png}. Stop with Ctrl-C "
        "or SIGTERM at any time: the sequence stays valid.",
    )
    parser.add_argument("--out", required=True, metavar="DIR", help="new sequence directory")
    parser.add_argument("--camera", metavar="SOURCE",
                        help="camera source (default: camera.source from the config), e.g. "
                        "aravis, aravis:SERIAL, aravis:192.168.1.20, replay:DIR")
    parser.add_argument("--frames", type=int, metavar="N", help="stop after N frames")
    parser.add_argument("--seconds", type=float, metavar="S", help="stop after S seconds")
    parser.add_argument("--config", metavar="FILE", help="TOML config (camera settings, logging)")
    parser.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from cubeloc.errors import ConfigError, InputFileError
    from daemon.cameras import make_camera
    from daemon.config import load_config
    from daemon.logs import configure_logging
    from drivers.recorder import record_sequence
    from drivers.sequence import SequenceWriter, camera_dir

    if args.frames is not None and args.frames <= 0:
        raise ConfigError(f"--frames {args.frames}: expected a positive number of frames")
    if args.seconds is not None and args.seconds <= 0:
        raise ConfigError(f"--seconds {args.seconds}: expected a positive duration")
    config = load_config(args.config)
    configure_logging(config.logging.level, config.logging.format, stream=sys.stderr)
    out = Path(args.out)
    if (camera_dir(out) / "data.csv").exists():
        raise InputFileError(f"{out}: a sequence is already there (choose another --out)")

    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        camera = make_camera(args.camera or config.camera.source, config.camera.settings())
        with camera:  # opened before the directory is made: a bad camera leaves nothing behind
            camera.start()
            with SequenceWriter(out) as writer:
                summary = record_sequence(camera, writer, stop=stop, max_frames=args.frames,
                                          max_seconds=args.seconds,
                                          frame_timeout_s=config.camera.frame_timeout_s)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    stats = summary.stats
    print(f"recorded {summary.frames} frames in {summary.seconds:.1f} s to {out} "
          f"({summary.reason}); dropped: {stats.incomplete} incomplete, {stats.bad_timestamp} bad "
          f"timestamps, {stats.frame_id_gaps} frame-id gaps; reconnects: {stats.reconnects}")
    return 0
