"""``cubeloc calibrate``: camera intrinsics and distortion from views of a board.

Two sources, one solve (``calib.pipeline``):

* ``--camera SOURCE``: live. Each frame is searched for the board; a view is kept only
  when it is sharp and adds coverage (``calib.coverage``); one terminal line shows the
  coverage bars and what to do next. Capture stops when coverage is good enough, at the
  end of a recorded source, or on Ctrl-C / SIGTERM (then the views so far are solved if
  there are enough, and nothing is written otherwise). ``--foxglove HOST:PORT`` shows it in
  the Foxglove app too (daemon/calibration_view.py). The kept images and their corners
  go to ``<out stem>.views/``, so ``--images '<stem>.views/*.png'`` re-solves them.
* ``--images GLOB...``: any image set; corners are cached in ``corners.yaml`` next to
  the images, so solving again (another model, a fixed principal point) is quick.

Output: the camera_info YAML (``--out``, with the ``calibration:`` report block) and
``<out stem>.report.png`` (residuals, coverage, per-view errors). Nothing is written when
the solve fails; an existing output is replaced only with ``--force``.
"""

from __future__ import annotations

import argparse
import contextlib
import glob
import signal
import sys
import threading
import time
from pathlib import Path

from cubeloc.errors import CubelocError, InputFileError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
MAX_TIMEOUTS = 10  # consecutive frame timeouts before giving up on the camera

EPILOG = """\
board specs (lengths in metres; or a YAML file with kind, cols, rows, size, ...):
  charuco:11x8:0.030:0.022:DICT_5X5_100   ChArUco, counts SQUARES: 11 across, 8 down,
                                          square 30 mm, marker 22 mm (the default board)
  chessboard:9x6:0.025                    chessboard, counts INNER CORNERS (where four
                                          squares meet): a board of 10x7 squares, 25 mm
  circles:7x5:0.030[:DIAMETER]            circle grid, counts circles, 30 mm apart
  acircles:4x11:0.020[:DIAMETER]          OpenCV's asymmetric grid: 4 circles per row,
                                          11 rows 20 mm apart (40 mm within a row)
  aprilgrid:6x6:0.088:0.3                 Kalibr AprilGrid, counts TAGS: 6 x 6 tag36h11
                                          of 88 mm, gaps of 0.3 x 88 mm with black squares
  kalibr:april_6x6.yaml                   a Kalibr target file (aprilgrid or checkerboard)
Print a board with `cubeloc generate board --board SPEC --out board.pdf` and measure it.

examples:
  cubeloc calibrate --camera aravis --board charuco:11x8:0.030:0.022:DICT_5X5_100 --out cam.yaml
  cubeloc calibrate --images 'cam.views/*.png' --board charuco:11x8:0.030:0.022:DICT_5X5_100 \\
      --out cam.yaml --force --model rational_polynomial
"""


def register(subparsers) -> None:
    from cubeloc.calib.boards import BOARD_HELP, DEFAULT_BOARD

    parser = subparsers.add_parser(
        "calibrate", help="camera intrinsics and distortion from a board (live or from images)",
        description="Zhang calibration from a live camera or image files, with coverage "
        "feedback, outlier views dropped and named, and a verdict on the result.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--camera", metavar="SOURCE", help="live camera source: aravis[:ID], replay:DIR[@pace], ...")
    source.add_argument(
        "--images", nargs="+", metavar="GLOB",
        help="image files, directories or quoted globs ('DIR/*.png'); corners are cached in DIR/corners.yaml",
    )
    parser.add_argument("--board", default=DEFAULT_BOARD, metavar="SPEC", help=BOARD_HELP + f" (default {DEFAULT_BOARD})")
    parser.add_argument("--out", required=True, metavar="FILE", help="camera_info YAML to write")
    parser.add_argument("--force", action="store_true", help="replace an existing output")
    parser.add_argument("--model", choices=("plumb_bob", "rational_polynomial", "fisheye", "equidistant"),
                        default="plumb_bob",
                        help="distortion model (default plumb_bob: k1 k2 p1 p2 k3); fisheye (or equidistant, "
                             "its camera_info name) for fisheye and very wide lenses: Kannala-Brandt k1..k4")
    parser.add_argument("--fix-principal-point", action="store_true", help="keep the principal point at the image centre")
    parser.add_argument("--fix-aspect-ratio", action="store_true", help="solve one focal length (fx = fy)")
    parser.add_argument("--camera-name", default="camera", help="camera_name in the output (default 'camera')")
    parser.add_argument("--config", metavar="FILE", help="daemon config whose [camera] settings to use (live only)")
    parser.add_argument("--foxglove", metavar="HOST:PORT",
                        help="live: show the image, the board, the coverage and the next hint in the Foxglove app "
                             "(ws://HOST:PORT; 127.0.0.1 for this machine only, 0.0.0.0 for a laptop on the network)")
    parser.add_argument("--min-views", type=int, default=15, help="live: views needed before coverage can finish (default 15)")
    parser.add_argument("--max-views", type=int, default=40, help="live: stop after this many views (default 40)")
    parser.set_defaults(func=run)


def _outputs(out: str, force: bool, live: bool) -> tuple[Path, Path, Path]:
    """(camera_info, views folder, report PNG); refuse to overwrite without --force.
    The views folder is written by live captures only (from images it may be the input)."""
    path = Path(out)
    if path.is_dir():
        raise InputFileError(f"--out {path}: is a directory; give a file name such as {path / 'camera.yaml'}")
    if not path.parent.is_dir():
        raise InputFileError(f"--out {path}: directory {path.parent} does not exist")
    views = path.with_name(path.stem + ".views")
    report = path.with_name(path.stem + ".report.png")
    if not force:
        for existing in (path, views, report) if live else (path, report):
            if existing.exists():
                raise InputFileError(f"{existing}: already exists; use --force to replace it (or another --out)")
    return path, views, report


def expand_images(patterns: list[str]) -> list[Path]:
    """Files from globs, directories and names, sorted within each pattern, no repeats."""
    paths: list[Path] = []
    for pattern in patterns:
        given = Path(pattern)
        if given.is_dir():
            matches = sorted(p for p in given.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        elif any(ch in pattern for ch in "*?["):
            matches = sorted(Path(p) for p in glob.glob(pattern) if Path(p).suffix.lower() in IMAGE_SUFFIXES)
        elif given.is_file():
            matches = [given]
        else:
            raise InputFileError(f"--images {pattern}: no such file or directory")
        if not matches:
            raise InputFileError(f"--images {pattern!r}: no image files match")
        paths += [p for p in matches if p not in paths]
    return paths


def run(args) -> int:
    from cubeloc.calib.boards import parse_board
    from cubeloc.calib.solve import SolveOptions

    board = parse_board(args.board)
    out, views_dir, report_png = _outputs(args.out, args.force, live=args.camera is not None)
    model = "equidistant" if args.model == "fisheye" else args.model
    options = SolveOptions(model=model, fix_principal_point=args.fix_principal_point, fix_aspect_ratio=args.fix_aspect_ratio)
    if args.images:
        if args.foxglove:
            raise InputFileError("--foxglove shows a live calibration: use it with --camera, not --images")
        return _run_images(args, board, options, out, report_png)
    return _run_live(args, board, options, out, views_dir, report_png)


def _run_images(args, board, options, out: Path, report_png: Path) -> int:
    from cubeloc.calib.pipeline import calibrate_views, detect_images, views_from_detections

    paths = expand_images(args.images)
    print(f"detecting {board.description} in {len(paths)} images ...", flush=True)
    detections = detect_images(paths, board)
    views, skipped = views_from_detections(detections, board)
    run = calibrate_views(views, detections[0].size, board, options, skipped=skipped, camera_name=args.camera_name)
    _write_results(run, out, report_png)
    return 0


def _write_results(run, out: Path, report_png: Path, views_note: str = "") -> None:
    import cv2

    from cubeloc.atomic import atomic_write_bytes
    from cubeloc.calib.camera_info import write_camera_info
    from cubeloc.calib.report import format_report, render_report

    for line in format_report(run.solution, run.verdict, list(run.skipped)):
        print(line)
    ok, png = cv2.imencode(".png", render_report(run.solution))
    if ok:
        atomic_write_bytes(report_png, png.tobytes())
    write_camera_info(out, run.calibration)  # last: its presence means a finished calibration
    print(f"wrote {out}{views_note} and {report_png}")


def _camera_settings(config_path: str | None):
    from cubeloc.daemon.config import load_config

    return load_config(config_path).camera.settings() if config_path else None


def _run_live(args, board, options, out: Path, views_dir: Path, report_png: Path) -> int:
    from cubeloc.calib.pipeline import (
        ImageDetection,
        calibrate_views,
        views_from_detections,
        write_views,
    )
    from cubeloc.calib.solve import MIN_VIEWS
    from cubeloc.daemon.cameras import make_camera
    from cubeloc.drivers.base import CameraBusy

    if args.min_views < MIN_VIEWS or args.max_views < args.min_views:
        raise InputFileError(f"--min-views {args.min_views} / --max-views {args.max_views}: need {MIN_VIEWS} <= min <= max")
    camera = make_camera(args.camera, _camera_settings(args.config))
    view = None
    if args.foxglove:  # an address in use or not ours: exit 2 before the camera opens
        from cubeloc.daemon.calibration_view import CalibrationView

        view = CalibrationView(args.foxglove)
    stop = threading.Event()
    # SIGTERM ends the capture loop cleanly; the handler stays until the results are
    # written, so a SIGTERM while solving or writing lets the writes finish (exit 0)
    # instead of killing the process between the views, the report and the calibration.
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        try:
            try:
                camera.open()
            except CameraBusy as exc:
                raise CameraBusy(f"{exc}; calibrate, then start the daemon again ('systemctl start cubeloc')") from None
            serial = camera.info.serial
            camera.start()
            accepted, ended = _capture(camera, board, args, stop, view)
        finally:
            with contextlib.suppress(Exception):
                camera.stop()
            camera.close()
            if view is not None:
                view.close()
        print(f"\ncapture ended: {ended}; {len(accepted)} views kept", flush=True)
        if len(accepted) < MIN_VIEWS:
            raise CubelocError(
                f"only {len(accepted)} views were kept ({ended}); at least {MIN_VIEWS} are needed: nothing written"
            )
        height, width = accepted[0][1].shape
        detections = [ImageDetection(Path(name), (width, height), det) for name, _, det in accepted]
        views, skipped = views_from_detections(detections, board)
        run = calibrate_views(
            views, (width, height), board, options, skipped=skipped, camera_name=args.camera_name, camera_serial=serial
        )
        write_views(views_dir, board, accepted)
        _write_results(run, out, report_png, views_note=f", {views_dir}/ ({len(accepted)} images + corners.yaml)")
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0


def _capture(camera, board, args, stop: threading.Event, view=None) -> tuple[list[tuple], str]:
    """``calib.pipeline.capture_views`` with the status on the terminal (rewritten in place
    5 times a second on a terminal, else one line per kept view) and in ``view``."""
    from cubeloc.calib.pipeline import capture_views

    interactive = sys.stdout.isatty()
    last_print = [0.0]

    def shown(stamp_ns, image, detection, offer, tracker) -> None:
        if view is not None:
            view.show(stamp_ns, image, detection, offer, tracker)
        now = time.monotonic()
        if offer.accepted or (interactive and now - last_print[0] > 0.2):
            line = tracker.status_line() + ("  + " if offer.accepted else "  - ") + offer.reason
            print(("\r" + line.ljust(160)) if interactive else line, end="" if interactive else "\n", flush=True)
            last_print[0] = now

    print("capturing: move the board through the whole image, near and far, tilted; Ctrl-C to finish early", flush=True)
    return capture_views(camera, board, args.min_views, args.max_views, stop, shown, source=args.camera,
                         max_timeouts=MAX_TIMEOUTS)
