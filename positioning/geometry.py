"""Rigid transforms and the quaternion convention used everywhere in cubeloc, and the
small shared maths beside them (``skew``, ``quaternion_angle_deg``, ``robust_sigma``).

``Transform`` T_a_b maps points from frame b into frame a: ``p_a = R @ p_b + t``.
Names say the frames (``T_world_camera``, ``T_camera_target``), as in mrcal and pyslam.
Quaternions are ``[x, y, z, w]`` (ROS / SciPy order), unit norm, ``w >= 0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class Transform:
    """A rigid transform T_a_b: rotation (3, 3) and translation (3,) in metres."""

    rotation: np.ndarray  # (3, 3) float64, orthonormal, det +1
    translation: np.ndarray  # (3,) float64, metres

    def __post_init__(self) -> None:
        r = np.array(self.rotation, dtype=np.float64).reshape(3, 3)
        t = np.array(self.translation, dtype=np.float64).reshape(3)
        r.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)

    @staticmethod
    def identity() -> Transform:
        return Transform(np.eye(3), np.zeros(3))

    @staticmethod
    def from_matrix(matrix: np.ndarray) -> Transform:
        m = np.asarray(matrix, dtype=np.float64)
        return Transform(m[:3, :3], m[:3, 3])

    @staticmethod
    def from_rvec_tvec(rvec: np.ndarray, tvec: np.ndarray) -> Transform:
        """From OpenCV's solvePnP output (which is T_camera_object)."""
        return Transform(rotation_from_rvec(rvec), np.asarray(tvec, dtype=np.float64).reshape(3))

    @staticmethod
    def from_quaternion(position: np.ndarray, quaternion_xyzw: np.ndarray) -> Transform:
        rotation = Rotation.from_quat(np.asarray(quaternion_xyzw, dtype=np.float64)).as_matrix()
        return Transform(rotation, position)

    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m

    def rvec(self) -> np.ndarray:
        """Rodrigues vector (3,), for OpenCV."""
        rvec, _ = cv2.Rodrigues(self.rotation)
        return rvec.reshape(3)

    def quaternion(self) -> np.ndarray:
        """``[x, y, z, w]``, unit norm, ``w >= 0``."""
        return canonical_quaternion(Rotation.from_matrix(self.rotation).as_quat())

    def inverse(self) -> Transform:
        r_inv = self.rotation.T
        return Transform(r_inv, -r_inv @ self.translation)

    def __matmul__(self, other: Transform) -> Transform:
        """Composition: (T_a_b @ T_b_c) = T_a_c."""
        return Transform(self.rotation @ other.rotation, self.rotation @ other.translation + self.translation)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points (N, 3) from frame b into frame a."""
        return np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation

    def rotation_angle_to(self, other: Transform) -> float:
        """Angle in radians of the relative rotation between two transforms."""
        relative = self.rotation.T @ other.rotation
        return float(np.arccos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)))


def rotation_from_rvec(rvec: np.ndarray) -> np.ndarray:
    """The rotation matrix (3, 3) of a Rodrigues vector (OpenCV's)."""
    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix [v]x of a 3-vector (3, 3), or of each of (N, 3) vectors (N, 3, 3):
    ``skew(a) @ b == np.cross(a, b)``.

    >>> skew([1.0, 2.0, 3.0]) @ [4.0, 5.0, 6.0]
    array([-3.,  6., -3.])
    >>> skew(np.zeros((5, 3))).shape
    (5, 3, 3)
    """
    v = np.asarray(v, np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return out


def canonical_quaternion(q: np.ndarray) -> np.ndarray:
    """Normalise and flip the sign so that ``w >= 0`` (the published convention)."""
    q = np.asarray(q, dtype=np.float64).reshape(4)
    q = q / np.linalg.norm(q)
    return -q if q[3] < 0 else q


def look_at(camera_position: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> Transform:
    """T_world_camera for an OpenCV camera (x right, y down, z forward) looking at ``target``."""
    position = np.asarray(camera_position, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - position
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:  # looking straight along 'up': any perpendicular will do
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Transform(np.column_stack([x, y, z]), position)



def quaternion_angle_deg(q1: np.ndarray, q2: np.ndarray) -> float:
    """The angle (degrees) of the rotation between two unit quaternions, either sign.

    >>> round(quaternion_angle_deg([0.0, 0.0, 0.0, 1.0], [0.0, 0.0, np.sin(0.25), np.cos(0.25)]), 4)
    28.6479
    """
    dot = abs(float(np.dot(np.asarray(q1, float), np.asarray(q2, float))))
    return math.degrees(2 * math.acos(min(1.0, dot)))

# a normal distribution's standard deviation over its median absolute deviation
MAD_TO_SIGMA = 1.4826


def robust_sigma(values: np.ndarray, centre: float | None = None, times: float = 1.0) -> float:
    """``times`` the standard deviation of ``values`` that their median absolute deviation
    about ``centre`` gives (their median when None; 0 for magnitudes, such as residual
    norms): the outlier rule everywhere a few bad values must not set the scale.

    >>> robust_sigma(np.array([1.0, 2.0, 3.0, 100.0]))
    1.4826
    >>> robust_sigma(np.array([0.1, 0.2, 0.3]), 0.0, times=3.0)
    0.88956
    """
    if centre is None:
        centre = float(np.median(values))
    return times * MAD_TO_SIGMA * float(np.median(np.abs(np.asarray(values) - centre)))
