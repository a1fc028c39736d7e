"""The camera model of positioning/: OpenCV's pinhole with its distortion, or OpenCV's
fisheye (``equidistant``), in one place.

Everything in positioning/ that projects, projects with a Jacobian, undistorts or hands
pixels to an OpenCV PnP solver comes here, so one convention (OpenCV pixels, distortion
applied to the model as ``cv2.projectPoints`` or ``cv2.fisheye.projectPoints`` does) and
one undistortion (the same iterations everywhere) hold throughout. fakes/ keeps its own,
independent optics on purpose: it is the ground truth.

* ``project(points_camera)``: pixels of camera-frame points;
* ``project_pose(points_world, rvec, tvec)``: pixels of world points at a solver pose
  (T_camera_world as OpenCV's rvec, tvec), optionally with d(pixel)/d(rvec, tvec);
* ``project_with_jacobian(points_camera)``: pixels and d(pixel)/d(point), up to 8
  coefficients (plumb_bob, rational_polynomial);
* ``undistort(pixels)``: normalised coordinates of the rays; ``distort(normalised)``
  back to pixels; ``outline_pixels(normalised)`` for a coarse outline, finite anywhere;
* ``project_normalised(T_camera_world, points_world)``: normalised projections and depths;
* ``normalised_jacobian(points_camera, depth, scale)``: d(scale (x / z, y / z)) / d(x, y, z),
  the pinhole part the tracker's pose fit and bundle adjustment work in (each decides
  how a depth near zero is clamped, and passes it);
* ``solver_pixels(pixels, calibration)``: pixels, camera matrix and distortion to give
  OpenCV's PnP solvers, which know the pinhole models only (a fisheye's pixels go as the
  pixels of a pinhole camera with the same camera matrix);
* ``ahead(pixels)``, ``ahead_mask(calibration)``: which pixels see less than 90 deg off
  the axis, the only rays normalised coordinates (x, y, 1) can describe (a fisheye such
  as TUM-VI's sees 108 deg in its image corners; ``undistort`` returns those rays
  mirrored through the centre).
"""

from __future__ import annotations

import cv2
import numpy as np

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.jit import compiled, read_only

# Iterations of the undistortion: 20 at most, stopping at 1e-10 (normalised units).
# Measured over the whole 1280x1024 image, on the project's lens (k1 -0.08, k2 0.05) and
# on a strong one (k1 -0.3, k2 0.12, k3 -0.02): pixels come back within 1e-10 px.
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-10)
_ZERO = np.zeros(3)
_IDENTITY = np.eye(3)


def project(points_camera: np.ndarray, calibration: CameraCalibration) -> np.ndarray:
    """Pixels (N, 2) of camera-frame points (N, 3)."""
    points = np.asarray(points_camera, np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros((0, 2))
    if calibration.is_fisheye:
        pixels, _ = cv2.fisheye.projectPoints(points.reshape(-1, 1, 3), _ZERO, _ZERO, calibration.camera_matrix,
                                              calibration.distortion, alpha=_fisheye_alpha(calibration))
    else:
        pixels, _ = cv2.projectPoints(points, _ZERO, _ZERO, calibration.camera_matrix, calibration.distortion)
    return pixels.reshape(-1, 2)


def project_pose(points_world: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, calibration: CameraCalibration,
                 jacobian: bool = False):
    """Pixels (N, 2) of world points seen from the solver pose (rvec, tvec) =
    T_camera_world; with ``jacobian``, also d(pixel)/d(rvec, tvec) as (2N, 6)."""
    points = np.asarray(points_world, np.float64).reshape(-1, 3)
    rvec, tvec = np.asarray(rvec, np.float64).reshape(3), np.asarray(tvec, np.float64).reshape(3)
    if calibration.is_fisheye:  # its Jacobian's columns: f (2), c (2), k (4), rvec, tvec, skew
        pixels, j = cv2.fisheye.projectPoints(points.reshape(-1, 1, 3), rvec, tvec, calibration.camera_matrix,
                                              calibration.distortion, alpha=_fisheye_alpha(calibration))
        j = j[:, 8:14]
    else:
        pixels, j = cv2.projectPoints(points, rvec, tvec, calibration.camera_matrix, calibration.distortion)
        j = j[:, :6]
    return (pixels.reshape(-1, 2), j) if jacobian else pixels.reshape(-1, 2)


def undistort(pixels: np.ndarray, calibration: CameraCalibration) -> np.ndarray:
    """Normalised coordinates (N, 2) of the rays through pixels (N, 2)."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if len(pixels) == 0:
        return np.zeros((0, 2))
    src = pixels.reshape(-1, 1, 2)
    if calibration.is_fisheye:  # cv2.fisheye reads no skew from K: it is taken out first
        k = calibration.camera_matrix
        src = (pixels - np.outer((pixels[:, 1] - k[1, 2]) / k[1, 1], [k[0, 1], 0.0])).reshape(-1, 1, 2)
        out = cv2.fisheye.undistortPoints(src, k, calibration.distortion, None, _IDENTITY, _IDENTITY,
                                          UNDISTORT_CRITERIA)
    elif hasattr(cv2, "undistortPointsIter"):  # OpenCV 4: the criteria have their own function
        out = cv2.undistortPointsIter(src, calibration.camera_matrix, calibration.distortion,
                                      _IDENTITY, _IDENTITY, UNDISTORT_CRITERIA)
    else:  # OpenCV 5 folded them into undistortPoints
        out = cv2.undistortPoints(src, calibration.camera_matrix, calibration.distortion, None,
                                  _IDENTITY, _IDENTITY, UNDISTORT_CRITERIA)
    return out.reshape(-1, 2)


def _ahead_radius(calibration: CameraCalibration) -> float | None:
    """A fisheye's distorted normalised radius of the rays 90 deg off the axis (theta_d at
    theta = pi / 2); None for the pinhole models, whose every pixel looks ahead."""
    if not calibration.is_fisheye:
        return None
    k = np.zeros(4)
    coefficients = np.asarray(calibration.distortion, np.float64).ravel()[:4]
    k[: len(coefficients)] = coefficients
    theta = np.pi / 2
    return float(theta * (1 + k[0] * theta**2 + k[1] * theta**4 + k[2] * theta**6 + k[3] * theta**8))


def ahead(pixels: np.ndarray, calibration: CameraCalibration) -> np.ndarray:
    """(N,) True where a pixel's ray is less than 90 deg off the optical axis."""
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    radius = _ahead_radius(calibration)
    if radius is None:
        return np.ones(len(pixels), bool)
    k = calibration.camera_matrix
    y = (pixels[:, 1] - k[1, 2]) / k[1, 1]
    x = (pixels[:, 0] - k[0, 2] - k[0, 1] * y) / k[0, 0]
    return np.hypot(x, y) < radius


def ahead_mask(calibration: CameraCalibration) -> np.ndarray | None:
    """(height, width) uint8, 255 where ``ahead``; None when every pixel is."""
    if _ahead_radius(calibration) is None:
        return None
    u, v = np.meshgrid(np.arange(calibration.width, dtype=np.float64),
                       np.arange(calibration.height, dtype=np.float64))
    inside = ahead(np.column_stack([u.ravel(), v.ravel()]), calibration)
    if inside.all():
        return None
    return (inside.reshape(calibration.height, calibration.width) * 255).astype(np.uint8)


def outline_pixels(normalised: np.ndarray, calibration: CameraCalibration) -> np.ndarray:
    """Pixels (N, 2) of normalised points for a coarse outline (a mask with a margin),
    finite wherever the points are: a fisheye's own projection, monotonic at any angle;
    the undistorted pinhole for the polynomial models, whose distortion folds points far
    outside the view back into it (inside the view a margin covers the difference)."""
    normalised = np.asarray(normalised, np.float64).reshape(-1, 2)
    if calibration.is_fisheye:
        return distort(normalised, calibration)
    k = calibration.camera_matrix
    return normalised @ k[:2, :2].T + k[:2, 2]


def _fisheye_alpha(calibration: CameraCalibration) -> float:
    """cv2.fisheye's skew: an argument of its own (K's skew is not read), as K[0, 1] / fx."""
    return float(calibration.camera_matrix[0, 1] / calibration.camera_matrix[0, 0])


def distort(normalised: np.ndarray, calibration: CameraCalibration) -> np.ndarray:
    """Pixels (N, 2) of normalised ray coordinates (N, 2): the inverse of ``undistort``."""
    normalised = np.asarray(normalised, np.float64).reshape(-1, 2)
    return project(np.column_stack([normalised, np.ones(len(normalised))]), calibration)


def solver_pixels(pixels: np.ndarray, calibration: CameraCalibration
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(pixels, camera matrix, distortion) for OpenCV's PnP solvers (``solvePnP*``): the
    pixels and the calibration as they are for the pinhole models; for a fisheye, where the
    pixels would land in a pinhole camera with the same camera matrix, and no distortion
    (pixel-sized residuals near the centre, larger towards the edge)."""
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    if not calibration.is_fisheye:
        return pixels, calibration.camera_matrix, calibration.distortion
    rays = np.column_stack([undistort(pixels, calibration), np.ones(len(pixels))])
    return np.ascontiguousarray((rays @ calibration.camera_matrix.T)[:, :2]), calibration.camera_matrix, None


def project_normalised(T_camera_world: Transform, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised projections (N, 2) and depths (N,) of world points in a camera."""
    p = T_camera_world.apply(points_world)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = p[:, :2] / z[:, None]
    return xy, z


def normalised_jacobian(points_camera: np.ndarray, depth: np.ndarray, scale: float) -> np.ndarray:
    """(N, 2, 3): d(scale * (x / z, y / z)) / d(x, y, z) of camera-frame points (N, 3), with
    ``depth`` (N,) their z as the caller clamps it away from zero."""
    out = np.zeros((len(points_camera), 2, 3))
    out[:, 0, 0] = out[:, 1, 1] = scale / depth
    out[:, 0, 2] = -scale * points_camera[:, 0] / depth**2
    out[:, 1, 2] = -scale * points_camera[:, 1] / depth**2
    return out


def _project_with_jacobian(points, camera_matrix, d):
    """The compiled loop under ``project_with_jacobian``: OpenCV's plumb_bob /
    rational_polynomial model point by point, its Jacobian in closed form."""
    k1, k2, p1, p2, k3, k4, k5, k6 = d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7]
    fx, skew, cx = camera_matrix[0, 0], camera_matrix[0, 1], camera_matrix[0, 2]
    fy, cy = camera_matrix[1, 1], camera_matrix[1, 2]
    count = points.shape[0]
    pixels = np.empty((count, 2))
    jacobian = np.empty((count, 2, 3))
    for i in range(count):
        inv_z = 1.0 / points[i, 2]
        x, y = points[i, 0] * inv_z, points[i, 1] * inv_z
        r2 = x * x + y * y
        numerator, denominator = 1 + r2 * (k1 + r2 * (k2 + r2 * k3)), 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        radial = numerator / denominator
        # d(radial)/d(r2), and d(r2)/dx = 2x, d(r2)/dy = 2y
        slope = ((k1 + r2 * (2 * k2 + 3 * k3 * r2)) - radial * (k4 + r2 * (2 * k5 + 3 * k6 * r2))) / denominator
        xy = x * y
        xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
        cross = 2 * xy * slope + 2 * p1 * x + 2 * p2 * y  # d(xd)/dy = d(yd)/dx
        d00 = radial + 2 * x * x * slope + 2 * p1 * y + 6 * p2 * x
        d11 = radial + 2 * y * y * slope + 6 * p1 * y + 2 * p2 * x
        # d(distorted)/d(x, y), then the camera matrix (fx, skew, fy) on its rows
        m00, m01 = fx * d00 + skew * cross, fx * cross + skew * d11
        m10, m11 = fy * cross, fy * d11
        # times d(x, y)/d(X, Y, Z) = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
        jacobian[i, 0, 0], jacobian[i, 0, 1] = m00 * inv_z, m01 * inv_z
        jacobian[i, 0, 2] = -(m00 * x + m01 * y) * inv_z
        jacobian[i, 1, 0], jacobian[i, 1, 1] = m10 * inv_z, m11 * inv_z
        jacobian[i, 1, 2] = -(m10 * x + m11 * y) * inv_z
        pixels[i, 0] = fx * xd + skew * yd + cx
        pixels[i, 1] = fy * yd + cy
    return pixels, jacobian


def _project_equidistant_with_jacobian(points, camera_matrix, d):
    """The compiled loop under ``project_with_jacobian`` for the fisheye: cv2.fisheye's
    model (theta = atan2(rho, z), rho the distance from the axis), its Jacobian in closed
    form; on the axis, the pinhole's."""
    k1, k2, k3, k4 = d[0], d[1], d[2], d[3]
    fx, skew, cx = camera_matrix[0, 0], camera_matrix[0, 1], camera_matrix[0, 2]
    fy, cy = camera_matrix[1, 1], camera_matrix[1, 2]
    count = points.shape[0]
    pixels = np.empty((count, 2))
    jacobian = np.empty((count, 2, 3))
    for i in range(count):
        X, Y, Z = points[i, 0], points[i, 1], points[i, 2]
        rho2 = X * X + Y * Y
        rho = np.sqrt(rho2)
        if rho < 1e-12 * abs(Z):
            inv_z = 1.0 / Z
            xd, yd = X * inv_z, Y * inv_z
            a00, a01, a02 = inv_z, 0.0, -xd * inv_z
            a10, a11, a12 = 0.0, inv_z, -yd * inv_z
        else:
            theta = np.arctan2(rho, Z)
            t2 = theta * theta
            theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
            slope = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))  # d(theta_d)/d(theta)
            ux, uy = X / rho, Y / rho
            xd, yd = theta_d * ux, theta_d * uy
            # d(theta)/d(X, Y, Z) and d(X / rho, Y / rho)/d(X, Y)
            denominator = rho2 + Z * Z
            g = slope * Z / (rho * denominator)  # d(theta_d)/dX = g X, /dY = g Y
            gz = -slope * rho / denominator
            h = theta_d / (rho * rho2)
            a00, a01, a02 = g * X * ux + h * Y * Y, g * Y * ux - h * X * Y, gz * ux
            a10, a11, a12 = g * X * uy - h * X * Y, g * Y * uy + h * X * X, gz * uy
        jacobian[i, 0, 0], jacobian[i, 0, 1] = fx * a00 + skew * a10, fx * a01 + skew * a11
        jacobian[i, 0, 2] = fx * a02 + skew * a12
        jacobian[i, 1, 0], jacobian[i, 1, 1], jacobian[i, 1, 2] = fy * a10, fy * a11, fy * a12
        pixels[i, 0] = fx * xd + skew * yd + cx
        pixels[i, 1] = fy * yd + cy
    return pixels, jacobian


def _warm_up() -> None:
    project_with_jacobian(np.ones((1, 3)), CameraCalibration(16, 16, np.eye(3), np.zeros(5)))


def _warm_up_equidistant() -> None:
    project_with_jacobian(np.ones((1, 3)), CameraCalibration(16, 16, np.eye(3), np.zeros(4), "equidistant"))


_compiled_projection = compiled(_project_with_jacobian, _warm_up)  # see positioning/jit.py
_compiled_equidistant = compiled(_project_equidistant_with_jacobian, _warm_up_equidistant)


def project_with_jacobian(points_camera: np.ndarray, calibration: CameraCalibration) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of camera-frame points (N, 3), and d(pixel)/d(point) (N, 2, 3).

    The model of ``project`` with up to 8 coefficients, the distortion's 2x2 Jacobian in
    closed form; compiled (``positioning/jit.py``): 648 points in ~0.02 ms, where the
    same formulas as numpy array operations took ~0.1 ms. The points must be in front of
    the camera (z > 0: compiled, a division by zero raises ZeroDivisionError). A fisheye
    (``equidistant``) has its own loop, where z > 0 is not needed."""
    if calibration.is_fisheye:
        return _compiled_equidistant()(read_only(np.reshape(points_camera, (-1, 3)), np.float64),
                                       read_only(calibration.camera_matrix, np.float64),
                                       read_only(np.asarray(calibration.distortion, np.float64).ravel()))
    d = np.zeros(8)
    coefficients = np.asarray(calibration.distortion, np.float64).ravel()
    if len(coefficients) > 8 and np.any(coefficients[8:] != 0):
        raise ValueError("the Jacobian supports plumb_bob and rational_polynomial distortion only")
    d[: min(len(coefficients), 8)] = coefficients[:8]
    return _compiled_projection()(read_only(np.reshape(points_camera, (-1, 3)), np.float64),
                                  read_only(calibration.camera_matrix, np.float64), read_only(d))
