"""Trajectory metrics: no alignment, association by time, relative error per metre, scale drift."""

from __future__ import annotations

import numpy as np
import pytest

from cubeloc.positioning.evaluation import (
    absolute_trajectory_error,
    associate,
    relative_pose_error,
    scale_drift,
    scale_walk,
)
from cubeloc.positioning.geometry import Transform, look_at
from cubeloc.positioning.trajectory_io import StampedPose, read_tum, write_tum


def straight_line(n: int = 101, length_m: float = 2.0, dt_ns: int = 100_000_000) -> list[StampedPose]:
    """Camera moving along +x at 1.5 m height, looking at +y."""
    poses = []
    for i in range(n):
        x = length_m * i / (n - 1)
        poses.append(StampedPose(i * dt_ns, look_at(np.array([x, -2.0, 1.5]), np.array([x, 0.0, 1.5]))))
    return poses


def shifted(poses: list[StampedPose], offset: np.ndarray) -> list[StampedPose]:
    return [StampedPose(p.stamp_ns, Transform(p.T_world_camera.rotation, p.T_world_camera.translation + offset))
            for p in poses]


def test_ate_is_zero_for_identical_and_equals_a_constant_offset_without_alignment():
    gt = straight_line()
    assert absolute_trajectory_error(gt, gt).rmse_m == pytest.approx(0.0, abs=1e-12)
    # a constant offset is exactly what an aligned ATE would hide; ours reports it whole
    ate = absolute_trajectory_error(gt, shifted(gt, np.array([0.003, 0.0, 0.004])))
    assert ate.rmse_m == pytest.approx(0.005, abs=1e-9)
    assert ate.max_m == pytest.approx(0.005, abs=1e-9)
    assert ate.count == len(gt)


def test_association_pairs_nearest_stamp_and_drops_the_unmatched():
    gt = straight_line(n=11)
    est = [StampedPose(p.stamp_ns + 400_000, p.T_world_camera) for p in gt[:5]]  # 0.4 ms late
    est.append(StampedPose(gt[5].stamp_ns + 50_000_000, gt[5].T_world_camera))  # 50 ms off: dropped
    pairs = associate(gt, est)
    assert [r.stamp_ns for r, _ in pairs] == [p.stamp_ns for p in gt[:5]]
    with pytest.raises(ValueError):
        absolute_trajectory_error(gt, [StampedPose(10**15, gt[0].T_world_camera)])


def test_ate_over_a_time_window_only():
    gt = straight_line(n=21)
    est = gt[:10] + shifted(gt[10:], np.array([0.0, 0.0, 0.01]))
    assert absolute_trajectory_error(gt, est, end_ns=gt[9].stamp_ns).rmse_m == pytest.approx(0.0, abs=1e-12)
    assert absolute_trajectory_error(gt, est, start_ns=gt[10].stamp_ns).rmse_m == pytest.approx(0.01)


def test_relative_error_per_metre_sees_scale_but_not_a_constant_offset():
    gt = straight_line()
    assert relative_pose_error(gt, shifted(gt, np.array([1.0, 2.0, 3.0]))).translation_rmse_percent == pytest.approx(
        0.0, abs=1e-9
    )
    scaled = [StampedPose(p.stamp_ns, Transform(p.T_world_camera.rotation, p.T_world_camera.translation * 1.02))
              for p in gt]
    # x grows by 2 % (the y and z of the start move too, but equally for all poses)
    rpe = relative_pose_error(gt, scaled, delta_m=0.5)
    assert rpe.translation_rmse_percent == pytest.approx(2.0, rel=0.05)
    with pytest.raises(ValueError):
        relative_pose_error(gt, gt, delta_m=10.0)


def test_scale_drift_recovers_a_linearly_growing_scale_error():
    gt = straight_line(n=201, length_m=4.0)
    # local scale 1 + 0.01 * s (1 %/m): x_est(s) = s + 0.005 s^2
    est = []
    for p in gt:
        x = p.T_world_camera.translation[0]
        t = p.T_world_camera.translation.copy()
        t[0] = x + 0.005 * x * x
        est.append(StampedPose(p.stamp_ns, Transform(p.T_world_camera.rotation, t)))
    drift = scale_drift(gt, est, gt[0].stamp_ns, gt[-1].stamp_ns, window_m=0.2)
    assert drift.distance_m == pytest.approx(4.0)
    assert drift.drift_percent_per_m == pytest.approx(1.0, rel=0.05)
    assert drift.scale_error_percent == pytest.approx(2.0, rel=0.05)  # 0.08 m over 4 m
    assert drift.end_error_m == pytest.approx(0.08, rel=1e-6)
    none = scale_drift(gt, gt, gt[0].stamp_ns, gt[-1].stamp_ns)
    assert abs(none.drift_percent_per_m) < 1e-9 and none.end_error_m == 0.0


def test_tum_round_trip_keeps_the_error(tmp_path):
    gt = straight_line(n=31)
    est = shifted(gt, np.array([0.0, 0.002, 0.0]))
    write_tum(tmp_path / "gt.tum", gt)
    write_tum(tmp_path / "est.tum", est)
    ate = absolute_trajectory_error(read_tum(tmp_path / "gt.tum"), read_tum(tmp_path / "est.tum"))
    assert ate.rmse_m == pytest.approx(0.002, abs=1e-8)


def _drive_turn_drive(n: int = 200, step_m: float = 0.01, turn_deg: float = 90.0) -> list[StampedPose]:
    """n steps along x, a turn on the spot of ``turn_deg`` over n frames, n steps on."""
    poses, yaw, x = [], 0.0, np.zeros(3)
    for i in range(3 * n):
        if i < n or i >= 2 * n:
            x = x + step_m * np.array([np.cos(yaw), np.sin(yaw), 0.0])
        else:
            yaw += np.radians(turn_deg) / n
        c, s = np.cos(yaw), np.sin(yaw)  # optical axis along the heading, image y down
        poses.append(StampedPose(i, Transform(np.array([[s, 0, c], [-c, 0, s], [0, -1, 0.0]]), x)))
    return poses


def test_scale_walk_tells_a_step_in_a_turn_from_a_drift_and_measures_the_under_turn():
    truth = _drive_turn_drive()
    # the estimate turns 2 % less than the camera (from the turn on), and its scale falls 6 %
    # in the turn; before the turn the scale grows 1 % per metre
    est = []
    for i, p in enumerate(truth):
        t = p.T_world_camera.translation.copy()
        if i < 200:
            t[0] = t[0] + 0.005 * t[0] ** 2
        else:
            t = est[199].T_world_camera.translation + 0.94 * (t - truth[199].T_world_camera.translation)
        turned = np.radians(90.0) * min(max(i - 200, 0), 200) / 200
        # about the camera's y, which points down: against the turn
        fix = Transform.from_rvec_tvec(np.array([0.0, 0.02 * turned, 0.0]), np.zeros(3))
        est.append(StampedPose(p.stamp_ns, Transform(p.T_world_camera.rotation @ fix.rotation, t)))
    walk = scale_walk(truth, est, stretch_m=0.5)
    assert walk.turned_deg.round().tolist() == [90.0]
    # the step: log(0.94 / 1.015), the scale before it being 1.015 over the stretch 1.5-2 m
    assert walk.turn_step_percent == pytest.approx(100 * abs(np.log(0.94 / (1 + 0.01 * 1.75))), abs=0.3)
    assert walk.largest_step_percent == walk.turn_step_percent
    assert walk.under_turn_percent.tolist() == pytest.approx([2.0], abs=0.05)
    assert walk.under_turn_median_percent == pytest.approx(2.0, abs=0.05)
    # driving: 3 pairs 0.5 % apart before the turn (1 %/m), 2 pairs with no change after it
    assert len(walk.drive_steps) == 5
    assert walk.drive_walk_percent == pytest.approx(100 * np.sqrt(3 * 0.005**2 / 5 / 0.5), rel=0.05)
    # with the frames of the turn marked as the target in view, no pair spans it
    away = np.ones(len(truth), bool)
    away[250:350] = False
    assert len(scale_walk(truth, est, away, stretch_m=0.5).turn_steps) == 0
    none = scale_walk(truth, truth, stretch_m=0.5)
    assert none.turn_step_percent == pytest.approx(0.0, abs=1e-9) and none.drive_walk_percent < 1e-9
