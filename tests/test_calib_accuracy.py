"""Calibration recovers the camera that rendered the views, for every board kind.

Views are rendered by ``fakes.board_views`` with the exact inverse of OpenCV's projection
(known intrinsics and distortion), 1.5 grey levels of noise and a 0.5 px lens blur.
Bounds (issue 6): fx, fy within 0.2 %, principal point within 1 px, k1 within 0.01.
Then 10 % corrupted views (a wrong board, heavy blur) are added: same bounds, and every
bad view is named in the result. Every board at 640x512, and the chessboard also at the
real camera's 1280x1024: its sharp corners are where cornerSubPix alone moved the
principal point by 1.5 px (``bench/calibrate.py``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cubeloc.calib.boards import parse_board
from cubeloc.calib.detect import detect_board
from cubeloc.calib.pipeline import ImageDetection, calibrate_views, views_from_detections
from cubeloc.fakes.board_views import board_views, synthetic_board_camera

CAMERAS = {640: synthetic_board_camera(640, 512), 1280: synthetic_board_camera(1280, 1024)}
# 1280 (chessboard only): one sample per pixel keeps the render time down; the chessboard
# is computed exactly per sample (anti-aliased), its corners within 0.003 px even so
SUPERSAMPLE = {640: 3, 1280: 1}
GOOD_VIEWS, BAD_VIEWS = 20, 2

# board kind -> (spec, a wrong board to show in a corrupted view, or None for a
# misprinted copy of the right board: stretched 8 % along x, found but inconsistent)
BOARDS = {
    "charuco": ("charuco:11x8:0.030:0.022:DICT_5X5_100", "chessboard:9x6:0.025"),
    "chessboard": ("chessboard:9x6:0.025", None),
    "circles": ("circles:7x5:0.030", None),
    "acircles": ("acircles:4x11:0.020", None),
    "aprilgrid": ("aprilgrid:6x6:0.088:0.3", None),
}


CASES = [(kind, 640) for kind in sorted(BOARDS)] + [("chessboard", 1280)]


@pytest.fixture(scope="module", params=CASES, ids=[f"{kind}-{width}" for kind, width in CASES])
def rendered(request):
    kind, width = request.param
    spec, wrong = BOARDS[kind]
    board, camera = parse_board(spec), CAMERAS[width]
    views = board_views(
        board, camera, GOOD_VIEWS + BAD_VIEWS, seed=2, corrupt=BAD_VIEWS,
        wrong_board=parse_board(wrong) if wrong else None, supersample=SUPERSAMPLE[width],
    )
    detections = [
        ImageDetection(Path(f"view_{i:02d}.png"), camera.size, detect_board(v.image, board))
        for i, v in enumerate(views)
    ]
    return board, camera, views, detections


def _assert_recovered(calibration, camera):
    k, d = calibration.camera_matrix, calibration.distortion
    true_k, true_d = camera.camera_matrix, camera.distortion
    assert abs(k[0, 0] / true_k[0, 0] - 1) < 0.002, (k[0, 0], true_k[0, 0])
    assert abs(k[1, 1] / true_k[1, 1] - 1) < 0.002, (k[1, 1], true_k[1, 1])
    assert np.hypot(k[0, 2] - true_k[0, 2], k[1, 2] - true_k[1, 2]) < 1.0, (k[:2, 2], true_k[:2, 2])
    assert abs(d[0] - true_d[0]) < 0.01, (d[0], true_d[0])


def test_clean_views_recover_the_camera(rendered):
    board, camera, _, detections = rendered
    views, skipped = views_from_detections(detections[:GOOD_VIEWS], board)
    assert len(views) >= GOOD_VIEWS - 2, skipped  # the detector finds (almost) every clean view
    run = calibrate_views(views, camera.size, board, skipped=skipped)
    _assert_recovered(run.calibration, camera)
    assert run.solution.rms_px < 0.3
    assert run.verdict.grade == "good", run.verdict.text


def test_corrupted_views_are_named_and_change_nothing(rendered):
    board, camera, views, detections = rendered
    usable, skipped = views_from_detections(detections, board)
    run = calibrate_views(usable, camera.size, board, skipped=skipped)
    _assert_recovered(run.calibration, camera)
    named = {v.name for v in run.solution.dropped} | {name for name, _ in skipped}
    bad = {f"view_{i:02d}.png" for i, v in enumerate(views) if v.corrupted}
    assert len(bad) == BAD_VIEWS
    assert bad <= named, (bad, run.solution.dropped, skipped)
    assert len(named - bad) <= 1  # at most one clean view is lost on the way
    metadata = run.calibration.metadata
    listed = {e["view"] for e in metadata["dropped"]} | {e["image"] for e in metadata["skipped"]}
    assert bad <= listed
