"""The pose solver on corners projected by the exact optics, with seeded pixel noise."""

from __future__ import annotations

import numpy as np
import pytest

from cubeloc.calib.camera_info import paper_camera
from cubeloc.fakes.optics import project
from cubeloc.positioning.detection import TagDetection
from cubeloc.positioning.geometry import Transform, look_at
from cubeloc.positioning.tag_scale import check_tag_scale
from cubeloc.positioning.target import make_cube
from cubeloc.positioning.target_pose import (
    PoseOptions,
    Refusal,
    count_planes,
    estimate_target_pose,
)

CUBE = make_cube()
CAMERA = paper_camera()


def corner_view(T_world_camera: Transform, tag_ids, *, sigma_px=0.0, seed=0, target=CUBE):
    """Detections of ``tag_ids`` as the camera at ``T_world_camera`` sees them."""
    rng = np.random.default_rng(seed)
    T_camera_world = T_world_camera.inverse()
    detections = []
    for tag_id in tag_ids:
        pixels = project(T_camera_world.apply(target.tag(tag_id).corners), CAMERA)
        detections.append(TagDetection(tag_id, pixels + rng.normal(0, sigma_px, (4, 2)), 100.0, 0))
    return detections


def three_face_camera(distance_m: float) -> Transform:
    # Looking at the +x/+y/+z corner of the cube: faces +x (id 0), +y (id 1), top (id 4).
    direction = np.array([1.0, 1.0, 0.8]) / np.linalg.norm([1.0, 1.0, 0.8])
    return look_at(direction * distance_m, np.zeros(3))


def test_exact_corners_give_the_exact_pose():
    truth = three_face_camera(2.0)
    outcome = estimate_target_pose(corner_view(truth, [0, 1, 4]), CUBE, CAMERA)
    pose = outcome.pose
    assert pose is not None and pose.planes == 3 and pose.tag_ids == (0, 1, 4)
    assert np.linalg.norm(pose.T_world_camera.translation - truth.translation) < 1e-6
    assert pose.T_world_camera.rotation_angle_to(truth) < 1e-7
    assert pose.reproj_rms_px < 1e-4


def test_noise_gives_millimetres_and_a_covariance_that_matches_the_scatter():
    truth = three_face_camera(2.0)
    positions, covariances = [], []
    for seed in range(40):
        pose = estimate_target_pose(corner_view(truth, [0, 1, 4], sigma_px=0.1, seed=seed), CUBE, CAMERA).pose
        positions.append(pose.T_world_camera.translation)
        covariances.append(pose.covariance)
    errors = np.linalg.norm(np.array(positions) - truth.translation, axis=1)
    assert np.median(errors) < 2e-3
    scatter = np.cov(np.array(positions).T)
    predicted = np.mean(covariances, axis=0)[:3, :3]
    # The predicted standard deviation along the worst axis is right within a factor 2.
    ratio = np.sqrt(np.linalg.eigvalsh(scatter)[-1] / np.linalg.eigvalsh(predicted)[-1])
    assert 0.5 < ratio < 2.0
    assert np.all(np.linalg.eigvalsh(covariances[0]) > 0)


def test_two_faces_pose_is_flagged_and_less_accurate():
    truth = three_face_camera(2.0)
    err3, err2 = [], []
    for seed in range(20):
        p3 = estimate_target_pose(corner_view(truth, [0, 1, 4], sigma_px=0.15, seed=seed), CUBE, CAMERA).pose
        p2 = estimate_target_pose(corner_view(truth, [0, 1], sigma_px=0.15, seed=seed), CUBE, CAMERA).pose
        assert p2.planes == 2
        err3.append(np.linalg.norm(p3.T_world_camera.translation - truth.translation))
        err2.append(np.linalg.norm(p2.T_world_camera.translation - truth.translation))
    assert np.median(err3) < np.median(err2)
    refused = estimate_target_pose(corner_view(truth, [0, 1]), CUBE, CAMERA, PoseOptions(allow_two_faces=False))
    assert refused.pose is None and refused.refusal is Refusal.TWO_FACES


def test_one_face_waits_unless_allowed_with_a_previous_pose():
    truth = look_at([2.0, 0.3, 0.2], np.zeros(3))
    view = corner_view(truth, [0], sigma_px=0.05, seed=3)
    assert estimate_target_pose(view, CUBE, CAMERA).refusal is Refusal.ONE_FACE
    allowed = PoseOptions(allow_one_face=True)
    assert estimate_target_pose(view, CUBE, CAMERA, allowed).refusal is Refusal.ONE_FACE  # no previous
    previous = look_at([2.02, 0.31, 0.18], np.zeros(3))
    pose = estimate_target_pose(view, CUBE, CAMERA, allowed, previous=previous).pose
    assert pose is not None and pose.planes == 1
    assert np.linalg.norm(pose.T_world_camera.translation - truth.translation) < 0.03


def nees(pose, truth: Transform) -> float:
    error = pose.T_world_camera.translation - truth.translation
    return float(error @ np.linalg.solve(pose.covariance[:3, :3], error))


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_one_tag_alone_is_refused_even_where_its_two_solutions_differ(seed):
    """At 1 m and 40 deg the wrong solution of one tag fits 6.7 px RMS worse, but 4
    corners cannot show a biased edge: still ``one_face``."""
    truth = look_at([1.0, 0.8, 0.3], np.zeros(3))
    outcome = estimate_target_pose(corner_view(truth, [0], sigma_px=0.05, seed=seed), CUBE, CAMERA)
    assert outcome.pose is None and outcome.refusal is Refusal.ONE_FACE


def test_foreign_tags_are_ignored_and_no_target_is_said():
    truth = three_face_camera(2.0)
    stray = TagDetection(77, np.array([[10.0, 10], [50, 10], [50, 50], [10, 50]]), 90.0, 0)
    outcome = estimate_target_pose([stray, *corner_view(truth, [0, 1, 4])], CUBE, CAMERA)
    assert outcome.pose.tag_ids == (0, 1, 4)
    assert estimate_target_pose([stray], CUBE, CAMERA).refusal is Refusal.NO_TARGET


def test_a_wrong_corner_is_gated_by_the_residuals():
    truth = three_face_camera(2.0)
    view = corner_view(truth, [0, 1, 4], sigma_px=0.05)
    corners = view[1].corners.copy()
    corners[2] += (9.0, -7.0)  # a mis-fitted quad corner
    view[1] = TagDetection(1, corners, 50.0, 0)
    # Three tags: the bad one is left out and the other two give a (two-face) pose.
    outcome = estimate_target_pose(view, CUBE, CAMERA)
    assert outcome.pose.tag_ids == (0, 4) and outcome.pose.planes == 2
    assert "tag 1 left out" in outcome.detail
    assert np.linalg.norm(outcome.pose.T_world_camera.translation - truth.translation) < 0.01
    # Two tags: nothing to leave out, so no pose.
    outcome = estimate_target_pose(view[:2], CUBE, CAMERA)
    assert outcome.pose is None and outcome.refusal is Refusal.REPROJECTION
    assert "reprojection RMS" in outcome.detail


def test_count_planes_groups_parallel_tags():
    assert count_planes(CUBE, [0]) == 1 and count_planes(CUBE, [0, 2]) == 2
    assert count_planes(CUBE, [0, 1, 4]) == 3


@pytest.mark.parametrize("printed_scale", [1.0, 1.25])
def test_tag_scale_check_finds_a_wrong_tag_size(printed_scale):
    # The cube really carries tags printed ``printed_scale`` times the configured size.
    printed = make_cube(0.18, 0.144 * printed_scale if printed_scale * 0.144 <= 0.18 else 0.18)
    truth = three_face_camera(1.5)
    view = corner_view(truth, [0, 1, 4], sigma_px=0.1, seed=1, target=printed)
    pose = estimate_target_pose(view, CUBE, CAMERA, PoseOptions(max_reproj_rms_px=50)).pose
    check = check_tag_scale(view, CUBE, CAMERA, pose)
    assert check.tag_scale == pytest.approx(printed_scale, rel=0.01)
    assert check.agrees == (printed_scale == 1.0)
    if not check.agrees:
        assert check.implied_side_m == pytest.approx(0.18 / 1.25, rel=0.01)
        assert "tag_size" in check.message()


def test_a_small_edge_on_tag_is_weighted_down_and_refuses_only_an_uncertain_pose():
    from cubeloc.positioning.range_map import camera_on_sphere

    truth = camera_on_sphere(80.0, 30.0, 4.0)  # face +x (id 0) at 81 deg, about 10 px wide
    view = corner_view(truth, [0, 1, 4], sigma_px=0.05, seed=2)
    outcome = estimate_target_pose(view, CUBE, CAMERA)
    assert outcome.pose.tag_ids == (0, 1, 4) and "weighted down" in outcome.detail
    assert np.linalg.norm(outcome.pose.T_world_camera.translation - truth.translation) < 0.003  # measured 0.9 mm
    # +x and the top only: the steep tag is the second plane; the pose stands, its
    # covariance says how sure it is (measured 1.1 mm off, sigma 1.7 mm)
    two = estimate_target_pose([view[0], view[2]], CUBE, CAMERA)
    assert two.pose is not None and two.pose.planes == 2 and nees(two.pose, truth) < 14.2
    strict = PoseOptions(max_position_sigma_m=0.001)
    refused = estimate_target_pose([view[0], view[2]], CUBE, CAMERA, strict)
    assert refused.pose is None and refused.refusal is Refusal.OBLIQUE and "sigma" in refused.detail
    # A wrong corner on the steep tag (1 px, on a tag 25 px wide at 2 m) would move the
    # weighted pose by 3 mm: the others' pose does not predict it, so the tag is left out.
    truth = camera_on_sphere(75.0, 30.0, 2.0)
    view = corner_view(truth, [0, 1, 4], sigma_px=0.05, seed=2)
    wrong = view[0].corners.copy()
    wrong[1] += (1.0, -1.0)
    outcome = estimate_target_pose([TagDetection(0, wrong, 50.0, 0), view[1], view[2]], CUBE, CAMERA)
    assert outcome.pose.tag_ids == (1, 4) and "disagree" in outcome.detail
    assert np.linalg.norm(outcome.pose.T_world_camera.translation - truth.translation) < 0.001  # measured 0.21 mm
    # Close up, the same angle leaves a wide enough image: not weighted at all.
    near = corner_view(camera_on_sphere(72.0, 30.0, 0.8), [0, 4], sigma_px=0.05, seed=2)
    outcome = estimate_target_pose(near, CUBE, CAMERA)
    assert outcome.pose.tag_ids == (0, 4) and "weighted" not in outcome.detail
