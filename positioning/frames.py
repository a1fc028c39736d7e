"""The robot's frames: from the camera's pose in the target's frame to the base's in the map.

The vision gives ``T_world_camera`` (world = the target's frame). A robot integrator wants
``T_map_base`` (REP 105: ``map`` -> ``base_link``):

    T_map_base = T_map_target @ T_world_camera @ inverse(T_base_camera)

with ``T_map_target`` where the target stands in the facility map and ``T_base_camera``
the camera's mount on the robot (both fixed, measured once). A robot whose wheel odometry
publishes ``odom`` -> ``base_link`` gets ``map`` -> ``odom`` instead (REP 105: the
localiser's correction of the odometry's drift), from the same frame's base pose and the
odometry's ``T_odom_base`` at the frame's capture time:

    T_map_odom = T_map_base @ inverse(T_odom_base)

Covariances are 6x6 over (position, rotation) of the child frame expressed in the parent
frame, ROS ``PoseWithCovariance`` order: the perturbation is ``p' = p + dp`` and
``R' = exp([dtheta]x) R`` with ``dp`` and ``dtheta`` in the parent frame (the convention of
``positioning.estimator.PoseEstimate.covariance``). Moving the child by a fixed mount turns
a rotation error into a position error at the lever arm; changing the parent rotates both
blocks. Both are linear maps (the pose's adjoint), so the covariance goes through exactly
to first order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from cubeloc.positioning.geometry import Transform, skew


def reframe_covariance(covariance: np.ndarray, T_parent_child: Transform, T_child_new: Transform,
                       T_newparent_parent: Transform) -> np.ndarray:
    """The covariance of ``T_newparent_parent @ T_parent_child @ T_child_new`` from that of
    ``T_parent_child`` (6x6, position then rotation, both in the parent frame); the two
    outer transforms are exact (no uncertainty of their own)."""
    lever = T_parent_child.rotation @ T_child_new.translation  # child -> new child, in the parent frame
    # p_new = p + R t  =>  dp_new = dp + dtheta x (R t) = dp - [R t]x dtheta; dtheta_new = dtheta
    mount = np.eye(6)
    mount[:3, 3:] = -skew(lever)
    rotate = np.zeros((6, 6))
    rotate[:3, :3] = rotate[3:, 3:] = T_newparent_parent.rotation
    jacobian = rotate @ mount
    out = jacobian @ np.asarray(covariance, np.float64) @ jacobian.T
    return (out + out.T) / 2.0


@dataclass(frozen=True)
class RobotFrames:
    """The fixed placements and the frame names of ``map`` -> ``base_link``."""

    T_base_camera: Transform  # the camera's mount: camera-frame points into the base frame
    T_map_target: Transform  # where the target's frame stands in the map
    map_frame: str = "map"
    base_frame: str = "base_link"
    camera_frame: str = "camera_optical"
    odom_frame: str = "odom"

    @property
    def up_in_target(self) -> np.ndarray:
        """The map's vertical (REP 105: z up) in the target's frame: where the floor's normal is."""
        return self.T_map_target.rotation.T @ np.array([0.0, 0.0, 1.0])

    def base_in_map(self, T_world_camera: Transform, covariance: np.ndarray | None
                    ) -> tuple[Transform, np.ndarray | None]:
        """``T_map_base`` and its covariance (None when the camera pose has none)."""
        return self._in_map(T_world_camera, covariance, self.T_base_camera.inverse())

    def odom_in_map(self, T_world_camera: Transform, covariance: np.ndarray | None, T_odom_base: Transform
                    ) -> tuple[Transform, np.ndarray | None]:
        """``T_map_odom`` (REP 105) from the camera's pose and the odometry's ``T_odom_base``
        at the same time, with the covariance of the camera's pose carried to the odom
        frame's origin (the odometry taken as exact at that instant)."""
        return self._in_map(T_world_camera, covariance, self.T_base_camera.inverse() @ T_odom_base.inverse())

    def _in_map(self, T_world_camera: Transform, covariance: np.ndarray | None, T_camera_child: Transform
                ) -> tuple[Transform, np.ndarray | None]:
        pose = self.T_map_target @ T_world_camera @ T_camera_child
        if covariance is None:
            return pose, None
        return pose, reframe_covariance(covariance, T_world_camera, T_camera_child, self.T_map_target)


class SpreadCorrection:
    """``map`` -> ``odom`` for controllers that dislike steps: each new value is approached
    exponentially, with time constant ``seconds`` (63 % of a step after ``seconds``, 95 %
    after three times that); 0 passes every value through. The translation is blended
    linearly, the rotation along the geodesic. A slow drift of the odometry is followed
    ``seconds`` late: its heading drift times ``seconds`` (0.2 deg/s and 1 s: 0.2 deg)."""

    def __init__(self, seconds: float) -> None:
        self.seconds = float(seconds)
        self._value: Transform | None = None
        self._stamp_ns = 0

    def update(self, stamp_ns: int, raw: Transform) -> Transform:
        """The spread value at ``stamp_ns`` given the newest raw one (a stamp not after the
        last one, the first value, or ``seconds`` 0: the raw value)."""
        if self._value is None or self.seconds <= 0.0 or stamp_ns <= self._stamp_ns:
            self._value = raw
        else:
            share = 1.0 - math.exp(-(stamp_ns - self._stamp_ns) / 1e9 / self.seconds)
            turn = cv2.Rodrigues(self._value.rotation.T @ raw.rotation)[0].ravel() * share
            self._value = Transform(self._value.rotation @ cv2.Rodrigues(turn)[0],
                                    self._value.translation + share * (raw.translation - self._value.translation))
        self._stamp_ns = stamp_ns
        return self._value

