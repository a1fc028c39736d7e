"""Wheel odometry in: the buffer's motion between two frame times and what it refuses
(positioning/tracking/odometry.py), the simulated odometry's errors (fakes/odometry.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cubeloc.fakes.odometry import simulate_odometry
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking.odometry import OdometryBuffer, OdometryModel, OdometryPrior

T0 = 1_700_000_000 * 10**9


def _arc(buffer: OdometryBuffer, seconds: float, rate_hz: float = 50.0, speed: float = 0.5, turn: float = 0.4):
    """Samples of a base driving an arc (speed m/s, turn rad/s) from the origin."""
    for k in range(int(seconds * rate_hz) + 1):
        t = k / rate_hz
        heading = turn * t
        x, y = speed / turn * math.sin(heading), speed / turn * (1 - math.cos(heading))
        buffer.add(T0 + int(t * 1e9), [x, y, 0.0], Rotation.from_euler("z", heading).as_quat())


def _arc_pose(t: float, speed: float = 0.5, turn: float = 0.4) -> Transform:
    heading = turn * t
    return Transform(Rotation.from_euler("z", heading).as_matrix(),
                     [speed / turn * math.sin(heading), speed / turn * (1 - math.cos(heading)), 0.0])


def test_the_motion_between_two_frames_is_interpolated_between_samples_and_extrapolated_a_little():
    buffer = OdometryBuffer(max_extrapolation_s=0.1)
    _arc(buffer, 2.0)
    for t0, t1 in ((0.307, 0.913), (1.0, 1.0), (0.5, 2.05)):  # off the 50 Hz grid; the last past the newest
        motion, covariance = buffer.motion(T0 + int(t0 * 1e9), T0 + int(t1 * 1e9))
        truth = _arc_pose(t0).inverse() @ _arc_pose(t1)
        # between samples the arc is a chord: within (v dt)^2 / (8 r) = 0.2 mm
        np.testing.assert_allclose(motion.translation, truth.translation, atol=3e-4)
        assert motion.rotation_angle_to(truth) < 1e-6
        assert covariance.shape == (6, 6) and np.all(np.diag(covariance)[:3] > 0)  # the floor, even for no motion
    assert buffer.motion(T0 + int(0.5e9), T0 + int(2.2e9)) is None  # 0.2 s past the newest
    assert buffer.motion(T0 - 10**8, T0 + 10**9) is None  # before the first


def test_the_covariance_grows_with_the_distance_the_turn_and_the_time():
    model = OdometryModel(scale_sigma=0.02, turn_sigma=0.02, heading_drift_rad_s=0.0)
    straight = model.covariance(Transform(np.eye(3), [2.0, 0, 0]), 4.0)
    assert math.isclose(math.sqrt(straight[0, 0]), 0.001 + 0.04)  # 2 % of 2 m and the floor
    turned = model.covariance(Transform(Rotation.from_euler("z", 1.0).as_matrix(), [2.0, 0, 0]), 4.0)
    assert math.isclose(math.sqrt(turned[3, 3]), 0.02)  # 2 % of 1 rad
    assert turned[0, 0] > straight[0, 0]  # the heading error pulls the position over 2 m
    drifting = OdometryModel(heading_drift_rad_s=0.01).covariance(Transform.identity(), 10.0)
    assert math.isclose(math.sqrt(drifting[3, 3]), 0.1)


@pytest.mark.parametrize("position, quaternion, reason", [
    ([math.nan, 0, 0], [0, 0, 0, 1], "nan"),
    ([0, 0, 0], [0, 0, 0, math.inf], "nan"),
    ([0, 0, 0], [0, 0, 0.5, 0.5], "not_unit"),
])
def test_a_sample_that_is_not_a_pose_is_dropped_and_counted(position, quaternion, reason):
    buffer = OdometryBuffer()
    assert buffer.add(T0, position, quaternion) == reason
    assert buffer.report()["dropped"] == {reason: 1} and buffer.report()["used"] == 0


def test_late_and_out_of_order_samples_never_enter():
    buffer = OdometryBuffer(stale_s=0.5)
    assert buffer.add(T0 + 10**9, [0, 0, 0], [0, 0, 0, 1], now_ns=T0 + 10**9 + 10**7) is None
    assert buffer.add(T0 + 5 * 10**8, [1, 0, 0], [0, 0, 0, 1]) == "out_of_order"
    assert buffer.add(T0 + 10**9, [1, 0, 0], [0, 0, 0, 1]) == "out_of_order"  # the same stamp again
    assert buffer.add(T0 + 2 * 10**9, [1, 0, 0], [0, 0, 0, 1], now_ns=T0 + 3 * 10**9) == "stale"
    buffer.reject("malformed")
    report = buffer.report()
    assert report["received"] == 5 and report["used"] == 1
    assert report["dropped"] == {"out_of_order": 2, "stale": 1, "malformed": 1}
    assert report["newest_stamp_ns"] == T0 + 10**9


def test_the_camera_moves_as_its_mount_says_when_the_base_turns():
    """A camera 0.2 m ahead of the axis, looking ahead: a base turning on the spot moves it
    on a 0.2 m circle; the prior carries the camera pose there."""
    mount = Transform(Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix(), [0.2, 0.0, 1.0])
    camera0 = mount  # the base at the origin
    buffer = OdometryBuffer()
    buffer.add(T0, [0, 0, 0], [0, 0, 0, 1])
    buffer.add(T0 + 10**9, [0, 0, 0], Rotation.from_euler("z", 90, degrees=True).as_quat())
    prior = OdometryPrior(buffer, mount)
    camera1 = prior.predict(camera0, T0, T0 + 10**9)
    np.testing.assert_allclose(camera1.translation, [0.0, 0.2, 1.0], atol=1e-12)
    np.testing.assert_allclose(camera1.rotation, Rotation.from_euler("z", 90, degrees=True).as_matrix() @ mount.rotation,
                               atol=1e-12)
    # tilted down 20 deg on its mount, the same turn: the same position, the tilt kept
    tilted = Transform(mount.rotation @ Rotation.from_euler("x", -20, degrees=True).as_matrix(), mount.translation)
    moved = prior.predict(tilted, T0, T0 + 10**9)
    np.testing.assert_allclose(moved.translation, [0.0, 0.2, 1.0], atol=1e-12)
    assert abs(np.degrees(tilted.rotation_angle_to(moved)) - 90) < 1e-9
    covariance = prior.covariance(T0, T0 + 10**9)
    assert covariance[0, 0] > covariance[3, 3] * 0.2**2 > 0  # the heading error at the lever arm


def test_the_map_pose_and_the_wheels_motion_are_combined_by_their_covariances():
    """The relative-motion factor: the map's pose (PnP) and the last pose carried on by the
    wheels, each weighed by its covariance; as given where the odometry is only the bridge."""
    mount = Transform(Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix(), [0.2, 0.0, 1.0])
    buffer = OdometryBuffer()
    buffer.add(T0, [0, 0, 0], [0, 0, 0, 1])
    buffer.add(T0 + 10**8, [0.05, 0, 0], [0, 0, 0, 1])  # 5 cm ahead in 0.1 s
    prior = OdometryPrior(buffer, mount, as_prior=True)
    carried = prior.predict(mount, T0, T0 + 10**8)
    odometry = prior.covariance(T0, T0 + 10**8)
    # the map's pose 10 mm aside and 1 deg off in yaw, as sure as the odometry: halfway
    off = Transform(Rotation.from_euler("z", 1.0, degrees=True).as_matrix() @ carried.rotation,
                    carried.translation + [0.0, 0.010, 0.0])
    fused, covariance = prior.fuse(off, odometry.copy(), mount, T0, T0 + 10**8)
    np.testing.assert_allclose(fused.translation, carried.translation + [0.0, 0.005, 0.0], atol=1e-9)
    assert abs(np.degrees(carried.rotation_angle_to(fused)) - 0.5) < 1e-6
    np.testing.assert_allclose(covariance, odometry / 2.0, atol=1e-15)
    # nine times less sure than the odometry: a tenth of the way from the odometry's pose
    fused, _ = prior.fuse(off, 9.0 * odometry, mount, T0, T0 + 10**8)
    np.testing.assert_allclose(fused.translation, carried.translation + [0.0, 0.001, 0.0], atol=1e-9)
    # only the bridge: untouched
    bridge = OdometryPrior(buffer, mount)
    assert bridge.fuse(off, odometry, mount, T0, T0 + 10**8) == (off, odometry)


def test_the_simulated_odometry_is_as_wrong_as_it_says():
    """spin_in_place's base turns on the spot (the camera 0.2 m ahead of the axis): its
    odometry turns 1 % too far plus 0.2 deg/s, and drives nearly nowhere."""
    from cubeloc.fakes.odometry import mount_of
    from cubeloc.fakes.trajectories import make_trajectory, trajectory_at

    xyz, quaternion = mount_of(make_trajectory("spin_in_place", 22.0)[0].T_world_camera)
    rows = simulate_odometry("spin_in_place", 22.0, Transform.from_quaternion(xyz, quaternion), noise_rad=0.0)
    stamps = np.array([r["stamp_ns"] for r in rows])
    assert np.all(np.diff(stamps) == 20_000_000) and (stamps[0] - T0) == 7_000_000  # 50 Hz, its own phase
    assert all(r["arrival_ns"] - r["stamp_ns"] == 30_000_000 for r in rows)
    headings = np.unwrap([Rotation.from_quat(r["orientation"]).as_euler("xyz")[2] for r in rows])
    truth = trajectory_at("spin_in_place", (stamps - T0) / 1e9, 22.0)
    true_headings = np.unwrap([math.atan2(T.rotation[1, 2], T.rotation[0, 2]) for T in truth])
    true_turn = true_headings[-1] - true_headings[0]
    assert true_turn > 4 * math.pi - 0.3  # two turns
    seconds = (stamps[-1] - stamps[0]) / 1e9
    # the turn 1 % long, and 0.2 deg/s on top (white noise off)
    assert abs(headings[-1] - headings[0] - (true_turn * 1.01 + math.radians(0.2) * seconds)) < 1e-6
    assert max(np.hypot(r["position"][0], r["position"][1]) for r in rows) < 0.5  # the axis barely moves


def test_each_drawn_robot_has_its_own_wheels_and_draw_0_the_documented_ones():
    """bench odometry's robots: draw 0 the errors the docs state, each other draw its own
    distance, turn and drift within the family's bounds, the same every time."""
    from cubeloc.fakes.odometry import drawn_errors, mount_of
    from cubeloc.fakes.trajectories import make_trajectory

    assert drawn_errors(0) == {}
    draws = [drawn_errors(k) for k in range(1, 9)]
    assert draws == [drawn_errors(k) for k in range(1, 9)]
    for bound, key in ((0.02, "scale_error"), (0.015, "turn_error"), (0.3, "heading_drift_deg_s")):
        values = [d[key] for d in draws]
        assert all(abs(v) <= bound for v in values) and len(set(values)) == len(values)
    xyz, quaternion = mount_of(make_trajectory("spin_in_place", 22.0)[0].T_world_camera)
    mount = Transform.from_quaternion(xyz, quaternion)
    turned = [simulate_odometry("spin_in_place", 22.0, mount, **errors)[-1]["orientation"]
              for errors in (drawn_errors(0), draws[0])]
    assert not np.allclose(*turned)  # other wheels, another odometry
