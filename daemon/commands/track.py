"""``cubeloc track --target T --calib C --sequence DIR --out OUT.tum``: the tracker offline.

Replays a recorded sequence (EuRoC layout) through the same ``TrackingProcessor`` the
daemon runs: initialisation on the target, then tracking, relocalisation and correction
by the target. Writes every frame with a pose to ``OUT.tum`` (T_world_camera, TUM
format, readable by ``evo_ape tum``), prints a summary line per state and, when
``DIR/groundtruth.tum`` exists, the RMS absolute trajectory error with no alignment.
A frame that cannot be read or has the wrong size is dropped and counted (``dropped N``
in the summary, a warning naming it), as a camera's bad frame; ``--strict`` stops there
with exit 2.

Bundle adjustment runs in the frame loop here (``--background-ba`` to run it in a worker
thread as the daemon does): offline there is no frame to miss, and the result does not
depend on thread timing, so two runs give the same trajectory.
"""

from __future__ import annotations

import sys
import time
from collections import Counter
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "track", help="the whole pipeline (initialisation on the target, then tracker) on a recorded sequence",
        description="Replay a sequence in the EuRoC layout through the tracker and write the "
                    "trajectory in the TUM format; prints the ATE when the sequence has groundtruth.tum.",
    )
    parser.add_argument("--target", required=True, metavar="FILE", help="target definition YAML")
    parser.add_argument("--calib", required=True, metavar="FILE", help="camera_info YAML of the camera")
    parser.add_argument("--sequence", required=True, metavar="DIR", help="sequence directory (mav0/cam0/...)")
    parser.add_argument("--out", required=True, metavar="OUT.tum", help="trajectory to write (TUM format)")
    parser.add_argument("--poses", metavar="OUT.jsonl",
                        help="also write the cubeloc.pose/1 payload of every frame with a pose, one JSON per line")
    parser.add_argument("--strict", action="store_true",
                        help="stop at the first frame that cannot be read or has the wrong size (exit 2); "
                             "by default it is dropped and counted, as a camera's bad frames are")
    parser.add_argument("--background-ba", action="store_true",
                        help="run bundle adjustment in a worker thread, as the daemon does")
    parser.set_defaults(func=run)


def run(args) -> int:
    from dataclasses import replace

    import structlog

    from calib.camera_info import read_camera_info
    from cubeloc.atomic import atomic_write_text
    from cubeloc.errors import InputFileError
    from daemon.logs import configure_logging
    from daemon.messages import UnpublishablePose, encode, pose_payload
    from drivers.sequence import read_mono_png, read_sequence_index
    from positioning.evaluation import absolute_trajectory_error
    from positioning.target import load_target
    from positioning.tracking.processor import ProcessorOptions, TrackingProcessor
    from positioning.trajectory_io import StampedPose, read_tum, write_tum

    configure_logging("warning", stream=sys.stderr)  # stdout is for the summary
    log = structlog.get_logger()
    target = load_target(args.target)
    calibration = read_camera_info(args.calib)
    entries = read_sequence_index(args.sequence)
    out = Path(args.out)
    for path in (out, Path(args.poses) if args.poses else None):
        if path is not None and not path.parent.is_dir():
            raise InputFileError(f"{path}: the directory {path.parent} does not exist")
    groundtruth_path = Path(args.sequence) / "groundtruth.tum"
    groundtruth = read_tum(groundtruth_path) if groundtruth_path.is_file() else None

    defaults = ProcessorOptions()
    options = replace(defaults, tracker=replace(
        defaults.tracker, bundle=replace(defaults.tracker.bundle, background=bool(args.background_ba))))
    processor = TrackingProcessor(target, calibration, options)
    poses: list[StampedPose] = []
    payloads: list[str] = []
    states: Counter[str] = Counter()
    started = time.perf_counter()
    try:
        for seq, entry in enumerate(entries):
            try:
                image = read_mono_png(entry.path)
                if image.shape != (calibration.height, calibration.width):
                    raise InputFileError(
                        f"{entry.path}: image is {image.shape[1]}x{image.shape[0]} but {args.calib} is for "
                        f"{calibration.width}x{calibration.height}"
                    )
            except InputFileError as exc:
                if args.strict:
                    raise
                states["dropped"] += 1
                log.warning("track.frame_dropped", seq=seq, error=str(exc))
                continue
            result = processor.process(image, entry.stamp_ns, seq)
            if result.estimate is not None:
                poses.append(StampedPose(entry.stamp_ns, result.estimate.T_world_camera))
                states[result.estimate.state.value] += 1
                if args.poses:
                    try:
                        payloads.append(encode(pose_payload(seq, entry.stamp_ns, result.estimate)).decode())
                    except UnpublishablePose as exc:  # as the daemon: such a frame publishes nothing
                        log.warning("track.unpublishable", seq=seq, error=str(exc))
            else:
                states[result.status] += 1
    finally:
        processor.close()
    elapsed = time.perf_counter() - started
    write_tum(out, poses)
    if args.poses:
        atomic_write_text(Path(args.poses), "".join(line + "\n" for line in payloads))
    summary = ", ".join(f"{name} {count}" for name, count in states.most_common())
    print(f"{len(entries)} frames in {elapsed:.1f} s ({len(entries) / max(elapsed, 1e-9):.1f} fps): {summary}")
    print(f"wrote {len(poses)} poses to {out}" + (f" and {args.poses}" if args.poses else ""))
    if groundtruth is not None:
        if not poses:
            print("no pose to compare with the ground truth", file=sys.stderr)
            return 1
        try:
            ate = absolute_trajectory_error(groundtruth, poses)
        except ValueError as exc:
            raise InputFileError(f"{groundtruth_path}: {exc}") from None
        print(f"ATE (no alignment, {ate.count} poses): RMS {ate.rmse_m * 1000:.2f} mm, "
              f"median {ate.median_m * 1000:.2f} mm, max {ate.max_m * 1000:.2f} mm")
    return 0
