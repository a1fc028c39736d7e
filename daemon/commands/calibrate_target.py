"""``cubeloc calibrate-target --images GLOB --target NOMINAL.yaml --calib C --out REFINED.yaml``.

A hand-built cube is never exact. From 20-50 images of it from all around (every tag in
several images, each image showing two faces or more), a bundle adjustment finds where
every tag really is: 6-DoF per tag, the first tag of the nominal file held fixed as the
frame (``positioning.target_calibration``). Prints the report (residuals, each tag's
shift and rotation from nominal with its 1-sigma uncertainty) and writes the refined
target as an explicit-tag target file (interfaces.md), atomically; an existing output is
replaced only with ``--force``. Use it in place of the nominal file everywhere.

``--place OTHER.yaml``: where a second target stands relative to ``--target``, from images
showing both (each image posing each target on its own; the relative placements averaged,
their spread reported): writes the ``[[frames.targets]]`` block for cubeloc.toml.
"""

from __future__ import annotations

import sys
from pathlib import Path

from cubeloc.errors import InputFileError

EPILOG = """\
example:
  cubeloc calibrate-target --images 'cube_views/*.png' --target cube.yaml --calib cam.yaml --out cube_refined.yaml

Take the images with the calibrated camera, 0.6-1.5 m from the cube, from all around and
from above and below (turn the cube over for its bottom face), two or three faces in each.
"""


def register(subparsers) -> None:
    import argparse

    parser = subparsers.add_parser(
        "calibrate-target", help="refine a hand-built target's tag placements from images of it",
        description="Bundle adjustment of every tag's 6-DoF placement (the first tag fixed as the frame) from "
                    "images of the target; writes an explicit-tag target file.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--images", nargs="+", required=True, metavar="GLOB",
                        help="image files, directories or quoted globs ('DIR/*.png')")
    parser.add_argument("--target", required=True, metavar="FILE", help="the nominal target definition YAML")
    parser.add_argument("--calib", required=True, metavar="FILE", help="camera_info YAML of the camera")
    parser.add_argument("--out", required=True, metavar="FILE",
                        help="the refined target YAML to write (with --place: the [[frames.targets]] TOML block)")
    parser.add_argument("--force", action="store_true", help="replace an existing --out file")
    parser.add_argument("--place", metavar="OTHER.yaml",
                        help="instead: learn where the target OTHER stands relative to --target, from images that "
                             "show both; writes its [[frames.targets]] block for cubeloc.toml")
    parser.add_argument("--config", metavar="FILE",
                        help="with --place: the cubeloc.toml whose [frames.map_from_target] places --target in the "
                             "map (the block is then in map coordinates; without it --target's frame is the map)")
    parser.set_defaults(func=run)


def run(args) -> int:
    from cubeloc.atomic import atomic_write_text
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.daemon.commands.calibrate import expand_images
    from cubeloc.drivers.sequence import read_image_sized
    from cubeloc.positioning.target import load_target
    from cubeloc.positioning.target_calibration import calibrate_target, observe

    out = Path(args.out)
    if out.exists() and not args.force:
        raise InputFileError(f"--out {out}: file exists; pass --force to replace it")
    if out.parent != Path("") and not out.parent.is_dir():
        raise InputFileError(f"--out {out}: directory {out.parent} does not exist")
    if args.place:
        return place(args, out)
    nominal = load_target(args.target)
    calibration = read_camera_info(args.calib)
    paths = expand_images(args.images)
    for path in paths:
        read_image_sized(path, calibration.width, calibration.height)  # every image checked first
    print(f"detecting the tags of {args.target} in {len(paths)} images ...", flush=True)
    views, skipped = observe(((str(p), read_image_sized(p, calibration.width, calibration.height)) for p in paths),
                             nominal, calibration)
    result = calibrate_target(views, nominal, calibration, skipped)
    print(result.report())
    header = (
        f"# Refined by cubeloc calibrate-target from {result.views_used} images ({args.target} nominal);\n"
        f"# corner residual RMS {result.rms_px:.3f} px (nominal {result.nominal_rms_px:.3f} px).\n"
    )
    atomic_write_text(out, header + result.refined.to_yaml())
    print(f"wrote {out}", file=sys.stdout)
    return 0


def place(args, out: Path) -> int:
    """``--place``: the other target's placement in the first's frame (``place_target``),
    as a ``[[frames.targets]]`` entry of the map frame ``[frames]`` sets."""
    from cubeloc.atomic import atomic_write_text
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.daemon.commands.calibrate import expand_images
    from cubeloc.daemon.config import Config, load_config
    from cubeloc.daemon.replay import MIN_VIEWS_OF_BOTH, place_target
    from cubeloc.positioning.target import load_target

    first, other = load_target(args.target), load_target(args.place)
    if set(first.ids) & set(other.ids):
        raise InputFileError(f"{args.place}: tag id(s) {sorted(set(first.ids) & set(other.ids))} also in "
                             f"{args.target}: every tag of every target needs its own id")
    calibration = read_camera_info(args.calib)
    T_map_first = (load_config(args.config) if args.config else Config()).frames.robot_frames().T_map_target
    paths = expand_images(args.images)
    placement = place_target(paths, first, other, calibration)
    if placement.T_first_other is None:
        raise InputFileError(f"{args.place}: {placement.views} of the {len(paths)} images give a pose of both "
                             f"targets; {MIN_VIEWS_OF_BOTH} or more needed (two faces of each in view)")
    placed = T_map_first @ placement.T_first_other
    xyz = [round(float(v), 6) for v in placed.translation]
    quaternion = [round(float(v), 9) for v in placed.quaternion()]
    block = (f"# {args.place} placed by cubeloc calibrate-target from {placement.views} images of both targets:\n"
             f"# spread {placement.spread_mm:.1f} mm RMS, {placement.spread_deg:.2f} deg RMS about the mean\n"
             f'[[frames.targets]]\nfile = "{Path(args.place).resolve()}"\nxyz = {xyz}\nquaternion = {quaternion}\n')
    print(block, end="")
    atomic_write_text(out, block)
    print(f"wrote {out}: add it to cubeloc.toml", file=sys.stdout)
    return 0
