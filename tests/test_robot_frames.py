"""The robot's frames: map -> base_link from the camera's pose, its covariance through the
mount and the map placement, and the ``[frames]`` section's bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cubeloc.daemon.config import load_config
from cubeloc.daemon.messages import base_pose_payload, map_odom_payload, pose_payload
from cubeloc.errors import ConfigError
from cubeloc.positioning.estimator import PoseEstimate, PoseSource, PoseState
from cubeloc.positioning.frames import RobotFrames, reframe_covariance
from cubeloc.positioning.geometry import Transform, look_at

# A camera 0.4 m ahead of the base and 0.9 m up, looking forward and 20 deg down (optical
# frame: z forward, x right, y down), as a hand-measured [frames.base_from_camera] would say.
MOUNT = Transform(Rotation.from_euler("xyz", [-90 - 20, 0, -90], degrees=True).as_matrix(), [0.4, 0.05, 0.9])
PLACEMENT = Transform(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [12.0, -3.5, 0.0])


def _perturb(T: Transform, delta: np.ndarray) -> Transform:
    """T with (dp, dtheta) applied in its parent frame: p + dp, exp(dtheta) R."""
    return Transform(Rotation.from_rotvec(delta[3:]).as_matrix() @ T.rotation, T.translation + delta[:3])


def _delta(T: Transform, reference: Transform) -> np.ndarray:
    """(dp, dtheta) of T from reference, in the parent frame."""
    rotation = Rotation.from_matrix(T.rotation @ reference.rotation.T).as_rotvec()
    return np.concatenate([T.translation - reference.translation, rotation])


def test_the_base_in_the_map_is_where_the_robot_stands():
    truth = Transform(Rotation.from_euler("z", 75, degrees=True).as_matrix(), [14.2, -1.1, 0.0])  # T_map_base
    # what the camera sees in the target's frame for that base pose
    T_world_camera = PLACEMENT.inverse() @ truth @ MOUNT
    frames = RobotFrames(MOUNT, PLACEMENT)
    pose, covariance = frames.base_in_map(T_world_camera, None)
    assert covariance is None
    np.testing.assert_allclose(pose.translation, truth.translation, atol=1e-12)
    np.testing.assert_allclose(pose.rotation, truth.rotation, atol=1e-12)


def test_the_covariance_goes_through_the_mount_and_the_map_as_sampled_poses_do():
    """Monte Carlo: camera poses drawn from a covariance with a strong rotation part, each
    carried to the base in the map; the spread of those base poses is what
    reframe_covariance says (a lever arm of 1 m turns 10 mrad into 10 mm)."""
    rng = np.random.default_rng(7)
    T_world_camera = look_at(np.array([1.5, -1.2, 0.8]), np.zeros(3))
    a = rng.normal(size=(6, 6))
    covariance = a @ a.T * 1e-6 + np.diag([1e-6, 4e-6, 1e-6, 1e-4, 2e-4, 5e-5])  # rotation sigma ~ 10 mrad
    frames = RobotFrames(MOUNT, PLACEMENT)
    mean, predicted = frames.base_in_map(T_world_camera, covariance)
    draws = rng.multivariate_normal(np.zeros(6), covariance, size=40_000)
    deltas = np.array([_delta(frames.base_in_map(_perturb(T_world_camera, d), None)[0], mean) for d in draws])
    sampled = np.cov(deltas.T)
    sigma = np.sqrt(np.diag(predicted))
    # every entry within 4 % of the sigmas involved (sampling error ~1 %, second-order terms less)
    np.testing.assert_array_less(np.abs(sampled - predicted), 0.04 * np.outer(sigma, sigma))
    # and the lever arm matters: without it the position block would be off by far more
    rotated_only = reframe_covariance(covariance, T_world_camera, Transform.identity(), PLACEMENT)
    assert np.abs(rotated_only[:3, :3] - sampled[:3, :3]).max() > 0.5 * sampled[:3, :3].max()


def _estimate(T: Transform, covariance=None) -> PoseEstimate:
    return PoseEstimate(T, PoseState.TARGET, 3, (0, 1, 4), 0.1, covariance)


def test_the_base_pose_payload_is_the_camera_pose_moved_with_the_same_seq_and_stamp():
    T_world_camera = look_at(np.array([1.5, -1.2, 0.8]), np.zeros(3))
    frames = RobotFrames(MOUNT, PLACEMENT, "facility", "robot7/base_link", "robot7/camera")
    estimate = _estimate(T_world_camera, np.eye(6) * 1e-6)
    camera = pose_payload(42, 1_790_000_000_000_000_000, estimate)
    base = base_pose_payload(42, 1_790_000_000_000_000_000, estimate, frames)
    assert base["schema"] == "cubeloc.pose/4" and camera["schema"] == "cubeloc.pose/3"
    assert (base["seq"], base["stamp_ns"]) == (camera["seq"], camera["stamp_ns"])
    assert (base["frame_id"], base["child_frame_id"], base["camera_frame_id"]) == \
        ("facility", "robot7/base_link", "robot7/camera")
    expected = PLACEMENT @ T_world_camera @ MOUNT.inverse()
    np.testing.assert_allclose(base["position"], expected.translation, atol=1e-12)
    np.testing.assert_allclose(np.abs(np.dot(base["orientation"], expected.quaternion())), 1.0, atol=1e-12)
    assert len(base["covariance"]) == 36 and set(base) == set(camera) | {"camera_frame_id"}


def test_map_to_odom_composed_with_the_odometry_is_the_base_in_the_map_and_carries_the_covariance():
    """REP 105: map -> odom after odom -> base_link at the same stamp is map -> base_link;
    its covariance is the camera pose's carried to the odom frame's origin (sampled: within
    4 % of the sigmas, as the base's); the payload keeps seq, stamp, state and source."""
    rng = np.random.default_rng(11)
    T_world_camera = look_at(np.array([1.5, -1.2, 0.8]), np.zeros(3))
    # the odometry has drifted: it puts the base 3 m and 40 deg away from where the map has it
    T_odom_base = Transform(Rotation.from_euler("z", 40, degrees=True).as_matrix(), [3.0, 1.0, 0.0])
    frames = RobotFrames(MOUNT, PLACEMENT, "map", "base_link", "camera_optical", "odom")
    a = rng.normal(size=(6, 6))
    covariance = a @ a.T * 1e-6 + np.diag([1e-6, 4e-6, 1e-6, 1e-4, 2e-4, 5e-5])
    T_map_odom, predicted = frames.odom_in_map(T_world_camera, covariance, T_odom_base)
    T_map_base = frames.base_in_map(T_world_camera, None)[0]
    composed = T_map_odom @ T_odom_base  # what a tf2 consumer does
    np.testing.assert_allclose(composed.matrix(), T_map_base.matrix(), atol=1e-12)
    draws = rng.multivariate_normal(np.zeros(6), covariance, size=40_000)
    deltas = np.array([_delta(frames.odom_in_map(_perturb(T_world_camera, d), None, T_odom_base)[0], T_map_odom)
                       for d in draws])
    sigma = np.sqrt(np.diag(predicted))
    np.testing.assert_array_less(np.abs(np.cov(deltas.T) - predicted), 0.04 * np.outer(sigma, sigma))
    estimate = PoseEstimate(T_world_camera, PoseState.TRACKING, 0, (), 0.0, covariance, PoseSource.HELD)
    document = map_odom_payload(9, 1_790_000_000_000_000_000, estimate, frames, T_map_odom, predicted,
                                published_ns=1_790_000_000_020_000_000)
    assert document["schema"] == "cubeloc.map_odom/1" and (document["frame_id"], document["child_frame_id"]) == \
        ("map", "odom")
    assert (document["seq"], document["state"], document["source"], document["latency_ns"]) == \
        (9, "tracking", "held", 20_000_000)
    np.testing.assert_allclose(document["position"], T_map_odom.translation, atol=1e-12)
    assert document["spread_position"] == document["position"]  # nothing spread: the same


def test_a_step_of_map_to_odom_is_spread_over_its_time_constant_and_a_steady_value_kept():
    from cubeloc.positioning.frames import SpreadCorrection

    before = Transform(np.eye(3), [1.0, 2.0, 0.0])
    after = Transform(Rotation.from_euler("z", 4, degrees=True).as_matrix(), [1.1, 2.0, 0.0])  # the cube seen again
    spread = SpreadCorrection(0.5)
    stamps = [k * 100_000_000 for k in range(31)]  # 10 Hz for 3 s
    values = [spread.update(s, before if s < 1_000_000_000 else after) for s in stamps]
    steps = [np.linalg.norm(b.translation - a.translation) for a, b in zip(values, values[1:], strict=False)]
    assert max(steps) < 0.1 * 0.2  # no step above a fifth of the 0.1 m jump (exp(-0.2) spreads it)
    done = values[14]  # the jump is first seen at 1.0 s, 0.1 s after the last value: 1.4 s is 0.5 s on, 63 %
    assert abs(done.translation[0] - (1.0 + 0.1 * (1 - np.exp(-1.0)))) < 1e-9
    assert np.linalg.norm(values[-1].translation - after.translation) < 0.1 * np.exp(-3.9)
    assert abs(values[-1].rotation_angle_to(after)) < np.radians(4) * np.exp(-3.9)
    instant = SpreadCorrection(0.0)
    assert instant.update(0, before) is before and instant.update(1, after) is after


def _load(tmp_path, text: str):
    path = tmp_path / "cubeloc.toml"
    path.write_text(text)
    return load_config(path, environ={}), str(path)


def test_a_hand_measured_mount_reads_as_rpy_in_degrees_or_a_quaternion(tmp_path):
    config, _ = _load(tmp_path, "[frames.base_from_camera]\nxyz = [0.4, 0.05, 0.9]\nrpy_deg = [-110, 0, -90]\n")
    np.testing.assert_allclose(config.frames.robot_frames().T_base_camera.matrix(), MOUNT.matrix(), atol=1e-12)
    q = [float(v) for v in MOUNT.quaternion()]
    config, _ = _load(tmp_path, f"[frames.base_from_camera]\nxyz = [0.4, 0.05, 0.9]\nquaternion = {q}\n")
    np.testing.assert_allclose(config.frames.robot_frames().T_base_camera.matrix(), MOUNT.matrix(), atol=1e-12)
    assert config.frames.enabled  # the map placement not given: the identity
    np.testing.assert_array_equal(config.frames.robot_frames().T_map_target.matrix(), np.eye(4))
    defaults, _ = _load(tmp_path, "")
    assert not defaults.frames.enabled
    assert (defaults.frames.map_frame, defaults.frames.base_frame, defaults.frames.camera_frame) == \
        ("map", "base_link", "camera_optical")


@pytest.mark.parametrize("text, key, why", [
    ("[frames.base_from_camera]\nquaternion = [0, 0, 0.5, 0.5]\n", "frames.base_from_camera.quaternion",
     "not a unit quaternion"),
    ("[frames.map_from_target]\nxyz = [nan, 0, 0]\n", "frames.map_from_target.xyz", "finite"),
    ("[frames.map_from_target]\nrpy = [0, 0, 1]\nquaternion = [0, 0, 0, 1]\n", "frames.map_from_target",
     "one rotation"),
    ("[frames.base_from_camera]\nxyz = [400, 50, 900]\n", "frames.base_from_camera", "metres"),
    ("[frames]\nbase_frame = \"base link\"\n", "frames.base_frame", "frame name"),
    ("[frames.base_from_camera]\nrpy_deg = [0, 0]\n", "frames.base_from_camera.rpy_deg", "required"),
])
def test_a_malformed_transform_names_the_file_and_the_key(tmp_path, text, key, why):
    with pytest.raises(ConfigError) as caught:
        _load(tmp_path, text)
    message = str(caught.value)
    assert str(tmp_path / "cubeloc.toml") in message and key in message and why in message, message
    assert "\n" not in message
