"""Board specs, camera_info files (ours, ROS', and a kill mid-write), the corners cache,
coverage advice, the verdict, and the printable board."""

from __future__ import annotations

import os
import re
import signal
import stat
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest
import yaml

from cubeloc.calib.boards import BoardSpecError, parse_board
from cubeloc.calib.camera_info import CameraCalibration, read_camera_info, write_camera_info
from cubeloc.calib.corners_cache import CACHE_NAME, load_cache
from cubeloc.calib.coverage import CoverageTracker
from cubeloc.calib.detect import detect_board
from cubeloc.calib.pipeline import detect_images
from cubeloc.calib.report import judge
from cubeloc.calib.solve import Solution, SolveOptions
from cubeloc.fakes.board_views import board_views, synthetic_board_camera, write_board_images
from tests.conftest import REPO, run_cli

CAMERA = synthetic_board_camera(640, 512)


# -- board specs ---------------------------------------------------------------------------
def test_board_specs_parse_to_points_in_metres():
    charuco = parse_board("charuco:11x8:0.030:0.022:DICT_5X5_100")
    assert charuco.inner_corners == (10, 7) and charuco.object_points().shape == (70, 3)
    expected = charuco.charuco_board().getChessboardCorners()
    np.testing.assert_allclose(charuco.object_points(), expected, atol=1e-7)
    chess = parse_board("chessboard:9x6:0.025")
    points = chess.object_points()
    assert points.shape == (54, 3) and points[1, 0] - points[0, 0] == pytest.approx(0.025)
    assert chess.extent_m == pytest.approx((0.25, 0.175))
    acircles = parse_board("acircles:4x11:0.02")
    p = acircles.object_points()
    assert p[1, 0] - p[0, 0] == pytest.approx(0.04) and p[4, 0] - p[0, 0] == pytest.approx(0.02)
    assert parse_board("circles:7x5:0.03").diameter_m == pytest.approx(0.015)


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("chessboard:9x6:25", "metres"),
        ("chessboard:9x6", "wrong number of fields"),
        ("chess:9x6:0.025", "unknown kind 'chess'"),
        ("chessboard:9-6:0.025", "COLSxROWS"),
        ("charuco:11x8:0.030:0.022:DICT_5X5_10", "unknown dictionary"),
        ("charuco:11x8:0.030:0.040:DICT_5X5_100", "smaller than the square"),
        ("charuco:20x20:0.030:0.022:DICT_5X5_100", "needs 200 markers"),
        ("circles:4x4:0.02:0.03", "touch"),
        ("aprilgrid:6x6:0.088", "wrong number of fields"),
        ("aprilgrid:6x6:0.088:3", "fraction of the tag size"),
        ("aprilgrid:30x30:0.088:0.3", "2 to 587"),
    ],
)
def test_bad_board_specs_say_what_to_type(spec, match):
    with pytest.raises(BoardSpecError, match=match) as info:
        parse_board(spec)
    assert spec in str(info.value) and "\n" not in str(info.value)


def test_board_yaml_file(tmp_path):
    path = tmp_path / "board.yaml"
    path.write_text("kind: charuco\ncols: 5\nrows: 7\nsize: 0.04\nmarker_size: 0.03\ndictionary: DICT_6X6_250\n")
    board = parse_board(str(path))
    assert board.text == "charuco:5x7:0.04:0.03:DICT_6X6_250"
    path.write_text("kind: chessboard\ncols: 9\n")
    with pytest.raises(BoardSpecError, match=r"missing rows, size"):
        parse_board(str(path))


# -- camera_info ---------------------------------------------------------------------------
def test_camera_info_round_trip_keeps_every_number(tmp_path):
    rng = np.random.default_rng(3)
    k = np.array([[1667.123456789012, 0.0, 641.98765432], [0.0, 1666.5, 511.25], [0.0, 0.0, 1.0]])
    metadata = {
        "rms_px": 0.1234, "std": {"fx": 0.51, "k1": 0.00283}, "views": 25, "corners": 1750,
        "board": "charuco:11x8:0.03:0.022:DICT_5X5_100", "camera_serial": "DA1234567",
        "date": "2026-11-22T09:00:00+00:00", "software": "cubeloc 0.1.0",
        "dropped": [{"view": "view_007.png", "rms_px": 2.1, "reason": "far above the rest"}],
    }
    for model, n in (("plumb_bob", 5), ("rational_polynomial", 8)):
        calibration = CameraCalibration(1280, 1024, k, rng.normal(0, 0.1, n), model, "cam", metadata)
        path = tmp_path / f"{model}.yaml"
        write_camera_info(path, calibration)
        loaded = read_camera_info(path)
        assert np.array_equal(loaded.camera_matrix, calibration.camera_matrix)
        assert np.array_equal(loaded.distortion, calibration.distortion)
        assert loaded.distortion_model == model and loaded.metadata == metadata
    old_mask = os.umask(0o022)
    try:
        write_camera_info(path, calibration)
    finally:
        os.umask(old_mask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644  # readable by the daemon's user too


def test_camera_info_written_by_ros_camera_calibration_loads(tmp_path):
    # The layout of ROS camera_calibration's ost.yaml (camera_calibration_parsers), with
    # the rational_polynomial model its calibrator writes for wide lenses.
    path = tmp_path / "ost.yaml"
    path.write_text(
        "image_width: 1280\nimage_height: 1024\ncamera_name: mv_ca013\n"
        "camera_matrix:\n  rows: 3\n  cols: 3\n"
        "  data: [1671.40228, 0.00000, 645.19391, 0.00000, 1670.84412, 508.80025, 0.00000, 0.00000, 1.00000]\n"
        "distortion_model: rational_polynomial\n"
        "distortion_coefficients:\n  rows: 1\n  cols: 8\n"
        "  data: [-0.081231, 0.051032, 0.000214, -0.000117, 0.002211, 0.000000, 0.000000, 0.000000]\n"
        "rectification_matrix:\n  rows: 3\n  cols: 3\n"
        "  data: [1.00000, 0.00000, 0.00000, 0.00000, 1.00000, 0.00000, 0.00000, 0.00000, 1.00000]\n"
        "projection_matrix:\n  rows: 3\n  cols: 4\n"
        "  data: [1649.05847, 0.00000, 646.69013, 0.00000, 0.00000, 1660.52368, 508.40164, 0.00000, 0.00000, 0.00000, 1.00000, 0.00000]\n"
    )
    loaded = read_camera_info(path)
    assert loaded.fx == pytest.approx(1671.40228) and loaded.cy == pytest.approx(508.80025)
    assert loaded.distortion_model == "rational_polynomial" and loaded.distortion[0] == pytest.approx(-0.081231)
    assert loaded.metadata == {}


WRITER = """
import sys, numpy as np
from cubeloc.calib.camera_info import CameraCalibration, write_camera_info
k = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
i = 0
while True:
    i += 1
    meta = {"views": i, "per_view_rms_px": {f"view_{j:03d}.png": 0.1 for j in range(400)}}
    write_camera_info(sys.argv[1], CameraCalibration(640, 480, k, [0.01 * (i % 7), 0, 0, 0, 0], metadata=meta))
    if i == 1:
        print("first", flush=True)
"""


def test_kill_9_while_writing_leaves_a_whole_file(tmp_path):
    path = tmp_path / "cam.yaml"
    for delay in (0.05, 0.13, 0.21):
        process = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, text=True, cwd=REPO)
        assert process.stdout.readline().strip() == "first"
        time.sleep(delay)  # not a timed assert: only where in its loop the kill lands
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=10)
        loaded = read_camera_info(path)  # parses: the old file or the new one, never half
        assert loaded.metadata["views"] >= 1 and len(loaded.metadata["per_view_rms_px"]) == 400
    leftovers = [p.name for p in tmp_path.iterdir() if p.name != "cam.yaml"]
    assert all(re.fullmatch(r"\.cam\.yaml\..*\.tmp", name) for name in leftovers)


# -- detection cache, coverage, verdict ----------------------------------------------------
def test_corners_cache_is_reused_and_refreshed_when_an_image_changes(tmp_path):
    board = parse_board("circles:7x5:0.030")
    paths = write_board_images(tmp_path, board, CAMERA, count=3, seed=8)
    first = detect_images(paths, board)
    cache = load_cache(tmp_path, board)
    assert set(cache) == {p.name for p in paths} and all(r.detection is not None for r in cache.values())
    np.testing.assert_array_equal(cache[paths[0].name].detection.image_points, first[0].detection.image_points)
    assert load_cache(tmp_path, parse_board("circles:7x5:0.031")) == {}  # another board: not used
    cv2.imwrite(str(paths[1]), np.full((512, 640), 128, np.uint8))  # the board is gone from it
    second = detect_images(paths, board)
    assert second[1].detection is None and second[0].detection is not None
    doc = yaml.safe_load((tmp_path / CACHE_NAME).read_text())
    assert doc["images"][paths[1].name]["board"] is None


COVERAGE_BOARDS = {"charuco:11x8:0.030:0.022:DICT_5X5_100": "an 11x8 ChArUco board",
                   "aprilgrid:6x6:0.088:0.3": "a 6x6 AprilGrid"}


@pytest.mark.parametrize("spec", sorted(COVERAGE_BOARDS))
def test_coverage_accepts_new_views_only_and_says_what_is_missing(spec):
    board = parse_board(spec)
    views = board_views(board, CAMERA, count=6, seed=9)
    tracker = CoverageTracker(board, CAMERA.size, min_views=5)
    nothing = tracker.offer(None)
    assert not nothing.accepted and nothing.reason == f"{COVERAGE_BOARDS[spec]} not in view"
    first = detect_board(views[0].image, board)
    assert tracker.offer(first).accepted
    repeat = tracker.offer(first)
    assert not repeat.accepted and "move or tilt" in repeat.reason
    blurred = detect_board(cv2.GaussianBlur(views[1].image, (0, 0), 3.0), board)
    if blurred is not None:  # heavy blur: refused as blurred (when found at all)
        offer = tracker.offer(blurred)
        assert not offer.accepted and "blurred" in offer.reason
    advice = tracker.missing()
    assert "more views (1 of 5)" in advice
    assert any("corner" in a for a in advice)
    assert "views  1" in tracker.status_line() and "skew [" in tracker.status_line()
    assert not tracker.done


@pytest.mark.parametrize("spec", sorted(COVERAGE_BOARDS))
def test_coverage_finishes_once_near_far_tilted_and_corner_views_are_in(spec):
    from cubeloc.calib.detect import Detection
    from cubeloc.fakes.board_views import random_poses
    from cubeloc.fakes.optics import project

    board = parse_board(spec)
    points = board.object_points().astype(np.float64)
    tracker = CoverageTracker(board, CAMERA.size, min_views=15)
    offered = 0
    for rotation, translation in random_poses(board, CAMERA, 30, np.random.default_rng(5)):
        for distance in (1.0, 0.6, 1.6):  # as placed, nearer (partial view), farther
            uv = project(points @ rotation.T + translation * distance, CAMERA)
            seen = (uv[:, 0] >= 0) & (uv[:, 0] < CAMERA.width) & (uv[:, 1] >= 0) & (uv[:, 1] < CAMERA.height)
            if seen.sum() >= 8 and not tracker.done:
                detection = Detection(uv[seen].astype(np.float32), board.object_points()[seen], np.flatnonzero(seen), 1.0)
                for _ in range(2):  # the board held still: the second frame adds nothing
                    offered += 1
                    tracker.offer(detection)
    assert tracker.done and tracker.missing() == []
    assert 15 <= len(tracker.scores) <= offered // 2
    assert "coverage good" in tracker.status_line()


def test_verdict_names_the_weak_parameter():
    k = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])

    def solution(rms, std_fx, views):
        return Solution((640, 480), "plumb_bob", k, np.zeros(5), rms,
                        {"fx": std_fx, "fy": 0.5, "cx": 0.5, "cy": 0.5}, tuple([None] * views), (), SolveOptions())

    assert judge(solution(0.2, 0.5, 20)).grade == "good"
    loose = judge(solution(0.2, 6.4, 20))
    assert loose.grade == "usable" and "fx uncertain to 0.8% - add tilted views" in loose.text
    assert judge(solution(1.5, 0.5, 20)).grade == "poor"


# -- printable board -----------------------------------------------------------------------
def test_generate_board_pdf_at_true_scale(tmp_path):
    out = tmp_path / "board.pdf"
    result = run_cli("generate", "board", "--board", "chessboard:9x6:0.025", "--out", str(out), "--dpi", "300")
    assert result.returncode == 0, result.stderr
    pdf = out.read_bytes()
    assert pdf.startswith(b"%PDF")
    media = re.search(rb"/MediaBox \[ 0 0 ([\d.]+) ([\d.]+) \]", pdf)
    width_mm, height_mm = (float(v) / 72 * 25.4 for v in media.groups())
    assert (round(width_mm), round(height_mm)) == (297, 420)  # A3 portrait
    again = run_cli("generate", "board", "--out", str(out))
    assert again.returncode == 2 and "--force" in again.stderr


def test_printed_board_is_found_and_measures_true_scale():
    from cubeloc.calib.printable_board import board_sheet

    board = parse_board("charuco:5x4:0.030:0.022:DICT_4X4_50")
    sheet = board_sheet(board, dpi=150)
    small = cv2.resize(sheet.image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    detection = detect_board(small, board)
    assert detection is not None and detection.count == 12
    pitch_px = np.linalg.norm(detection.image_points[1] - detection.image_points[0]) * 2
    assert pitch_px == pytest.approx(0.030 / 0.0254 * 150, rel=0.01)
