"""Planar targets: boards of tags posed from one image, against a corners-only SQPnP over all
tags on the same frames, and the real AprilGrid frames of ``../shared/data/aprilgrid-real``.

Renders: a board in a textured room, 0.5-3 m away, 0-60 deg off its normal, rolled at
random, wholly in view; blur 0.3-1 px, motion blur 0-2 px, read noise 2 DN; through three
cameras: ``vga`` (640x480), ``euroc`` (752x480, the EuRoC MAV camera) and the paper's
(1280x1024). Boards: a 3 x 4 board of 95.5 mm tags 24 mm apart (one-cell borders, white
gaps: the real handheld board of the AprilGrid issue), a 6 x 6 board of 88 mm tags 26 mm
apart, and Kalibr's 6 x 6 AprilGrid (88 mm, spacing 0.3: two-cell borders, black squares
in the gaps). Each view is solved twice: with the true calibration, and with one that is
off as a real calibration is (f by 0.2 %, the principal point by 0.5 px, k1 by 0.005: a
systematic corner error of a few tenths of a pixel). The baseline decodes with the same
decoder at full resolution (the AprilTag library without decimation; OpenCV's aruco for the
AprilGrid) and solves SQPnP and Levenberg-Marquardt on the decoded corners of all tags.

Real frames: the tags decoded by cubeloc and by OpenCV's ``ArucoDetector``
(``DICT_APRILTAG_36h11``, ``markerBorderBits = 2``, its defaults otherwise), the time per
frame (median of 5), and on the EuRoC frame (whose published calibration is known) how
well each set of corners fits: the reprojection RMS of one pose of Kalibr's grid, and the
RMS distance of the corners of each tag row from their line in the undistorted image.

Environment: ``CUBELOC_BENCH_PLANAR_VIEWS`` views per case (default 120: with 40 a median moved by a
millimetre with one view),
``CUBELOC_BENCH_PLANAR_JOBS`` processes (default 2).
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from bench.common import markdown_table

TITLE = "Planar targets"
CAMERAS = ("vga", "euroc", "paper")
BOARDS = ("3x4", "6x6", "aprilgrid")
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "aprilgrid-real"
# the EuRoC MAV cam0 calibration (the dataset's sensor.yaml)
EUROC_K = ((458.654, 0.0, 367.215), (0.0, 457.296, 248.375), (0.0, 0.0, 1.0))
EUROC_D = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0)


def _board(name: str):
    from cubeloc.positioning.target import make_aprilgrid, make_board

    if name == "3x4":
        return make_board(rows=3, cols=4, tag_size_m=0.0955, gap_m=0.024)
    if name == "6x6":
        return make_board()
    return make_aprilgrid()


def _camera(name: str):
    from cubeloc.calib.camera_info import paper_camera
    from cubeloc.fakes.lenses import lens_calibration

    return paper_camera() if name == "paper" else lens_calibration(name)


def _case(args) -> list[tuple[float | None, float | None]]:
    """(cubeloc error, SQPnP error) in metres for each view of one camera, board and
    calibration (None: no pose)."""
    camera_name, board_name, off, views = args
    import logging

    import structlog

    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    from cubeloc.fakes.planar_views import miscalibrated, rendered_board_view
    from cubeloc.positioning.detection import TagDetector
    from cubeloc.positioning.evaluation import decoded_corners_pose
    from cubeloc.positioning.single_frame import TargetPoseProcessor

    board, calibration = _board(board_name), _camera(camera_name)
    detector = TagDetector(board.family, border_bits=board.border_bits)
    out = []
    for seed in range(views):
        view = rendered_board_view(board, calibration, seed)
        if view is None:
            continue
        truth, image, rng = view
        used = miscalibrated(calibration, rng) if off else calibration
        result = TargetPoseProcessor(board, used).process(image, 0, seed)
        ours = None if result.estimate is None else result.estimate.T_world_camera
        theirs = decoded_corners_pose(image, board, used, detector)
        out.append(tuple(None if p is None else float(np.linalg.norm(p.translation - truth.translation))
                         for p in (ours, theirs)))
    return out


def _spread(errors_m) -> str:
    if not len(errors_m):
        return "-"
    e = np.asarray(errors_m) * 1000.0
    return f"{np.median(e):.2f} / {np.percentile(e, 90):.2f} / {e.max():.1f}"


def renders(views: int, jobs: int) -> str:
    cases = [(c, b, m, views) for m in (False, True) for c in CAMERAS for b in BOARDS]
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        results = list(pool.map(_case, cases))
    rows = []
    for (camera, board, off, _), result in zip(cases, results, strict=True):
        both = [(a, b) for a, b in result if b is not None]
        ours_where_both = [a for a, _ in both if a is not None]
        theirs_where_ours = [b for a, b in both if a is not None]
        theirs_alone = np.asarray([b for a, b in both if a is None]) * 1000.0
        alone = f"{len(theirs_alone)}: {np.median(theirs_alone):.0f} / {theirs_alone.max():.0f}" \
            if len(theirs_alone) else "0"
        rows.append([camera, board, "off" if off else "true", str(len(result)), str(len(both)),
                     str(sum(a is not None for a, _ in result)), _spread(ours_where_both),
                     _spread(theirs_where_ours), alone])
    return markdown_table(
        ["camera", "board", "calibration", "views", "SQPnP posed", "cubeloc posed",
         "cubeloc mm (median / p90 / max)", "SQPnP mm, same views",
         "posed by SQPnP alone: views, its mm (median / max)"], rows)


def _row_lines_rms(corners: dict[int, np.ndarray], cols: int, calibration) -> float:
    """RMS distance (px, undistorted) of each tag row's corners from their fitted line: the
    two edges of a row of tags (upper corners and lower corners) are two straight lines."""
    from cubeloc.positioning.camera_model import undistort

    residuals = []
    rows = {tag_id // cols for tag_id in corners}
    for row in rows:
        members = [corners[t] for t in sorted(corners) if t // cols == row]
        if len(members) < 2:
            continue
        for edge in ((0, 1), (2, 3)):  # TL, TR: one edge of the row; BR, BL: the other
            points = undistort(np.concatenate([m[list(edge)] for m in members]), calibration) * calibration.fx
            centred = points - points.mean(axis=0)
            normal = np.linalg.svd(centred)[2][1]
            residuals.extend(centred @ normal)
    return float(np.sqrt(np.mean(np.square(residuals))))


def real_frames() -> str:
    import cv2

    from cubeloc.calib.camera_info import CameraCalibration
    from cubeloc.drivers.sequence import read_image
    from cubeloc.positioning.detection import TagDetector, refine_corners
    from cubeloc.positioning.target import make_aprilgrid
    from cubeloc.positioning.target_pose import plane_solutions, unique_target_detections

    if not REAL.is_dir():
        return f"_{REAL} not found: no real frames measured._"
    grid = make_aprilgrid()
    ours = TagDetector(grid.family, border_bits=2)
    parameters = cv2.aruco.DetectorParameters()
    parameters.markerBorderBits = 2
    theirs = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), parameters)
    rows = []
    for path in sorted(REAL.glob("*.png")):
        image = read_image(path)
        times_ours, times_theirs = [], []
        for _ in range(5):
            started = time.perf_counter()
            found = [refine_corners(image, d, None, ours.cells, saddles=True) for d in ours.detect(image)]
            times_ours.append(time.perf_counter() - started)
            started = time.perf_counter()
            _, ids, _ = theirs.detectMarkers(image)
            times_theirs.append(time.perf_counter() - started)
        count = sum(d is not None for d in found)
        rows.append([path.name, f"{image.shape[1]}x{image.shape[0]}", str(count), str(0 if ids is None else len(ids)),
                     f"{np.median(times_ours) * 1000:.0f}", f"{np.median(times_theirs) * 1000:.0f}"])
    table = markdown_table(["frame", "size", "cubeloc tags", "OpenCV tags", "cubeloc ms", "OpenCV ms"], rows)

    euroc = CameraCalibration(752, 480, np.array(EUROC_K), np.array(EUROC_D), "plumb_bob", "euroc cam0")
    image = read_image(REAL / "EuRoC.png")
    raw = unique_target_detections(ours.detect(image), grid)
    saddle = [d for d in (refine_corners(image, d, euroc, ours.cells, saddles=True) for d in raw) if d is not None]
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    corners, ids, _ = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11),
                                              parameters).detectMarkers(image)
    subpix = {int(i): c.reshape(4, 2).astype(np.float64) for c, i in zip(corners, ids.ravel(), strict=True)}
    fits = []
    for name, sets in (("cubeloc (saddle points)", {d.tag_id: d.corners for d in saddle}),
                       ("OpenCV aruco, no refinement", {d.tag_id: d.corners for d in raw}),
                       ("OpenCV aruco, CORNER_REFINE_SUBPIX", subpix)):
        tag_ids = tuple(sorted(sets))
        rms = plane_solutions(grid.corners_of(tag_ids), np.concatenate([sets[t] for t in tag_ids]), euroc)[0][0]
        fits.append([name, str(len(tag_ids)), f"{rms:.3f}", f"{_row_lines_rms(sets, grid.grid.cols, euroc):.3f}"])
    fit_table = markdown_table(["corners (EuRoC.png, its published calibration)", "tags",
                                "one pose of Kalibr's grid: RMS px", "rows' corners off their lines: RMS px"], fits)
    return f"{table}\n\n{fit_table}"


# TUM-VI cam0's published calibration (equidistant, at 512 x 512; its 1024 x 1024 frames
# are the same sensor unbinned, so f doubles and c goes to 2 c + 0.5)
TUM_VI_512 = {"fx": 190.97847715128717, "fy": 190.9733070521226, "cx": 254.93170605935475, "cy": 256.8974428996504}
TUM_VI_FRAMES = ("TUM_VI.png", "r45.png", "right.png", "top.png", "top_right.png")


def fisheye_frames() -> str:
    """The five TUM-VI frames: a fisheye model fitted to each corner set alone (cubeloc's
    saddle corners; OpenCV's aruco corners, refined by CORNER_REFINE_SUBPIX), the rows'
    straightness under it, and the fit against TUM-VI's published calibration."""
    import cv2

    from cubeloc.calib.boards import parse_board
    from cubeloc.calib.camera_info import CameraCalibration
    from cubeloc.calib.detect import detect_board
    from cubeloc.calib.solve import SolveOptions, View, solve
    from cubeloc.drivers.sequence import read_image

    if not REAL.is_dir():
        return f"_{REAL} not found: no fisheye frames measured._"
    board = parse_board("aprilgrid:6x6:0.088:0.3")
    points = board.object_points()
    parameters = cv2.aruco.DetectorParameters()
    parameters.markerBorderBits = 2
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    opencv = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), parameters)
    ours, theirs = "cubeloc (saddle points)", "OpenCV aruco, CORNER_REFINE_SUBPIX"
    sets: dict[str, list[dict[int, np.ndarray]]] = {ours: [], theirs: []}
    for name in TUM_VI_FRAMES:
        image = read_image(REAL / name)
        found = detect_board(image, board)  # tag t's corners are points 4 t .. 4 t + 3
        tags = found.ids // 4
        sets[ours].append({int(t): found.image_points[tags == t].astype(np.float64) for t in np.unique(tags)})
        corners, ids, _ = opencv.detectMarkers(image)
        sets[theirs].append(
            {int(i): c.reshape(4, 2).astype(np.float64) for c, i in zip(corners, ids.ravel(), strict=True)})
    published = (2 * TUM_VI_512["fx"], 2 * TUM_VI_512["fy"], 2 * TUM_VI_512["cx"] + 0.5, 2 * TUM_VI_512["cy"] + 0.5)
    rows = []
    for label, frames in sets.items():
        views = [View(f"{i}", np.concatenate([f[t] for t in sorted(f)]).astype(np.float32),
                      np.concatenate([points[4 * t: 4 * t + 4] for t in sorted(f)])) for i, f in enumerate(frames)]
        solution = solve(views, (1024, 1024), SolveOptions(model="equidistant"))
        k = solution.camera_matrix
        model = CameraCalibration(1024, 1024, k, solution.distortion, "equidistant")
        lines = np.sqrt(np.mean([_row_lines_rms(f, board.cols, model) ** 2 for f in frames]))
        rows.append([label, str(sum(len(f) for f in frames)), f"{solution.rms_px:.3f}", f"{lines:.3f}",
                     f"{k[0, 0]:.2f} ({100 * (k[0, 0] / published[0] - 1):+.2f} %)",
                     f"{k[0, 2]:.2f}, {k[1, 2]:.2f} ({k[0, 2] - published[2]:+.2f}, {k[1, 2] - published[3]:+.2f})"])
    table = markdown_table(["corners (the five TUM-VI frames, 1024x1024)", "tags", "fisheye fit: RMS px",
                            "rows' corners off their lines: RMS px", "fx (against TUM-VI cam0)",
                            "cx, cy (against TUM-VI cam0)"], rows)
    return (f"{table}\n\nEach corner set fits its own equidistant model (`calib.solve`, as `cubeloc calibrate "
            f"--model fisheye` does); TUM-VI cam0 published: fx {published[0]:.2f}, cx {published[2]:.2f}, "
            f"cy {published[3]:.2f} px at 1024x1024 (its 512x512 calibration, doubled). Line distances are in "
            "undistorted pixels (f tan theta), which stretch towards the edge of a fisheye's view.")


def run() -> str:
    views = int(os.environ.get("CUBELOC_BENCH_PLANAR_VIEWS", "120"))
    jobs = int(os.environ.get("CUBELOC_BENCH_PLANAR_JOBS", "2"))
    return (f"Board renders, {views} seeded views a case (errors in mm of the camera position, "
            f"median / 90th percentile / max, on the views both posed; the last column: the views SQPnP "
            f"posed and cubeloc refused, and how far off SQPnP was there):\n\n{renders(views, jobs)}\n\n"
            f"The real AprilGrid frames:\n\n{real_frames()}\n\nThe fisheye frames:\n\n{fisheye_frames()}")
