"""Fisheye lenses (ROS' ``equidistant`` model, OpenCV's cv2.fisheye): calibration from a
synthetic fisheye and from the real TUM-VI frames, a target's pose and the tracker behind
one. The model itself against fakes' independent optics: tests/test_camera_model.py."""

from __future__ import annotations

import json
import shutil

import numpy as np
from conftest import real_photographs

from cubeloc.calib.boards import parse_board
from cubeloc.calib.camera_info import read_camera_info
from cubeloc.fakes import render_view
from cubeloc.fakes.board_views import write_board_images
from cubeloc.fakes.lenses import lens_calibration
from cubeloc.positioning.geometry import Transform, look_at
from cubeloc.positioning.single_frame import TargetPoseProcessor
from cubeloc.positioning.target import make_cube

GRID = "aprilgrid:6x6:0.088:0.3"
# TUM-VI cam0's published equidistant calibration at 512 x 512; its 1024 x 1024 frames are
# the same sensor unbinned: f doubles, c goes to 2 c + 0.5
TUM_VI_1024 = (2 * 190.97847715128717, 2 * 254.93170605935475 + 0.5, 2 * 256.8974428996504 + 0.5)


def test_calibrate_a_synthetic_fisheye_from_25_aprilgrid_views(cli, tmp_path):
    """640x480, f 280 px, 131 deg across (fakes.lenses 'fisheye'): fx within 0.2 % and the
    fit at the corners' noise (measured: -0.01 %, 0.05 px)."""
    camera = lens_calibration("fisheye")
    write_board_images(tmp_path / "views", parse_board(GRID), camera, 25, seed=4)
    out = tmp_path / "fisheye.yaml"
    result = cli("calibrate", "--images", str(tmp_path / "views"), "--board", GRID, "--model", "fisheye",
                 "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "model equidistant" in result.stdout and "k4" in result.stdout
    solved = read_camera_info(out)
    assert solved.distortion_model == "equidistant" and len(solved.distortion) == 4
    assert abs(solved.fx / camera.fx - 1) < 0.002 and abs(solved.fy / camera.fy - 1) < 0.002, (solved.fx, camera.fx)
    assert np.hypot(solved.cx - camera.cx, solved.cy - camera.cy) < 0.5
    assert solved.metadata["rms_px"] < 0.15


def test_calibrate_the_real_tum_vi_frames_as_a_fisheye(cli, tmp_path):
    """The five TUM-VI frames of ../shared/data/aprilgrid-real (16-bit, 1024x1024): a fit at
    0.09 px that agrees with TUM-VI's own published calibration of that camera (measured:
    fx -0.12 %, the principal point within 0.2 px; OpenCV's aruco corners fit at 2.06 px)."""
    frames = real_photographs("aprilgrid-real")
    for name in ("TUM_VI.png", "r45.png", "right.png", "top.png", "top_right.png"):
        shutil.copy(frames / name, tmp_path / name)
    out = tmp_path / "tum_vi.yaml"
    result = cli("calibrate", "--images", str(tmp_path / "*.png"), "--board", GRID, "--model", "fisheye",
                 "--out", str(out))
    assert result.returncode == 0, result.stderr
    solved = read_camera_info(out)
    fx, cx, cy = TUM_VI_1024
    assert solved.metadata["views"] == 5 and solved.metadata["rms_px"] < 0.15
    assert abs(solved.fx / fx - 1) < 0.005, solved.fx
    assert np.hypot(solved.cx - cx, solved.cy - cy) < 1.0, (solved.cx, solved.cy)
    # and the grid posed through it, Kalibr's file as the target (measured: 0.08 px)
    (tmp_path / "grid.yaml").write_text("target_type: 'aprilgrid'\ntagCols: 6\ntagRows: 6\ntagSize: 0.088\n"
                                        "tagSpacing: 0.3\n")
    posed = cli("pose", "--target", str(tmp_path / "grid.yaml"), "--calib", str(out), str(tmp_path / "TUM_VI.png"))
    assert posed.returncode == 0, posed.stderr
    line = json.loads(posed.stdout)
    assert line["ok"] and line["planes"] == 1 and len(line["tags"]) == 36 and line["reproj_rms_px"] < 0.2


def test_a_cube_posed_through_a_fisheye_to_its_edge():
    """The cube 0.5-1 m away, the camera turned 0-50 deg away from it, a 1.3 MP fisheye
    (fakes.lenses 'fisheye_hd'): posed from two or three faces within 3 mm (measured
    0.02-0.27 mm)."""
    camera, cube = lens_calibration("fisheye_hd"), make_cube()
    rng = np.random.default_rng(7)
    errors = []
    for seed in range(6):
        distance, azimuth = rng.uniform(0.5, 1.0), rng.uniform(0.0, 2 * np.pi)
        eye = np.array([np.cos(azimuth), np.sin(azimuth), 0.5]) * distance
        aimed = look_at(eye, np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
        off_axis = np.radians(10.0 * seed)  # turn the camera away: the cube towards the edge
        turn = Transform.from_rvec_tvec(np.array([0.0, off_axis, 0.0]), np.zeros(3))
        truth = Transform(aimed.rotation @ turn.rotation, aimed.translation)
        image = render_view(truth, calibration=camera, target=cube, seed=seed)
        result = TargetPoseProcessor(cube, camera).process(image, 0, seed)
        assert result.estimate is not None, (seed, result.detail)
        assert result.estimate.planes >= 2
        errors.append(np.linalg.norm(result.estimate.T_world_camera.translation - truth.translation))
    assert max(errors) < 0.003, errors


def test_the_tracker_keeps_its_map_behind_a_fisheye(tmp_path_factory):
    """spin_in_place through the 1.3 MP fisheye: every frame with a pose, as behind the
    paper's lens (measured: 100 %, 1.9 mm RMS; the paper camera at half resolution
    100 %, under 8 mm)."""
    from test_tracking_scenarios import replay

    score, _, _ = replay(tmp_path_factory, "spin_in_place", calibration=lens_calibration("fisheye_hd"))
    assert score.coverage >= 0.99 and score.rmse_m < 0.008, score


def test_behind_a_small_fisheye_the_map_starts_on_the_poses_the_cube_gives(tmp_path_factory):
    """spin_in_place through a 640x480 fisheye (f 280 px): the cube 2.25 m away is posed
    only to 40-100 mm (its tags 18 px wide, fitting to 0.24-0.7 px), never within the
    bounds that let a pose begin or anchor the map (10 and 5 mm, 0.25 px). A camera that
    never meets them is held to twice what it can do (``anchor.best_ratio``): the map
    starts, on a pair whose baseline its poses measure to 50 % (``init.max_scale_std``),
    and carries the pose where the cube is out of view. Measured: 99.1 % of frames, 45.5
    mm RMS, 136 mm max, 99.5 % inside 3 sigma, none beyond 5; before, 45 % (the cube's
    own poses)."""
    from test_tracking_scenarios import replay

    score, _, _ = replay(tmp_path_factory, "spin_in_place", calibration=lens_calibration("fisheye"))
    assert score.coverage >= 0.95 and score.rmse_m < 0.08 and score.max_m < 0.2, score
    assert score.consistent >= 0.97 and score.beyond_5_sigma == 0, score


def test_a_very_wide_fisheye_is_solved_from_another_start():
    """f 200 px at 640x480: 12 views of a grid projected exactly (0.05 px of noise). From
    OpenCV's own start (f = larger side / pi) cv2.fisheye.calibrate ends at 72 px; the solve
    starts from several focal lengths and keeps the best."""
    from cubeloc.calib.camera_info import CameraCalibration
    from cubeloc.calib.solve import SolveOptions, View, solve
    from cubeloc.fakes.board_views import random_poses
    from cubeloc.fakes.optics import project

    board = parse_board(GRID)
    camera = CameraCalibration(640, 480, np.array([[200.0, 0.0, 321.0], [0.0, 200.0, 239.0], [0.0, 0.0, 1.0]]),
                               np.array([0.01, -0.004, 0.002, -0.0005]), "equidistant")
    rng = np.random.default_rng(3)
    views = []
    for index, (rotation, translation) in enumerate(random_poses(board, camera, 12, rng)):
        pixels = project(board.object_points().astype(np.float64) @ rotation.T + translation, camera)
        views.append(View(str(index), (pixels + rng.normal(0.0, 0.05, pixels.shape)).astype(np.float32),
                          board.object_points()))
    solution = solve(views, camera.size, SolveOptions(model="equidistant"))
    assert solution.rms_px < 0.1 and abs(solution.camera_matrix[0, 0] / 200.0 - 1) < 0.001, solution.rms_px


def test_the_tag_search_field_of_a_fisheye_seeing_past_90_degrees():
    """TUM-VI's camera (1024x1024, f 382 px) sees 108 deg off axis in its image corners: those
    rays come back from cv2.fisheye mirrored through the centre (x, y of +-106), and the tag
    search's field is bounded by the rays that are ahead (x, y within +-4.5)."""
    from cubeloc.calib.camera_info import CameraCalibration
    from cubeloc.positioning.tag_search import _field_of_view

    camera = CameraCalibration(1024, 1024, np.array([[381.5, 0.0, 510.2], [0.0, 381.3, 514.2], [0.0, 0.0, 1.0]]),
                               np.array([0.0044, -0.0001, -0.002, 0.0004]), "equidistant")
    low, high = _field_of_view(camera)
    assert np.all(low < -4.0) and np.all(low > -4.6) and np.all(high > 4.0) and np.all(high < 4.6), (low, high)


def _tum_vi_camera():
    from cubeloc.calib.camera_info import CameraCalibration

    return CameraCalibration(1024, 1024, np.array([[381.5, 0.0, 510.2], [0.0, 381.3, 514.2], [0.0, 0.0, 1.0]]),
                             np.array([0.0044, -0.0001, -0.002, 0.0004]), "equidistant")


def _pixel_at(camera, theta_deg: float, azimuth: float) -> np.ndarray:
    """The pixel of the ray ``theta_deg`` off axis, from the equidistant formula itself."""
    theta = np.radians(theta_deg)
    k = camera.distortion
    theta_d = theta * (1 + k[0] * theta**2 + k[1] * theta**4 + k[2] * theta**6 + k[3] * theta**8)
    return np.array([[camera.fx * theta_d * np.cos(azimuth) + camera.cx,
                      camera.fy * theta_d * np.sin(azimuth) + camera.cy]])


def test_pixels_seeing_past_90_degrees_are_told_apart_and_kept_out_of_the_features():
    """TUM-VI's image corners look 108 deg off axis. Such a ray has no normalised (x, y, 1),
    and undistort() returns it mirrored through the centre, so ``ahead`` tells those pixels
    apart (89 deg ahead, 91 deg not, in every direction), and neither the tracker's features
    nor the relocaliser's corners are born there, nor do tracks go there."""
    from cubeloc.positioning.camera_model import ahead, ahead_mask
    from cubeloc.positioning.tracking.features import KltFrontEnd
    from cubeloc.positioning.tracking.options import FeatureOptions

    camera = _tum_vi_camera()
    for azimuth in np.linspace(0.0, 2 * np.pi, 9)[:-1]:
        assert ahead(_pixel_at(camera, 89.0, azimuth), camera).all()
        assert not ahead(_pixel_at(camera, 91.0, azimuth), camera).any()
    assert ahead_mask(lens_calibration("fisheye")) is None  # 131 deg across: its corners 82 deg off
    assert ahead_mask(lens_calibration("vga")) is None  # a pinhole model looks ahead everywhere
    mask = ahead_mask(camera)
    assert mask[0, 0] == 0 and mask[514, 510] == 255 and 0.85 < (mask > 0).mean() < 0.95

    rng = np.random.default_rng(0)
    texture = (rng.random((64, 64)) * 255).astype(np.uint8)
    image = np.kron(texture, np.ones((16, 16), np.uint8))  # corners everywhere
    for scale in (1, 2):
        front_end = KltFrontEnd(FeatureOptions(max_features=4000, detect_scale=scale), mask)
        front_end.track(image)
        born = front_end.detect(image).pixels
        assert len(born) > 500 and ahead(born, camera).all()
        everywhere = KltFrontEnd(FeatureOptions(max_features=4000, detect_scale=scale))
        everywhere.track(image)
        assert not ahead(everywhere.detect(image).pixels, camera).all()  # the mask is what keeps them out
    # the view moves 60 px towards the top left corner: the tracks carried past 90 deg end
    moved = np.full_like(image, image.mean())
    moved[:-60, :-60] = image[60:, 60:]
    tracks = front_end.track(moved)
    assert len(tracks.ids) > 100 and ahead(tracks.pixels, camera).all()
    assert not ahead(everywhere.track(moved).pixels, camera).all()
