"""``cubeloc pose --target T --calib C IMAGE...``: the single-frame target pose per image.

Prints one JSON object per image (interfaces.md): ``{"image", "ok": true, "position",
"orientation", "planes", "tags", "reproj_rms_px", "covariance", ...}`` or ``{"image",
"ok": false, "reason", "detail"}`` when the image gives no pose. Every image is checked
before the first line is printed, so a bad file (not an image, empty, float, the wrong
size for the calibration) stops the command with one line and exit 2, and nothing
half-done is printed. Each image is solved on its own (no region prediction between them):
``daemon.replay.pose_images``, the library function; this command prints its results.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from cubeloc.errors import InputFileError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "pose", help="single-frame target pose per image, one JSON object per line",
        description="The camera pose in the target's frame from each image alone (3 faces: full "
                    "pose; 2 faces: flagged planes=2; 1 face: no pose).",
    )
    parser.add_argument("--target", required=True, metavar="FILE", help="target definition YAML")
    parser.add_argument("--calib", required=True, metavar="FILE", help="camera_info YAML of the camera")
    parser.add_argument("--no-two-faces", action="store_true", help="refuse poses from two faces")
    parser.add_argument("--max-reproj-rms", type=float, default=1.5, metavar="PX",
                        help="refuse poses whose reprojection RMS exceeds this (default 1.5 px)")
    parser.add_argument("images", nargs="+", metavar="IMAGE", help="images (PNG, JPEG, ...; 8- or 16-bit, grey or colour)")
    parser.set_defaults(func=run)


def result_line(image: str, result) -> dict:
    """The JSON object for one image."""
    estimate = result.estimate
    if estimate is None:
        return {"image": image, "ok": False, "reason": result.status, "detail": result.detail,
                "tags_seen": list(result.tags_seen)}
    T = estimate.T_world_camera
    return {
        "image": image,
        "ok": True,
        "position": [round(float(v), 6) for v in T.translation],
        "orientation": [round(float(v), 8) for v in T.quaternion()],
        "planes": estimate.planes,
        "tags": list(estimate.tag_ids),
        "reproj_rms_px": round(estimate.reproj_rms_px, 4),
        "covariance": [float(f"{v:.6g}") for v in estimate.covariance.reshape(-1)],
    }


def run(args) -> int:
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.daemon.logs import configure_logging
    from cubeloc.daemon.replay import pose_images
    from cubeloc.positioning.target import load_target
    from cubeloc.positioning.target_pose import PoseOptions

    configure_logging("warning", "console", stream=sys.stderr)  # stdout is for the JSON lines
    target = load_target(args.target)
    calibration = read_camera_info(args.calib)
    if not args.max_reproj_rms > 0:
        raise InputFileError(f"--max-reproj-rms {args.max_reproj_rms}: must be a positive number of pixels")
    options = PoseOptions(allow_two_faces=not args.no_two_faces, max_reproj_rms_px=args.max_reproj_rms)
    for path, result in pose_images([Path(p) for p in args.images], calibration, target, options):
        print(json.dumps(result_line(str(path), result)), flush=True)
    return 0
