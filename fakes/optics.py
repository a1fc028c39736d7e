"""Exact camera optics for rendering: which ray each (sub)pixel sees.

Rendering works backwards: for every output sample position (u, v) we need the undistorted
normalised coordinates (x, y) with ``distort(x, y) = (u, v)``, so that a surface point seen
along the ray (x, y, 1) lands exactly where OpenCV's ``projectPoints`` would put it.
OpenCV's ``undistortPoints`` iterates a fixed-point scheme that stops short of that
precision, so it only gives the starting point for a few Newton steps on our own copy of
the forward model (identical to OpenCV's for plumb_bob and rational_polynomial). A fisheye
(``equidistant``) is inverted here without OpenCV: the ray's angle from the axis by Newton
on its one-dimensional polynomial. Rays are (x, y, 1), so a lens must see less than 89 deg
off its axis everywhere in its image.

Pixel convention: OpenCV's, the centre of the top-left pixel is (0, 0). With ``s``-times
supersampling, sample (i, j) of the fine grid sits at ``u = (j + 0.5) / s - 0.5``, so the
mean of the s x s samples of a pixel is exactly at the pixel centre.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from cubeloc.calib.camera_info import CameraCalibration

# A fisheye's rays must stay this far inside 90 deg off-axis: (x, y, 1) grows without bound.
MAX_RAY_ANGLE_DEG = 89.0


def distort_normalized(x: np.ndarray, y: np.ndarray, distortion: np.ndarray,
                       model: str = "plumb_bob") -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's distortion model on normalised coordinates (plumb_bob or rational), or
    the fisheye's (``equidistant``: the ray's angle theta from the axis goes to a distance
    theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8) from the centre)."""
    if model == "equidistant":
        k1, k2, k3, k4 = np.asarray(distortion, np.float64)[:4]
        r = np.hypot(x, y)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(r > 1e-12, theta_d / r, 1.0)
        return x * scale, y * scale
    d = np.zeros(8)
    d[: len(distortion)] = distortion
    k1, k2, p1, p2, k3, k4, k5, k6 = d
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def project(points_camera: np.ndarray, calibration: CameraCalibration) -> np.ndarray:
    """Pixel positions (N, 2) of camera-frame points (N, 3) with z > 0 (OpenCV model)."""
    p = np.asarray(points_camera, dtype=np.float64)
    xd, yd = distort_normalized(p[:, 0] / p[:, 2], p[:, 1] / p[:, 2], calibration.distortion,
                                calibration.distortion_model)
    k = calibration.camera_matrix
    return np.column_stack([k[0, 0] * xd + k[0, 1] * yd + k[0, 2], k[1, 1] * yd + k[1, 2]])


def _undistort_fisheye(xd: np.ndarray, yd: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    """Normalised (x, y) of distorted normalised coordinates under the fisheye model."""
    k1, k2, k3, k4 = np.asarray(distortion, np.float64)[:4]
    theta_d = np.hypot(xd, yd)
    theta = theta_d.copy()
    for _ in range(30):  # Newton on theta (1 + k1 theta^2 + ...) = theta_d
        t2 = theta * theta
        value = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
        slope = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        theta = theta - value / slope
    if np.any(~np.isfinite(theta)) or np.degrees(theta.max(initial=0.0)) >= MAX_RAY_ANGLE_DEG:
        raise ValueError(f"the lens sees {np.degrees(np.nanmax(theta)):.1f} deg off its axis; rendered rays "
                         f"must stay under {MAX_RAY_ANGLE_DEG:g} deg")
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(theta_d > 1e-12, np.tan(theta) / theta_d, 1.0)
    return np.column_stack([xd * scale, yd * scale])


def undistort_pixels(uv: np.ndarray, calibration: CameraCalibration, newton_steps: int = 4) -> np.ndarray:
    """Undistorted normalised coordinates (N, 2) of pixels (N, 2), exact to ~1e-12."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    k = calibration.camera_matrix
    d = calibration.distortion
    if calibration.distortion_model == "equidistant":
        yd = (uv[:, 1] - k[1, 2]) / k[1, 1]
        return _undistort_fisheye((uv[:, 0] - k[0, 2] - k[0, 1] * yd) / k[0, 0], yd, d)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    # OpenCV 4 has undistortPointsIter; OpenCV 5 folded the criteria into undistortPoints.
    src, identity = uv.reshape(-1, 1, 2), np.eye(3)
    if hasattr(cv2, "undistortPointsIter"):
        start = cv2.undistortPointsIter(src, k, d, identity, identity, criteria)
    else:
        start = cv2.undistortPoints(src, k, d, None, identity, identity, criteria)
    start = start.reshape(-1, 2)
    x, y = start[:, 0].copy(), start[:, 1].copy()
    # target distorted normalised coordinates
    yd_t = (uv[:, 1] - k[1, 2]) / k[1, 1]
    xd_t = (uv[:, 0] - k[0, 2] - k[0, 1] * yd_t) / k[0, 0]
    h = 1e-7
    for _ in range(newton_steps):
        fx, fy = distort_normalized(x, y, d)
        rx, ry = fx - xd_t, fy - yd_t
        # 2x2 Jacobian by central differences (the model is smooth; h is tiny)
        ax, ay = distort_normalized(x + h, y, d)
        bx, by = distort_normalized(x - h, y, d)
        cx_, cy_ = distort_normalized(x, y + h, d)
        ex, ey = distort_normalized(x, y - h, d)
        j11, j21 = (ax - bx) / (2 * h), (ay - by) / (2 * h)
        j12, j22 = (cx_ - ex) / (2 * h), (cy_ - ey) / (2 * h)
        det = j11 * j22 - j12 * j21
        x -= (j22 * rx - j12 * ry) / det
        y -= (-j21 * rx + j11 * ry) / det
    return np.column_stack([x, y])


def _calibration_key(calibration: CameraCalibration) -> tuple:
    return (
        calibration.width,
        calibration.height,
        calibration.camera_matrix.tobytes(),
        calibration.distortion.tobytes(),
        calibration.distortion_model,
    )


@functools.lru_cache(maxsize=8)
def _ray_grid_cached(key: tuple, supersample: int) -> np.ndarray:
    width, height, k_bytes, d_bytes, model = key
    calibration = CameraCalibration(
        width, height, np.frombuffer(k_bytes).reshape(3, 3), np.frombuffer(d_bytes), model
    )
    s = supersample
    u = (np.arange(width * s) + 0.5) / s - 0.5
    v = (np.arange(height * s) + 0.5) / s - 0.5
    uu, vv = np.meshgrid(u, v)
    xy = undistort_pixels(np.column_stack([uu.ravel(), vv.ravel()]), calibration)
    grid = xy.reshape(height * s, width * s, 2).astype(np.float64)
    grid.setflags(write=False)
    return grid


def ray_grid(calibration: CameraCalibration, supersample: int = 1) -> np.ndarray:
    """(H*s, W*s, 2) undistorted normalised coordinates of every sample; the ray of a
    sample is (x, y, 1) in the camera frame. Cached per calibration (read-only)."""
    return _ray_grid_cached(_calibration_key(calibration), supersample)
