"""``cubeloc track --target T --calib C --sequence DIR --out OUT.tum``: the tracker offline.

Replays a recorded sequence (EuRoC layout) through the same ``TrackingProcessor`` the
daemon runs (``daemon.replay.track_sequence``, the library function; this command adds the
outputs): initialisation on the target, then tracking, relocalisation and correction
by the target. Writes every frame with a pose to ``OUT.tum`` (T_world_camera, TUM
format, readable by ``evo_ape tum``) and ``OUT.png`` (daemon/plots.py: the trajectory from above coloured
by state, the error over time), prints a summary line per state and, when
``DIR/groundtruth.tum`` exists, the RMS absolute trajectory error with no alignment.
``--mcap OUT.mcap`` also writes the Foxglove viewer's channels (daemon/viewer.py).
A frame that cannot be read or has the wrong size is dropped and counted (``dropped N``
in the summary, a warning naming it), as a camera's bad frame; ``--strict`` stops there
with exit 2.

Bundle adjustment runs in the frame loop here (``--background-ba`` to run it in a worker
thread as the daemon does): offline there is no frame to miss, and the result does not
depend on thread timing, so two runs give the same trajectory.
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

MAP_KEYFRAMES = 400  # a map to save or loaded keeps this many keyframes by default (~17 kB each)


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
                        help="also write the cubeloc.pose/3 payload of every frame with a pose, one JSON per line "
                             "(latency_ns null: not published live)")
    parser.add_argument("--strict", action="store_true",
                        help="stop at the first frame that cannot be read or has the wrong size (exit 2); "
                             "by default it is dropped and counted, as a camera's bad frames are")
    parser.add_argument("--background-ba", action="store_true",
                        help="run bundle adjustment in a worker thread, as the daemon does")
    parser.add_argument("--odometry", metavar="FILE.jsonl",
                        help="wheel odometry to replay with the frames: cubeloc.odometry/1 documents, one per "
                             "line in the order they arrived (each from its arrival_ns, else its stamp_ns)")
    parser.add_argument("--mcap", metavar="OUT.mcap",
                        help="also write the Foxglove viewer's channels (image, tags, features, pose, trajectory, "
                             "target) to an MCAP file, timed by the frames' stamps, to open in Foxglove")
    parser.add_argument("--map", metavar="MAP", help="start from a saved map (cubeloc.map/1): relocalise in it "
                        "without the cube")
    parser.add_argument("--save-map", metavar="MAP", help="write the map at the end of the sequence (cubeloc.map/1)")
    parser.add_argument("--map-keyframes", type=int, default=None, metavar="N",
                        help="keyframes the map keeps (oldest dropped first); default 40, 400 with --save-map")
    parser.add_argument("--first", type=int, default=0, metavar="N",
                        help="replay from frame N (0-based) of the sequence; the frames before it are skipped "
                             "and the ATE is over the frames replayed")
    parser.add_argument("--no-plot", action="store_true", help="do not write OUT.png (the trajectory and error plot)")
    parser.add_argument("--config", metavar="FILE",
                        help="a cubeloc.toml: its [positioning] face and residual limits and loop_closure, as "
                             "the daemon takes them; its [frames] (the camera's mount) and [odometry] (its error "
                             "model) with --odometry")
    parser.set_defaults(func=run)


def run(args) -> int:
    import structlog

    from cubeloc.atomic import atomic_write_text
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.daemon.config import Config, load_config
    from cubeloc.daemon.logs import configure_logging
    from cubeloc.daemon.messages import UnpublishablePose, encode, pose_payload
    from cubeloc.daemon.preflight import odometry_prior, processor_options
    from cubeloc.daemon.replay import OdometryReplay, track_sequence
    from cubeloc.drivers.sequence import read_sequence_index
    from cubeloc.errors import InputFileError
    from cubeloc.positioning.evaluation import absolute_trajectory_error
    from cubeloc.positioning.target import load_target
    from cubeloc.positioning.trajectory_io import StampedPose, read_tum, write_tum

    configure_logging("warning", stream=sys.stderr)  # stdout is for the summary
    log = structlog.get_logger()
    target = load_target(args.target)
    calibration = read_camera_info(args.calib)
    entries = read_sequence_index(args.sequence)
    if args.first < 0 or args.first >= max(len(entries), 1):
        raise InputFileError(f"--first {args.first}: {args.sequence} has {len(entries)} frames (0 to {len(entries) - 1})")
    out = Path(args.out)
    config = load_config(args.config) if args.config else Config()
    for path in (out, args.poses, args.save_map):  # (--mcap: McapRecording checks its own)
        if path is not None and not Path(path).parent.is_dir():
            raise InputFileError(f"{path}: the directory {Path(path).parent} does not exist")
    groundtruth_path = Path(args.sequence) / "groundtruth.tum"
    groundtruth = read_tum(groundtruth_path) if groundtruth_path.is_file() else None

    keyframes = args.map_keyframes if args.map_keyframes is not None else (
        MAP_KEYFRAMES if args.save_map or args.map else None)
    if keyframes is not None and keyframes < 2:
        raise InputFileError(f"--map-keyframes {keyframes}: at least 2")
    options = processor_options(config, keyframes, background=bool(args.background_ba))
    odometry = prior = None
    if args.odometry:
        odometry = OdometryReplay.read(Path(args.odometry), config.odometry.buffer())  # a bad file stops here
        prior = odometry_prior(config, odometry.buffer)
        if not config.frames.enabled:
            print("warning: no [frames.base_from_camera] (--config): the camera is taken for the robot's base",
                  file=sys.stderr)
    start_map = None
    if args.map:
        from cubeloc.positioning.tracking.map_file import load_map

        start_map, _ = load_map(Path(args.map), calibration, target)  # a bad file stops here, with one line
    recording = None
    if args.mcap:
        from cubeloc.daemon.viewer import McapRecording

        recording = McapRecording(Path(args.mcap), target, calibration, config.frames.robot_frames(),
                                  config.foxglove)
    try:
        replay = track_sequence(
            Path(args.sequence), calibration, target, options, odometry_prior=prior, odometry=odometry,
            start_map=start_map, first=args.first, strict=args.strict,
            on_frame=None if recording is None else
            lambda frame, image, _: recording.frame(frame.stamp_ns, image, frame.result))
    finally:
        if recording is not None:
            recording.close()
    poses: list[StampedPose] = []
    pose_states: list[str] = []
    payloads: list[str] = []
    states: Counter[str] = Counter()
    sources: Counter[str] = Counter()
    for frame in replay.frames:
        if frame.result is None:
            states["dropped"] += 1
        elif frame.result.estimate is None:
            states[frame.result.status] += 1
        else:
            estimate = frame.result.estimate
            poses.append(StampedPose(frame.stamp_ns, estimate.T_world_camera))
            pose_states.append(estimate.state.value)
            states[estimate.state.value] += 1
            sources[estimate.source.value] += 1
            if args.poses:
                try:
                    payloads.append(encode(pose_payload(frame.seq, frame.stamp_ns, estimate)).decode())
                except UnpublishablePose as exc:  # as the daemon: such a frame publishes nothing
                    log.warning("track.unpublishable", seq=frame.seq, error=str(exc))
    if args.save_map:
        from cubeloc.positioning.tracking.map_file import save_map

        header = save_map(Path(args.save_map), replay.tracker.map, calibration, target)
        print(f"map: {header['keyframes']} keyframes, {header['points']} points to {args.save_map}")
    write_tum(out, poses)
    if args.poses:
        atomic_write_text(Path(args.poses), "".join(line + "\n" for line in payloads))
    if odometry is not None:
        stats = odometry.buffer.stats
        states["odometry samples"] = stats.received - sum(stats.dropped.values())
        for reason, count in stats.dropped.items():
            states[f"odometry dropped ({reason})"] = count
    summary = ", ".join(f"{name} {count}" for name, count in states.most_common())
    if sources:  # what measured the poses (README, "Reading a pose": the pose's source)
        summary += "; poses from " + ", ".join(f"{name} {count}" for name, count in sources.most_common())
    tracker = replay.tracker
    if tracker.loops_closed or tracker.loops_refused:
        summary += f"; loops closed {tracker.loops_closed}, refused {tracker.loops_refused}"
    replayed, elapsed = len(replay.frames), replay.seconds
    print(f"{replayed} frames in {elapsed:.1f} s ({replayed / max(elapsed, 1e-9):.1f} fps): {summary}")
    written = [str(out)] + ([args.poses] if args.poses else []) + ([args.mcap] if args.mcap else [])
    print(f"wrote {len(poses)} poses to {', '.join(written)}")
    ate = None
    if groundtruth is not None and poses:
        try:
            ate = absolute_trajectory_error(groundtruth, poses)
        except ValueError as exc:
            raise InputFileError(f"{groundtruth_path}: {exc}") from None
    if not args.no_plot:
        from cubeloc.daemon.plots import plot_track

        picture = out.with_suffix(".png")
        plot_track(picture, poses, pose_states, groundtruth, f"cubeloc track {Path(args.sequence).name}: "
                   f"{len(poses)} poses of {replayed} frames",
                   None if ate is None else (ate.stamps_ns, ate.errors_m))
        print(f"plot: {picture}")
    if groundtruth is not None:
        if ate is None:
            print("no pose to compare with the ground truth", file=sys.stderr)
            return 1
        print(f"ATE (no alignment, {ate.count} poses): RMS {ate.rmse_m * 1000:.2f} mm, "
              f"median {ate.median_m * 1000:.2f} mm, max {ate.max_m * 1000:.2f} mm")
    return 0
