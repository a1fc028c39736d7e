"""Calibration: the run time of a 25-view solve and how close it comes to the truth.

For each board kind, 25 views are rendered at 1280x1024 by ``fakes.board_views`` with a
known camera (the paper's field of view, principal point off centre, plumb_bob
distortion with tangential terms), 1.5 grey levels of noise and a 0.5 px lens blur (the
chessboard is computed exactly at each sample; the other boards are read from a texture).
Detection and the solve are timed separately (medians); then the recovered parameters
are set against the true ones. Then the same through a fisheye (``fakes.lenses``
'fisheye_hd', 131 deg across at 1280x1024), solved with the equidistant model.
"""

from __future__ import annotations

import statistics
import time

from bench.common import markdown_table, median_seconds
from cubeloc.calib.boards import parse_board
from cubeloc.calib.detect import detect_board
from cubeloc.calib.pipeline import ImageDetection, calibrate_views, views_from_detections
from cubeloc.calib.solve import SolveOptions, View, solve
from cubeloc.fakes.board_views import board_views, synthetic_board_camera
from cubeloc.fakes.lenses import lens_calibration

TITLE = "Camera calibration: 25-view solve time and recovered-vs-true intrinsics"
VIEWS = 25
BOARDS = (
    "charuco:11x8:0.030:0.022:DICT_5X5_100",
    "chessboard:9x6:0.025",
    "circles:7x5:0.030",
    "acircles:4x11:0.020",
    "aprilgrid:6x6:0.088:0.3",
)
FISHEYE_BOARDS = ("aprilgrid:6x6:0.088:0.3", "chessboard:9x6:0.025")


def _measure(spec: str, camera, options: SolveOptions) -> tuple[list[object], dict[str, float]]:
    from pathlib import Path

    board = parse_board(spec)
    views = board_views(board, camera, VIEWS, seed=1, supersample=2)
    detect_times = []
    detections = []
    for index, view in enumerate(views):
        start = time.perf_counter()
        found = detect_board(view.image, board)
        detect_times.append(time.perf_counter() - start)
        detections.append(ImageDetection(Path(f"view_{index:02d}.png"), camera.size, found))
    usable, skipped = views_from_detections(detections, board)
    solve_views = [View(v.name, v.image_points, v.object_points) for v in usable]
    solve_s = median_seconds(lambda: solve(solve_views, camera.size, options), repeats=5, warmup=1)
    run = calibrate_views(usable, camera.size, board, options, skipped=skipped)
    k, d = run.calibration.camera_matrix, run.calibration.distortion
    true_k, true_d = camera.camera_matrix, camera.distortion
    row = [
        spec, f"{len(run.solution.views)}/{VIEWS}", run.solution.points, f"{run.solution.rms_px:.3f}",
        f"{100 * (k[0, 0] / true_k[0, 0] - 1):+.3f}", f"{100 * (k[1, 1] / true_k[1, 1] - 1):+.3f}",
        f"{k[0, 2] - true_k[0, 2]:+.2f}", f"{k[1, 2] - true_k[1, 2]:+.2f}",
        f"{d[0] - true_d[0]:+.4f}", f"{d[1] - true_d[1]:+.4f}",
        f"{1000 * statistics.median(detect_times):.0f}", f"{1000 * solve_s:.0f}", run.verdict.grade,
    ]
    return row, {"fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2], "k1": d[0], "k2": d[1]}


def run() -> str:
    camera = synthetic_board_camera(1280, 1024)
    rows = []
    values = {}
    for spec in BOARDS:
        row, recovered = _measure(spec, camera, SolveOptions())
        rows.append(row)
        values[spec.split(":")[0]] = recovered
    fisheye = lens_calibration("fisheye_hd")
    fisheye_rows = [_measure(spec, fisheye, SolveOptions(model="equidistant"))[0] for spec in FISHEYE_BOARDS]
    k, d = camera.camera_matrix, camera.distortion
    truth = (
        f"True camera: fx {k[0, 0]:.2f}, fy {k[1, 1]:.2f}, cx {k[0, 2]:.2f}, cy {k[1, 2]:.2f} px; "
        f"k1 {d[0]:+.3f}, k2 {d[1]:+.3f}, p1 {d[2]:+.4f}, p2 {d[3]:+.4f}, k3 {d[4]:+.3f} (1280x1024).\n\n"
    )
    headers = [
        "board", "views used", "corners", "RMS px", "fx err %", "fy err %", "cx err px", "cy err px",
        "k1 err", "k2 err", "detect ms/image", f"solve ms ({VIEWS} views)", "verdict",
    ]
    recovered_rows = [
        [name] + [f"{v[key]:.2f}" if key[0] in "fc" else f"{v[key]:+.4f}" for key in ("fx", "fy", "cx", "cy", "k1", "k2")]
        for name, v in values.items()
    ]
    recovered_rows.append(["**true**", f"{k[0, 0]:.2f}", f"{k[1, 1]:.2f}", f"{k[0, 2]:.2f}", f"{k[1, 2]:.2f}", f"{d[0]:+.4f}", f"{d[1]:+.4f}"])
    return (
        truth
        + markdown_table(headers, rows)
        + "\n"
        + markdown_table(["board", "fx", "fy", "cx", "cy", "k1", "k2"], recovered_rows)
        + f"\n{VIEWS} views per board rendered by `fakes.board_views` (seed 1, 2x supersampling, "
        "noise 1.5 grey levels, lens blur 0.5 px; the chessboard computed exactly at each sample, the "
        "other boards read from a texture of 60 texels a square, 20 an AprilGrid cell). Chessboard "
        "corners: cornerSubPix, then a fit of a blurred X-junction to the pixels. Solve: `cv2.calibrateCameraExtended`, plumb_bob, "
        "with outlier-view rejection (median of 5 runs); detection: median per image.\n\n"
        f"Through a fisheye (`fakes.lenses` fisheye_hd: 1280x1024, fx {fisheye.fx:.0f} px, 131 deg across, "
        f"equidistant k1..k4 {', '.join(f'{v:+.4f}' for v in fisheye.distortion)}), `--model fisheye` "
        "(`cv2.fisheye.calibrate`; k1, k2 errors of the equidistant coefficients):\n\n"
        + markdown_table(headers, fisheye_rows)
    )
