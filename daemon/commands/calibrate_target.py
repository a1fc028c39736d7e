"""``cubeloc calibrate-target --images GLOB --target NOMINAL.yaml --calib C --out REFINED.yaml``.

A hand-built cube is never exact. From 20-50 images of it from all around (every tag in
several images, each image showing two faces or more), a bundle adjustment finds where
every tag really is: 6-DoF per tag, the first tag of the nominal file held fixed as the
frame (``positioning.target_calibration``). Prints the report (residuals, each tag's
shift and rotation from nominal with its 1-sigma uncertainty) and writes the refined
target as an explicit-tag target file (interfaces.md), atomically; an existing output is
replaced only with ``--force``. Use it in place of the nominal file everywhere.
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
    parser.add_argument("--out", required=True, metavar="FILE", help="the refined target YAML to write")
    parser.add_argument("--force", action="store_true", help="replace an existing --out file")
    parser.set_defaults(func=run)


def run(args) -> int:
    from calib.camera_info import read_camera_info
    from cubeloc.atomic import atomic_write_text
    from daemon.commands.calibrate import expand_images
    from daemon.commands.pose import check_image, load_grey
    from positioning.target import load_target
    from positioning.target_calibration import calibrate_target, observe

    out = Path(args.out)
    if out.exists() and not args.force:
        raise InputFileError(f"--out {out}: file exists; pass --force to replace it")
    if out.parent != Path("") and not out.parent.is_dir():
        raise InputFileError(f"--out {out}: directory {out.parent} does not exist")
    nominal = load_target(args.target)
    calibration = read_camera_info(args.calib)
    paths = expand_images(args.images)
    for path in paths:
        check_image(path, calibration.width, calibration.height)
    print(f"detecting the tags of {args.target} in {len(paths)} images ...", flush=True)
    views, skipped = observe(((str(p), load_grey(p)) for p in paths), nominal, calibration)
    result = calibrate_target(views, nominal, calibration, skipped)
    print(result.report())
    header = (
        f"# Refined by cubeloc calibrate-target from {result.views_used} images ({args.target} nominal);\n"
        f"# corner residual RMS {result.rms_px:.3f} px (nominal {result.nominal_rms_px:.3f} px).\n"
    )
    atomic_write_text(out, header + result.refined.to_yaml())
    print(f"wrote {out}", file=sys.stdout)
    return 0
