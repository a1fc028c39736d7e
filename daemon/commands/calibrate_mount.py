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

MEASURED_SOURCES = ("target", "map", "relocalised")


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
    import numpy as np
    from scipy.spatial.transform import Rotation

    from cubeloc.atomic import atomic_write_text
    from cubeloc.daemon.commands import check_out
    from cubeloc.daemon.config import Config, load_config
    from cubeloc.daemon.odometry_in import read_odometry_file
    from cubeloc.errors import InputFileError
    from cubeloc.positioning.mount import camera_height, make_pairs, solve_mount
    from cubeloc.positioning.tracking.odometry import OdometryBuffer

    for name, value in (("--height", args.height), ("--base-height", args.base_height)):
        if value is not None and (not math.isfinite(value) or abs(value) > 5.0):
            raise InputFileError(f"{name} {value}: metres expected, within 5 m")
    if not 0.1 <= args.pair_seconds <= 10.0:
        raise InputFileError(f"--pair-seconds {args.pair_seconds}: between 0.1 and 10 s")
    if args.out:
        check_out(Path(args.out), args.force)
    config = load_config(args.config) if args.config else Config()
    frames = config.frames.robot_frames()
    camera = _read_poses(Path(args.poses))
    rows = read_odometry_file(args.odometry)
    if len(rows) < 2:
        raise InputFileError(f"{args.odometry}: {len(rows)} odometry samples, at least 2 needed")
    buffer = OdometryBuffer(capacity=len(rows))
    for _, stamp, position, orientation in sorted(rows, key=lambda r: r[1]):
        buffer.add(stamp, position, orientation)
    first, last = rows[0][1], max(r[1] for r in rows)
    inside = [c for c in camera if first <= c[0] <= last]
    if not inside:
        raise InputFileError(f"{args.odometry}: its samples ({first} to {last} ns) do not cover any pose of "
                             f"{args.poses} ({camera[0][0]} to {camera[-1][0]} ns): not recorded together")
    height, height_sigma, height_source = args.height, 0.0, "given (--height)"
    if height is None and args.target:
        height, height_sigma, height_source = _height_from_cube(
            args, frames, np.array([c[1].translation for c in inside]), camera_height)
    pairs = make_pairs(inside, buffer.pose_at, args.pair_seconds)
    result = solve_mount(pairs, height, height_source, height_sigma_m=height_sigma)
    mount = result.T_base_camera
    rpy = Rotation.from_matrix(mount.rotation).as_euler("xyz", degrees=True)
    sigma_m, sigma_deg = result.sigma()
    print(f"{len(inside)} camera poses, {len(rows)} odometry samples: {result.pairs} stretches of "
          f"{args.pair_seconds:g} s (largest turn {result.largest_turn_deg:.0f} deg), {result.used_pairs} within "
          f"their noise; residuals {result.residual_m * 1000:.1f} mm, {result.residual_deg:.2f} deg")
    for warning in result.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    z_note = (f"{sigma_m[2] * 1000:.1f} mm, {result.height_source}" if result.observed["z"]
              else "NOT OBSERVED (a drive on the floor cannot see it): measure the camera's height above the base's "
                   "origin and set it, or give --target with a cube on the floor, or --height")
    table = (
        "[frames.base_from_camera]\n"
        f"xyz = [{mount.translation[0]:.4f}, {mount.translation[1]:.4f}, {mount.translation[2]:.4f}]\n"
        f"rpy_deg = [{rpy[0]:.3f}, {rpy[1]:.3f}, {rpy[2]:.3f}]\n"
        f"# standard deviations: x {sigma_m[0] * 1000:.1f} mm, y {sigma_m[1] * 1000:.1f} mm, z {z_note}\n"
        f"# rotation about the base's x {sigma_deg[0]:.2f} deg, y {sigma_deg[1]:.2f} deg, z {sigma_deg[2]:.2f} deg\n"
        f"# the wheels measured {result.distance_scale:.4f} times the distance and {result.turn_scale:.4f} times "
        f"the turn the camera saw, and drifted {result.heading_drift_deg_s:+.3f} deg/s in heading\n"
        + ("" if result.map_scale is None else
           f"# the map away from the target: {result.map_scale:.4f} times the target's scale (sigma "
           f"{100 * result.map_scale_sigma:.1f} %, from the {result.target_pairs} stretches the target measured; "
           "in the lever's standard deviations)\n")
    )
    print(table, end="")
    if not result.observed["z"]:
        print("warning: the lever's z is not observed; it is written as 0", file=sys.stderr)
    if args.out:
        atomic_write_text(Path(args.out), table)
        print(f"wrote {args.out}")
    return 0


def _read_poses(path: Path) -> list:
    """(stamp_ns, T_world_camera, measured by the target) of the poses the camera
    measured, in time order."""
    import numpy as np

    from cubeloc.errors import InputFileError
    from cubeloc.jsonlines import read_json_lines
    from cubeloc.positioning.geometry import Transform

    def parse(doc: dict):
        if doc.get("schema") not in ("cubeloc.pose/1", "cubeloc.pose/3"):
            raise ValueError(f"schema {doc.get('schema')!r}")
        source = doc.get("source", "target" if doc.get("state") == "target" else "map")  # /1 has no source
        if source not in MEASURED_SOURCES:
            return None
        pose = Transform.from_quaternion(np.array(doc["position"], float), np.array(doc["orientation"], float))
        if not np.all(np.isfinite(pose.translation)):
            raise ValueError("not finite")
        return int(doc["stamp_ns"]), pose, source == "target"

    camera = read_json_lines(path, parse, "cubeloc.pose/3 (camera)")
    if not camera:
        raise InputFileError(f"{path}: no pose the camera measured (target, map or relocalised)")
    return sorted(camera, key=lambda c: c[0])


def _height_from_cube(args, frames, positions, camera_height) -> tuple[float | None, float, str]:
    """The lever's z from a cube standing on the floor: the camera's height above the
    cube's bottom face (its centre less half its side along the map's up), less
    ``--base-height``; with its spread over the drive as its standard deviation."""
    from cubeloc.positioning.target import load_target

    target = load_target(args.target)
    if target.cube is None:
        print(f"warning: {args.target} is not a cube: it says nothing of the floor, so the lever's z is not "
              "observed (give --height)", file=sys.stderr)
        return None, 0.0, "unobserved"
    up = frames.up_in_target
    height, spread = camera_height(positions, up, -up * target.cube.side_m / 2.0)
    source = (f"the camera {height:.3f} m above the cube's floor (spread {spread * 1000:.1f} mm over the drive) "
              f"less --base-height {args.base_height:g}")
    return height - args.base_height, spread, source
