"""Single-frame pose on the synthetic camera: the paper's camera, sensor noise sigma 2,
the 18 cm cube. Seeded; margins on the issue's targets."""

from __future__ import annotations

import numpy as np
import pytest
from structlog.testing import capture_logs

from cubeloc.calib.camera_info import paper_camera
from cubeloc.fakes import render_view
from cubeloc.fakes.optics import project
from cubeloc.positioning.detection import TagDetection, TagDetector, refine_corners
from cubeloc.positioning.edge_alignment import EdgeOptions
from cubeloc.positioning.estimator import PoseState
from cubeloc.positioning.evaluation import CHI2_3DOF_997
from cubeloc.positioning.geometry import look_at
from cubeloc.positioning.single_frame import TargetPoseProcessor
from cubeloc.positioning.target import make_cube
from cubeloc.positioning.target_pose import PoseOptions, estimate_target_pose

CUBE = make_cube()
CAMERA = paper_camera()


def three_face_views(distance_m: float, count: int, seed: int):
    """Cameras around the +x/+y/top corner (faces ids 0, 1, 4 in view), aimed near the
    cube centre, at ``distance_m``."""
    rng = np.random.default_rng(seed)
    views = []
    for _ in range(count):
        azimuth = np.radians(45 + rng.uniform(-15, 15))
        elevation = np.radians(32 + rng.uniform(-8, 8))
        direction = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                              np.sin(elevation)])
        views.append(look_at(direction * distance_m, rng.normal(0, 0.03, 3)))
    return views


def position_errors(views, *, hidden_tags=(), seed=0, edge_alignment=True):
    processor = TargetPoseProcessor(CUBE, CAMERA, edge_alignment=edge_alignment)
    errors, planes = [], []
    for k, truth in enumerate(views):
        processor.reset()
        result = processor.process(render_view(truth, hidden_tags=hidden_tags, seed=seed + k), 0, k)
        assert result.estimate is not None, result.detail
        assert result.estimate.state is PoseState.TARGET
        errors.append(np.linalg.norm(result.estimate.T_world_camera.translation - truth.translation))
        planes.append(result.estimate.planes)
    return np.array(errors), planes


# Issue 9's goals, on the same views as the corners-only baseline (target pose issue):
# median 0.5 mm at 2 m and 2.5 mm at 4 m (baseline measured here 0.22 mm and 1.3 mm;
# with the edge alignment 0.08 mm and 0.63 mm).
def test_three_faces_at_2_m_within_half_a_millimetre():
    errors, planes = position_errors(three_face_views(2.0, 8, seed=1))
    assert planes == [3] * 8
    assert np.median(errors) <= 0.5e-3


def test_three_faces_at_4_m_within_2_5_mm():
    errors, planes = position_errors(three_face_views(4.0, 8, seed=2), seed=100)
    assert planes == [3] * 8
    assert np.median(errors) <= 2.5e-3


def test_two_faces_within_one_and_a_half_times_the_three_face_error():
    views = three_face_views(2.0, 8, seed=3)
    three, _ = position_errors(views, seed=200)
    two, planes = position_errors(views, hidden_tags=(4,), seed=200)  # top face blank
    assert planes == [2] * 8
    assert np.median(two) <= 1.5 * max(np.median(three), 0.05e-3)


@pytest.mark.slow
def test_static_stability_over_100_frames_at_1_9_m():
    truth = three_face_views(1.9, 1, seed=4)[0]
    # A camera at rest: one noiseless frame, then fresh sensor noise (sigma 2) per frame,
    # the same frames for the edge alignment and for the corners-only baseline.
    still = render_view(truth, noise_sigma=0.0).astype(np.float32)
    rng = np.random.default_rng(4)
    aligned, corners_only = TargetPoseProcessor(CUBE, CAMERA), TargetPoseProcessor(CUBE, CAMERA, edge_alignment=False)
    positions, baseline, regions = [], [], 0
    for k in range(100):
        noise = rng.standard_normal(still.shape, dtype=np.float32) * np.float32(2.0)
        frame = np.clip(np.rint(still + noise), 0, 255).astype(np.uint8)
        result = aligned.process(frame, k, k)
        assert result.estimate is not None and result.estimate.planes == 3
        positions.append(result.estimate.T_world_camera.translation)
        regions += aligned.last_search == "predicted"
        if k % 2 == 0:
            baseline.append(corners_only.process(frame, k, k).estimate.T_world_camera.translation)
    positions, baseline = np.array(positions), np.array(baseline)
    # Stability as the paper measures it (a camera at rest, truth unknown): RMSE of the
    # outputs about their mean, per axis; and their offset from the truth (bias).
    # Issue 9's goals: 0.07 mm per axis and 0.3 mm (measured 0.04-0.05 mm and 0.16 mm;
    # the corners-only pose 0.09-0.10 mm and 0.26 mm here; its bias is not always larger
    # than the edges' at other views: 0.06-0.17 mm for both, so only the RMSE is compared).
    rmse_per_axis = np.sqrt(np.mean((positions - positions.mean(axis=0)) ** 2, axis=0))
    bias = np.linalg.norm(positions.mean(axis=0) - truth.translation)
    assert np.all(rmse_per_axis <= 0.07e-3), rmse_per_axis
    assert bias <= 0.3e-3, bias
    baseline_rmse = np.sqrt(np.mean((baseline - baseline.mean(axis=0)) ** 2, axis=0))
    assert np.linalg.norm(rmse_per_axis) * 1.5 <= np.linalg.norm(baseline_rmse)
    assert regions == 99  # every frame after the first searched the predicted region only
    # The covariance the pose carries: its noise share matches the scatter (within a factor
    # of 2); the whole of it, with the share every frame of a still scene has in common
    # (EdgeOptions.edge_bias_per_blur), covers the offset from the truth they share.
    claimed = result.estimate.covariance[:3, :3]
    noise_only = PoseOptions(edges=EdgeOptions(edge_bias_per_blur=0.0))
    noise = TargetPoseProcessor(CUBE, CAMERA, noise_only).process(frame, 100, 100).estimate.covariance[:3, :3]
    predicted = np.sqrt(np.diag(noise))
    assert np.all(predicted <= 2.0 * rmse_per_axis) and np.all(predicted >= 0.5 * rmse_per_axis), predicted
    offset = positions.mean(axis=0) - truth.translation
    assert offset @ np.linalg.solve(claimed, offset) <= CHI2_3DOF_997, (offset, np.sqrt(np.diag(claimed)))
    assert np.all(np.sqrt(np.diag(claimed)) <= 0.5e-3), np.sqrt(np.diag(claimed))  # measured 0.32-0.38 mm


def test_library_corners_are_in_opencv_pixels_after_the_half_pixel_shift():
    # Raw detector corners against the exact projection of the cube: no half-pixel offset
    # remains. Putting it back turns the camera by ~0.02 deg (1.7 mm of aim at 4 m), four
    # times the error of the pose from the right corners.
    truth = three_face_views(2.0, 1, seed=5)[0]
    image = render_view(truth, seed=5)
    detections = TagDetector().detect(image)
    offsets = np.concatenate([
        d.corners - project(truth.inverse().apply(CUBE.tag(d.tag_id).corners), CAMERA) for d in detections
    ])
    assert len(detections) == 3
    assert np.all(np.abs(offsets.mean(axis=0)) < 0.08)
    refined = [refine_corners(image, d, CAMERA) for d in detections]
    right = estimate_target_pose(refined, CUBE, CAMERA).pose
    shifted = [TagDetection(d.tag_id, d.corners + 0.5, d.decision_margin, d.hamming) for d in refined]
    wrong = estimate_target_pose(shifted, CUBE, CAMERA).pose
    assert wrong.T_world_camera.rotation_angle_to(truth) > 3 * right.T_world_camera.rotation_angle_to(truth)
    assert np.degrees(wrong.T_world_camera.rotation_angle_to(truth)) > 0.015


def test_one_face_waits_and_foreign_tags_are_no_target():
    processor = TargetPoseProcessor(CUBE, CAMERA)
    head_on = look_at([1.5, 0.0, 0.0], np.zeros(3))  # only the +x face (id 0)
    result = processor.process(render_view(head_on, seed=6), 0, 0)
    assert result.estimate is None and result.status == "one_face" and result.tags_seen == (0,)
    other_cube = make_cube(ids=(20, 21, 22, 23, 24, 25))
    result = processor.process(render_view(three_face_views(2.0, 1, 7)[0], target=other_cube, seed=7), 0, 1)
    assert result.estimate is None and result.status == "no_target" and result.tags_seen == ()


def test_bad_images_are_reported_not_raised():
    processor = TargetPoseProcessor(CUBE, CAMERA)
    for image in (np.zeros((1024, 1280), np.uint16), np.zeros((1024, 1280, 3), np.uint8),
                  np.zeros((100, 100), np.uint8), "not an array"):
        result = processor.process(image, 0, 0)
        assert result.estimate is None and result.status == "bad_image"


def test_a_wrong_tag_size_in_the_target_file_is_warned_about():
    truth = three_face_views(1.5, 1, seed=8)[0]
    image = render_view(truth, seed=8)  # the real cube: 144 mm tags
    misconfigured = make_cube(0.18, 0.12)  # the file says 120 mm (e.g. measured inside the border)
    with capture_logs() as logs:
        wrong = TargetPoseProcessor(misconfigured, CAMERA).process(image, 0, 0)
        right = TargetPoseProcessor(CUBE, CAMERA).process(image, 0, 0)
    assert right.estimate is not None
    # The residuals refuse the pose, and the reason says what to check.
    assert wrong.estimate is None and wrong.status == "reprojection"
    assert "tag_size" in wrong.detail and "144" in wrong.detail
    warnings = [entry for entry in logs if entry["event"] == "target_scale_mismatch"]
    assert len(warnings) == 1
    assert warnings[0]["tag_scale"] == pytest.approx(1.2, rel=0.02)
