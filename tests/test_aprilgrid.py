"""Kalibr AprilGrids as targets: Kalibr's own target file, two-cell borders decoded on the real
frames of ``../shared/data/aprilgrid-real``, corners at the saddle points the gap squares
make, a pose from one image; rendered boards against a corners-only SQPnP baseline."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from conftest import real_photographs

from cubeloc.calib.camera_info import CameraCalibration, paper_camera, write_camera_info
from cubeloc.drivers.sequence import read_image
from cubeloc.errors import InputFileError
from cubeloc.fakes import render_view
from cubeloc.fakes.planar_views import rendered_board_view
from cubeloc.positioning.detection import TagDetector, refine_corners
from cubeloc.positioning.evaluation import decoded_corners_pose
from cubeloc.positioning.single_frame import TargetPoseProcessor
from cubeloc.positioning.target import load_target, make_aprilgrid, parse_target
from cubeloc.positioning.target_pose import plane_solutions, unique_target_detections

KALIBR_YAML = "target_type: 'aprilgrid'\ntagCols: 6\ntagRows: 6\ntagSize: 0.088\ntagSpacing: 0.3\n"
# EuRoC MAV cam0, from the dataset's sensor.yaml: the camera of the real EuRoC frame
EUROC = CameraCalibration(752, 480, np.array([[458.654, 0.0, 367.215], [0.0, 457.296, 248.375], [0.0, 0.0, 1.0]]),
                          np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0]), "plumb_bob", "euroc")
# decoded by OpenCV's ArucoDetector (DICT_APRILTAG_36h11, markerBorderBits 2), the README's table
OPENCV_COUNTS = {"EuRoC.png": 35, "TUM_VI.png": 36, "r45.png": 36, "right.png": 19, "top.png": 17,
                 "top_right.png": 14, "iphone.png": 66, "two_boards.png": 72}


def test_kalibrs_target_file_is_a_target_with_kalibrs_layout(tmp_path):
    path = tmp_path / "april_6x6.yaml"
    path.write_text(KALIBR_YAML)
    grid = load_target(path)
    assert grid.border_bits == 2 and len(grid.tags) == 36 and grid.grid.gap_m == pytest.approx(0.0264)
    # tag r * cols + c at row r (+y) and column c (+x), the origin at tag 0's outer corner
    pitch = 0.088 * 1.3
    for tag_id, (row, col) in ((0, (0, 0)), (5, (0, 5)), (6, (1, 0)), (35, (5, 5))):
        corners = grid.tag(tag_id).corners
        assert np.allclose(corners.min(axis=0), [col * pitch, row * pitch, 0.0])
        assert np.allclose(grid.tag(tag_id).normal, [0.0, 0.0, 1.0])  # facing out of the print
    # written back (a map's or a sequence's copy) as Kalibr's file: the squares stay known
    assert grid.to_yaml() == KALIBR_YAML
    for bad, message in (("target_type: 'checkerboard'\ntargetCols: 6\n", "has no tags"),
                         ("target_type: 'aprilgrid'\ntagCols: 6\ntagRows: 6\ntagSize: 0.088\n", "tagSpacing"),
                         (KALIBR_YAML.replace("tagCols: 6", "tagCols: six"), "tagCols must be a whole number")):
        with pytest.raises(InputFileError, match=message):
            parse_target(yaml.safe_load(bad), "bad.yaml")


def test_generate_aprilgrid_prints_a_file_cubeloc_and_kalibr_read(cli, tmp_path):
    printed = cli("generate", "aprilgrid", "--cols", "7", "--rows", "5", "--tag-size", "0.06", "--spacing", "0.25")
    assert printed.returncode == 0, printed.stderr
    (tmp_path / "grid.yaml").write_text(printed.stdout)
    grid = load_target(tmp_path / "grid.yaml")
    assert (grid.grid.cols, grid.grid.rows, grid.tag(0).size_m) == (7, 5, pytest.approx(0.06))
    written = cli("generate", "aprilgrid", "--out", str(tmp_path / "out.yaml"))
    assert written.returncode == 0 and (tmp_path / "out.yaml").read_text() == KALIBR_YAML
    again = cli("generate", "aprilgrid", "--out", str(tmp_path / "out.yaml"))
    assert again.returncode == 2 and "already exists" in again.stderr


def test_every_real_frame_decodes_as_many_tags_as_opencv():
    """Eight real AprilGrid frames, three of them 16-bit fisheye (TUM-VI): read as 8-bit
    scaled to the bits they use, every tag OpenCV decodes is decoded and keeps its saddle
    corners (the AprilTag library alone decodes none of them)."""
    detector = TagDetector("tag36h11", border_bits=2)
    assert sorted(p.name for p in real_photographs("aprilgrid-real").glob("*.png")) == sorted(OPENCV_COUNTS)
    for path in sorted(real_photographs("aprilgrid-real").glob("*.png")):
        image = read_image(path)
        found = detector.detect(image)
        refined = [refine_corners(image, d, None, detector.cells, saddles=True) for d in found]
        assert sum(r is not None for r in refined) >= OPENCV_COUNTS[path.name], path.name
        assert TagDetector("tag36h11").detect(image, None, 1.0) == []  # the one-cell-border decoder


def test_the_euroc_frame_fits_kalibrs_grid_where_opencvs_corners_do_not():
    """With EuRoC's published calibration, the saddle corners of all 35 tags fit one pose of
    Kalibr's grid (0.25 px RMS) and lie on the rows' lines (0.15 px); OpenCV's own corners,
    0.5-1.5 px inside the tags, do not (2.5 px, 0.7 px)."""
    grid = make_aprilgrid()
    image = read_image(real_photographs("aprilgrid-real") / "EuRoC.png")
    detector = TagDetector("tag36h11", border_bits=2)
    raw = unique_target_detections(detector.detect(image), grid)
    saddle = [refine_corners(image, d, EUROC, detector.cells, saddles=True) for d in raw]
    assert all(d is not None for d in saddle) and len(saddle) == 35

    def fit(detections):
        ids = tuple(d.tag_id for d in detections)
        return plane_solutions(grid.corners_of(ids), np.concatenate([d.corners for d in detections]), EUROC)[0][0]

    assert fit(saddle) < 0.4 and fit(raw) > 4 * fit(saddle)


def test_cubeloc_pose_on_the_real_euroc_frame(cli, tmp_path):
    (tmp_path / "grid.yaml").write_text(KALIBR_YAML)
    write_camera_info(tmp_path / "euroc.yaml", EUROC)
    frame = real_photographs("aprilgrid-real") / "EuRoC.png"
    result = cli("pose", "--target", str(tmp_path / "grid.yaml"), "--calib", str(tmp_path / "euroc.yaml"), str(frame))
    assert result.returncode == 0, result.stderr
    line = json.loads(result.stdout)
    assert line["ok"] and line["planes"] == 1 and len(line["tags"]) == 35
    position_sigma = np.sqrt(np.diag(np.array(line["covariance"]).reshape(6, 6))[:3])
    # the board ~1 m in front, held up; the 35 tags' edges put the camera within a millimetre
    assert 0.9 < line["position"][2] < 1.1 and np.all(position_sigma < 0.002)


def test_a_rendered_aprilgrid_poses_within_half_the_corners_only_baseline():
    """Kalibr's grid rendered with its squares and two-cell borders, 0.5-3 m and up to 60 deg
    off, blurred: cubeloc's pose against SQPnP + LM on OpenCV's corners of every tag, on the
    same frames (bench planar, 40 views: 0.22 against 6.89 mm median)."""
    grid, camera = make_aprilgrid(), paper_camera()
    detector = TagDetector("tag36h11", border_bits=2)
    ours, theirs = [], []
    for seed in range(8):
        truth, image, _ = rendered_board_view(grid, camera, seed)
        result = TargetPoseProcessor(grid, camera).process(image, 0, seed)
        assert result.estimate is not None, (seed, result.detail)
        baseline = decoded_corners_pose(image, grid, camera, detector)
        ours.append(np.linalg.norm(result.estimate.T_world_camera.translation - truth.translation))
        theirs.append(np.linalg.norm(baseline.translation - truth.translation))
    assert np.median(ours) <= 0.5 * np.median(theirs), (np.median(ours), np.median(theirs))
    assert max(ours) < 0.01


def test_a_grid_render_puts_its_squares_at_the_tags_corners():
    """The synthetic camera draws the gap squares: the pixel just outside a tag's corner,
    diagonally, is ink, and so is the saddle's opposite quadrant inside the border."""
    grid, camera = make_aprilgrid(rows=2, cols=2, tag_size_m=0.1), paper_camera()
    centre = grid.corners_of(grid.ids).mean(axis=0)
    from cubeloc.positioning.geometry import look_at

    image = render_view(look_at(centre + [0.0, 0.0, 0.6], centre, up=(0.0, 1.0, 0.0)), calibration=camera,
                        target=grid, room=False, noise_sigma=0.0)
    corners = TagDetector("tag36h11", border_bits=2).detect(image)
    assert len(corners) == 4
    tag = corners[0].corners
    outward = tag[0] - tag.mean(axis=0)
    step = 4.0 * outward / np.linalg.norm(outward)
    inside, outside = tag[0] - step, tag[0] + step
    assert image[int(round(inside[1])), int(round(inside[0]))] < 80
    assert image[int(round(outside[1])), int(round(outside[0]))] < 80


def test_calibrate_on_25_aprilgrid_views_from_kalibrs_file(cli, tmp_path):
    """``cubeloc calibrate --board kalibr:FILE.yaml`` on 25 rendered views of a 6 x 6 grid
    (640 x 512): fx within 0.1 % of the camera that rendered them, at the noise floor."""
    from cubeloc.calib.boards import parse_board
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.fakes.board_views import synthetic_board_camera, write_board_images

    (tmp_path / "grid.yaml").write_text(KALIBR_YAML)
    camera = synthetic_board_camera(640, 512)
    write_board_images(tmp_path / "views", parse_board(f"kalibr:{tmp_path / 'grid.yaml'}"), camera, 25, seed=5)
    out = tmp_path / "cam.yaml"
    result = cli("calibrate", "--images", str(tmp_path / "views"), "--board", f"kalibr:{tmp_path / 'grid.yaml'}",
                 "--out", str(out))
    assert result.returncode == 0, result.stderr
    solved = read_camera_info(out)
    assert abs(solved.fx / camera.fx - 1) < 0.001 and abs(solved.fy / camera.fy - 1) < 0.001, (solved.fx, camera.fx)
    assert solved.metadata["rms_px"] < 0.1 and solved.metadata["board"] == "aprilgrid:6x6:0.088:0.3"
    assert solved.metadata["views"] >= 23
    # a grid with other counts is named, not solved with its tags in the wrong places
    wrong = cli("calibrate", "--images", str(tmp_path / "views"), "--board", "aprilgrid:5x5:0.088:0.3",
                "--out", str(tmp_path / "wrong.yaml"))
    assert wrong.returncode == 2 and "tags up to id 35" in wrong.stderr and "\n" not in wrong.stderr.strip()
