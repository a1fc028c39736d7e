"""A camera pose from matched corners, and its covariance: the pieces every pose solver of
positioning/ shares (``target_pose``'s corners, ``edge_alignment``'s edges, ``tag_scale``).

``TargetPose`` is the result record; ``refine_lm`` OpenCV's Levenberg-Marquardt on the
pixel residuals (finished by Gauss-Newton on a fisheye's own pixels);
``covariance_from_jacobian`` carries a measurement Jacobian with respect to the solver's
(rvec, tvec) to the 6x6 covariance of T_world_camera in ROS order.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.camera_model import project_pose, solver_pixels
from cubeloc.positioning.geometry import Transform

# Floor on the corner noise used for the covariance, so a perfect fit still has one.
MIN_CORNER_SIGMA_PX = 0.02


@dataclass(frozen=True)
class TargetPose:
    """A camera pose in the target (world) frame from one image."""

    T_world_camera: Transform
    planes: int
    tag_ids: tuple[int, ...]
    reproj_rms_px: float
    covariance: np.ndarray | None  # (6, 6) x y z, rotation about world X Y Z (ROS order)
    residuals_px: np.ndarray  # (4N, 2) observed minus predicted corners
    rvec: np.ndarray | None = None  # the solver's T_camera_world, for the covariance
    tvec: np.ndarray | None = None
    points_world: np.ndarray | None = None  # (4N, 3) corners used
    # (6, 6) the share of ``covariance`` that the frames of a still scene have in common (every
    # edge found off its place alike: ``EdgeOptions.edge_bias_per_blur``): it is in the
    # error against the truth, not in the scatter from frame to frame; None: no such share
    systematic_covariance: np.ndarray | None = None



def refine_lm(points_world: np.ndarray, pixels: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
              calibration: CameraCalibration) -> tuple[np.ndarray, np.ndarray]:
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    # Column vectors: given (3,) arrays, OpenCV's binding refines a converted copy and
    # returns the start unchanged (and spends 20x longer doing it).
    solver_px, camera_matrix, distortion = solver_pixels(pixels, calibration)
    rvec, tvec = cv2.solvePnPRefineLM(
        points_world, solver_px, camera_matrix, distortion,
        np.asarray(rvec, np.float64).reshape(3, 1).copy(), np.asarray(tvec, np.float64).reshape(3, 1).copy(),
        criteria,
    )
    rvec, tvec = rvec.reshape(3), tvec.reshape(3)
    if calibration.is_fisheye:  # OpenCV's LM knows no fisheye: finish on the fisheye's own pixels
        rvec, tvec = _gauss_newton(points_world, np.asarray(pixels, np.float64).reshape(-1, 2), rvec, tvec,
                                   calibration)
    return rvec, tvec


def _gauss_newton(points_world: np.ndarray, pixels: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
                  calibration: CameraCalibration, iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on the pixel residuals through ``project_pose`` (any camera model),
    from a start already near the minimum; a step that does not lower the error ends it."""
    x = np.concatenate([rvec, tvec])

    def residuals(params: np.ndarray, jacobian: bool = False):
        return project_pose(points_world, params[:3], params[3:], calibration, jacobian=jacobian)

    predicted, jac = residuals(x, jacobian=True)
    error = float(np.sum((pixels - predicted) ** 2))
    for _ in range(iterations):
        step = np.linalg.lstsq(jac, (pixels - predicted).ravel(), rcond=None)[0]
        candidate = x + step
        predicted_new, jac_new = residuals(candidate, jacobian=True)
        new_error = float(np.sum((pixels - predicted_new) ** 2))
        if not np.isfinite(new_error) or new_error >= error:
            break
        x, predicted, jac, error = candidate, predicted_new, jac_new, new_error
        if np.abs(step).max() < 1e-12:
            break
    return x[:3].copy(), x[3:].copy()


def _world_camera_vector(rvec: np.ndarray, tvec: np.ndarray, reference_rotation: np.ndarray) -> np.ndarray:
    """(camera position in world, world-frame rotation vector from ``reference_rotation``).

    The rotation vector is the first-order one, vee((D - D^T) / 2) of the small rotation
    D = R_world_camera @ reference^T: exact enough for a numerical derivative, and cheap."""
    rotation, _ = cv2.Rodrigues(rvec)  # R_camera_world
    position = -rotation.T @ tvec
    d = rotation.T @ reference_rotation.T
    delta = 0.5 * np.array([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]])
    return np.concatenate([position, delta])


def corners_covariance(points_world: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, residuals: np.ndarray,
                calibration: CameraCalibration) -> np.ndarray:
    """6x6 covariance of T_world_camera (ROS order) from the Jacobian at the solution.

    Corner noise is estimated from the residuals (with a floor); the covariance of the
    solver's (rvec, tvec) is then carried to (position, world rotation) numerically.
    """
    _, jacobian = project_pose(points_world, rvec, tvec, calibration, jacobian=True)
    return covariance_from_jacobian(jacobian, residuals, rvec, tvec)


def pose_covariance(pose: TargetPose, calibration: CameraCalibration) -> np.ndarray:
    """The 6x6 covariance of a corners' pose (as ``estimate_target_pose`` attaches it)."""
    return corners_covariance(pose.points_world, pose.rvec, pose.tvec, pose.residuals_px, calibration)


def covariance_from_jacobian(jacobian: np.ndarray, residuals: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
                             min_sigma_px: float = MIN_CORNER_SIGMA_PX) -> np.ndarray:
    """6x6 covariance of T_world_camera (ROS order) from any measurement Jacobian
    (M, 6) with respect to the solver's (rvec, tvec), and the M residuals (pixels)."""
    dof = max(residuals.size - 6, 1)
    sigma2 = max(float(np.sum(residuals**2)) / dof, min_sigma_px**2)
    cov_solver = sigma2 * np.linalg.pinv(jacobian.T @ jacobian)
    reference = cv2.Rodrigues(rvec)[0].T  # R_world_camera at the solution
    x0 = np.concatenate([rvec, tvec])
    step = 1e-7
    g = np.empty((6, 6))
    for k in range(6):
        dx = np.zeros(6)
        dx[k] = step
        plus = _world_camera_vector((x0 + dx)[:3], (x0 + dx)[3:], reference)
        minus = _world_camera_vector((x0 - dx)[:3], (x0 - dx)[3:], reference)
        g[:, k] = (plus - minus) / (2 * step)
    cov = g @ cov_solver @ g.T
    return (cov + cov.T) / 2.0


def make_pose(points_world: np.ndarray, pixels: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
               calibration: CameraCalibration, planes: int, tag_ids: tuple[int, ...]) -> TargetPose:
    residuals = pixels - project_pose(points_world, rvec, tvec, calibration)
    rms = float(np.sqrt(np.mean(np.sum(residuals**2, axis=1))))
    return TargetPose(
        T_world_camera=Transform.from_rvec_tvec(rvec, tvec).inverse(),
        planes=planes,
        tag_ids=tag_ids,
        reproj_rms_px=rms,
        covariance=None,  # filled in for the pose that is returned (with_covariance)
        residuals_px=residuals,
        rvec=rvec,
        tvec=tvec,
        points_world=points_world,
    )
