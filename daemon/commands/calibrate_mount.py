"""``cubeloc calibrate-mount --poses DRIVE.jsonl --odometry ODOM.jsonl``: the camera's
mount on the robot (``[frames] base_from_camera``) from a drive (positioning/mount.py).

The robot drives a few figure-eights in view of the cube (or of a mapped place) with its
wheel odometry recorded; ``cubeloc track --poses`` turns the frames into camera poses
(run it *without* ``--odometry``: poses fused with a wrong mount would bend the answer).
Poses the camera measured are used (the target, the map, a relocalisation); held and
odometry-bridged ones are not.

The lever's z (the camera above the base's origin) is not observable from a drive on the
floor. It comes from ``--height``, or from the target when it is a cube standing on the
floor: the camera's height above its bottom face, less ``--base-height`` (the base
origin's own height above the floor; 0 for a base_footprint on the floor). An existing
``--out`` is replaced only with ``--force``, as the other calibrations do.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "calibrate-mount", help="the camera's mount on the robot ([frames] base_from_camera) from a drive with "
                                "wheel odometry",
        description="Solve the camera's mount on the robot (hand-eye) from the camera poses of a drive "
                    "(cubeloc track --poses) and the wheel odometry recorded with it, and print the "
                    "[frames.base_from_camera] table with its uncertainty.",
    )
    parser.add_argument("--poses", required=True, metavar="DRIVE.jsonl",
                        help="the drive's camera poses: cubeloc.pose/3 documents, one per line (cubeloc track --poses, "
                             "run without --odometry)")
    parser.add_argument("--odometry", required=True, metavar="ODOM.jsonl",
                        help="the wheel odometry recorded with it: cubeloc.odometry/1 documents, one per line")
    parser.add_argument("--target", metavar="FILE",
                        help="the target of the drive: a cube standing on the floor gives the camera's height")
    parser.add_argument("--config", metavar="FILE",
                        help="a cubeloc.toml whose [frames] map_from_target says which way is up (default: the "
                             "target's z)")
    parser.add_argument("--height", type=float, metavar="M",
                        help="the lever's z, measured by hand: the camera above the base's origin (metres)")
    parser.add_argument("--base-height", type=float, default=0.0, metavar="M",
                        help="the base origin's height above the floor (default 0), taken off the camera's height "
                             "from the cube")
    parser.add_argument("--pair-seconds", type=float, default=1.0, metavar="S",
                        help="the stretches of the drive compared (default 1 s)")
    parser.add_argument("--out", metavar="FILE.toml", help="also write the [frames.base_from_camera] table there")
    parser.add_argument("--force", action="store_true", help="replace an existing --out file")
    parser.set_defaults(func=run)


def run(args) -> int:
    from cubeloc.atomic import atomic_write_text
    from cubeloc.daemon.commands import check_out
    from cubeloc.daemon.config import Config, load_config
    from cubeloc.daemon.replay import calibrate_mount
    from cubeloc.errors import InputFileError

    for name, value in (("--height", args.height), ("--base-height", args.base_height)):
        if value is not None and (not math.isfinite(value) or abs(value) > 5.0):
            raise InputFileError(f"{name} {value}: metres expected, within 5 m")
    if not 0.1 <= args.pair_seconds <= 10.0:
        raise InputFileError(f"--pair-seconds {args.pair_seconds}: between 0.1 and 10 s")
    if args.out:
        check_out(Path(args.out), args.force)
    config = load_config(args.config) if args.config else Config()
    drive = calibrate_mount(Path(args.poses), Path(args.odometry), config.frames.robot_frames(), args.pair_seconds,
                            height=args.height, target=Path(args.target) if args.target else None,
                            base_height=args.base_height)
    result = drive.result
    print(f"{drive.poses} camera poses, {drive.samples} odometry samples: {result.pairs} stretches of "
          f"{args.pair_seconds:g} s (largest turn {result.largest_turn_deg:.0f} deg), {result.used_pairs} within "
          f"their noise; residuals {result.residual_m * 1000:.1f} mm, {result.residual_deg:.2f} deg")
    for warning in (*drive.warnings, *result.warnings):
        print(f"warning: {warning}", file=sys.stderr)
    table = drive.table()
    print(table, end="")
    if not result.observed["z"]:
        print("warning: the lever's z is not observed; it is written as 0", file=sys.stderr)
    if args.out:
        atomic_write_text(Path(args.out), table)
        print(f"wrote {args.out}")
    return 0
