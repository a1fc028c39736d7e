"""Model-based refinement of a target pose on every known edge of its tags.

The corners-only pose uses 4 points per tag, each the meeting of two fitted lines. The
tag's code gives many more: every boundary between a black and a white cell is a straight
3-D segment known as well as the corners are (``positioning.tag_bits``). Here the pose is
aligned directly to all of them: each edge is projected at the current pose with the lens
distortion applied to the model (``cv2.projectPoints``: nothing is undistorted, curved
edges stay curved), short intensity profiles across it measure where the image's step
really is, and Gauss-Newton moves the pose to cancel those offsets along the edges'
normals. Two re-measured iterations, the first on half the profiles; profiles that
are not a clean single step (an occluder, glare, a neighbouring edge) are dropped, and
then the residual outliers.

The step's position comes from its area, as in ``detection.refine_corners``: pixels
average light over their area, which keeps the area of a step whether blurred or not.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from calib.camera_info import CameraCalibration
from positioning.camera_model import project_pose, project_with_jacobian
from positioning.corner_pose import TargetPose
from positioning.geometry import Transform
from positioning.step_profiles import step_positions
from positioning.tag_bits import grid_to_world, tag_edges
from positioning.target import Target

PROFILE_STEP_PX = 0.5
MIN_PROFILE_SIGMA_PX = 0.01  # floor on the profile noise used for the covariance
# The corners' RMS about the aligned pose on a sharp image (measured 0.02-0.05 px on the
# synthetic camera at noise sigma 2, slow frames of agile); more is blur or a bad image
SHARP_CORNER_RMS_PX = 0.05
END_MARGIN_CELLS = 0.3  # profiles keep this far from a run's ends (perpendicular edges)
PROFILE_HALF_CELLS = 0.4  # profiles reach this far into the cells on each side
MAX_HALF_WIDTH_PX = 4.0
MIN_HALF_WIDTH_PX = 1.25  # cells under ~3 px: the edges blur into each other
MIN_CONTRAST = 25.0  # grey levels between the black and the white side
MAX_VIEW_ANGLE_DEG = 75.0  # tags seen more obliquely give poor edges
ITERATIONS = 2
PIXELS_PER_PROFILE = 2.0
SAMPLES_PER_CELL = (2, 8)
MIN_PROFILES = 40


@dataclass(frozen=True)
class EdgeModel:
    """Sample points of a target's edges: world points, tangents and bright-side normals."""

    points: np.ndarray  # (M, 3)
    tangents: np.ndarray  # (M, 3) unit, along the edge
    normals: np.ndarray  # (M, 3) unit, in the tag plane, towards the white side
    cell_m: np.ndarray  # (M,) cell size of the sample's tag
    tag_index: np.ndarray  # (M,) which of the tags
    run_index: np.ndarray  # (M,) which edge run (global), for per-run intensity levels


_MODELS: dict[tuple, EdgeModel] = {}
_MODEL_CACHE_SIZE = 64


def edge_model(target: Target, tag_ids: tuple[int, ...], samples_per_cell: int) -> EdgeModel:
    """Edge samples of the given tags, ``samples_per_cell`` along each cell length
    (cached: a target's tags do not move, and building the model costs milliseconds)."""
    key = (target.family, samples_per_cell, tuple((i, target.tag(i).corners.tobytes()) for i in tag_ids))
    model = _MODELS.get(key)
    if model is None:
        if len(_MODELS) >= _MODEL_CACHE_SIZE:
            _MODELS.pop(next(iter(_MODELS)))
        model = _MODELS[key] = _build_edge_model(target, tag_ids, samples_per_cell)
    return model


def _build_edge_model(target: Target, tag_ids: tuple[int, ...], samples_per_cell: int) -> EdgeModel:
    points, tangents, normals, cell_m, tag_index, run_index = [], [], [], [], [], []
    run_base = 0
    for index, tag_id in enumerate(tag_ids):
        tag = target.tag(tag_id)
        edges = tag_edges(target.family, tag_id)
        n = edges.cells
        c = tag.corners
        right, down = (c[1] - c[0]) / n, (c[3] - c[0]) / n  # one cell, in metres
        cell = float(np.linalg.norm(right))
        for k in range(len(edges.start)):
            start, end = edges.start[k], edges.end[k]
            length = float(np.abs(end - start).sum())
            along = (end - start) / length
            usable = length - 2 * END_MARGIN_CELLS
            count = max(2, int(round(usable * samples_per_cell)))
            t = END_MARGIN_CELLS + (np.arange(count) + 0.5) * (usable / count)
            grid = start + t[:, None] * along
            points.append(grid_to_world(c, n, grid))
            tangent = along[0] * right + along[1] * down
            normal = edges.bright[k][0] * right + edges.bright[k][1] * down
            tangents.append(np.repeat((tangent / np.linalg.norm(tangent))[None], count, axis=0))
            normals.append(np.repeat((normal / np.linalg.norm(normal))[None], count, axis=0))
            cell_m.append(np.full(count, cell))
            tag_index.append(np.full(count, index))
            run_index.append(np.full(count, run_base + k))
        run_base += len(edges.start)
    return EdgeModel(np.concatenate(points), np.concatenate(tangents), np.concatenate(normals),
                     np.concatenate(cell_m), np.concatenate(tag_index), np.concatenate(run_index))


@dataclass(frozen=True)
class EdgeFit:
    rotation: np.ndarray  # R_camera_world
    translation: np.ndarray  # t_camera_world
    residuals_px: np.ndarray  # (K,) normal offsets of the profiles kept, after the fit
    jacobian: np.ndarray  # (K, 6) d(offset)/d(omega, delta_t), left perturbation in the camera frame
    profiles: int

    @property
    def rvec(self) -> np.ndarray:
        return cv2.Rodrigues(self.rotation)[0].reshape(3)

    @property
    def tvec(self) -> np.ndarray:
        return self.translation

    def covariance(self, min_sigma_px: float = MIN_PROFILE_SIGMA_PX) -> np.ndarray:
        """6x6 covariance of T_world_camera (ROS order: position, world rotation).

        With X_c' = exp(omega) X_c + delta_t, the camera position moves by -R^T delta_t
        and the world-frame rotation by -R^T omega (to first order)."""
        dof = max(self.residuals_px.size - 6, 1)
        sigma2 = max(float(np.sum(self.residuals_px**2)) / dof, min_sigma_px**2)
        cov_local = sigma2 * np.linalg.pinv(self.jacobian.T @ self.jacobian)
        g = np.zeros((6, 6))
        g[:3, 3:] = -self.rotation.T
        g[3:, :3] = -self.rotation.T
        cov = g @ cov_local @ g.T
        return (cov + cov.T) / 2.0


def _measure(image: np.ndarray, model: EdgeModel, rotation: np.ndarray, translation: np.ndarray,
             calibration: CameraCalibration):
    """Offsets (pixels along the projected edge's normal) of the image's steps from the
    model's projected edges, with their Jacobian for the left perturbation of the pose;
    profiles that are not clean single steps are left out. Returns (offsets (K,),
    jacobian (K, 6), model indices (K,)) or None."""
    points = model.points @ rotation.T + translation
    if np.any(points[:, 2] <= 1e-3):
        return None
    pixels, point_j = project_with_jacobian(points, calibration)
    # (einsum: a third of matmul's time on a stack of 2x3 matrices)
    tangent = np.einsum("nij,nj->ni", point_j, model.tangents @ rotation.T)
    across = np.einsum("nij,nj->ni", point_j, model.normals @ rotation.T) * model.cell_m[:, None]
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    normal /= (np.hypot(normal[:, 0], normal[:, 1]) + 1e-300)[:, None]
    normal *= np.where(normal[:, 0] * across[:, 0] + normal[:, 1] * across[:, 1] < 0, -1.0, 1.0)[:, None]
    # Profiles run along the image of the tag-plane normal (not the image normal: under
    # shear that would reach into the neighbouring cells along the edge); a step found at
    # s along it is s * cos(angle) from the projected edge along the image normal.
    cell_px = np.hypot(across[:, 0], across[:, 1])  # one cell across the edge, foreshortened
    direction = across / (cell_px[:, None] + 1e-300)
    cosine = direction[:, 0] * normal[:, 0] + direction[:, 1] * normal[:, 1]
    half = np.minimum(PROFILE_HALF_CELLS * cell_px, MAX_HALF_WIDTH_PX)
    usable = (half >= MIN_HALF_WIDTH_PX) & (cosine > 0.3)
    usable &= (pixels[:, 0] > 4) & (pixels[:, 1] > 4)
    usable &= (pixels[:, 0] < calibration.width - 5) & (pixels[:, 1] < calibration.height - 5)
    if usable.sum() < MIN_PROFILES:
        return None
    index = np.flatnonzero(usable)
    steps = int(np.ceil(half[index].max() / PROFILE_STEP_PX))
    # Profiles from the black cell to the white one, 2 * steps + 1 samples over 2 * half.
    reach, spacing = half[index, None] * direction[index], half[index] / steps
    runs = model.run_index[index]
    position, good, clean = step_positions(image, pixels[index] - reach, reach / steps, 2 * steps + 1,
                                           runs, int(runs.max()) + 1, MIN_CONTRAST)
    offset = (position * spacing - half[index]) * cosine[index]  # the step, along the normal from the model's edge
    good &= clean[runs] >= 2
    rows = np.flatnonzero(good)
    kept = index[rows]
    # d(offset)/d(omega, delta_t): the projected edge point moves by J (omega x X_c + delta_t).
    (x, y, z), n = points[kept].T, normal[kept]
    n_j = n[:, 0:1] * point_j[kept, 0] + n[:, 1:2] * point_j[kept, 1]  # (K, 3): d(offset)/d(X_c)
    a, b, c = n_j.T
    # n_j . (omega x X) = omega . (X x n_j)
    jacobian = np.column_stack([y * c - z * b, z * a - x * c, x * b - y * a, n_j])
    return offset[rows], jacobian, kept


def _rotation_of(omega: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(omega, np.float64).reshape(3, 1))[0]


def align_to_edges(image: np.ndarray, target: Target, calibration: CameraCalibration, tag_ids: tuple[int, ...],
                   rvec: np.ndarray, tvec: np.ndarray, iterations: int | None = None,
                   samples_per_cell: int | None = None) -> EdgeFit | None:
    """The pose (solver convention: T_camera_world as rvec, tvec) aligned to the edges of
    ``tag_ids`` in ``image``; None when too few edges could be measured. Each iteration
    measures every profile afresh at the current pose and takes one Gauss-Newton step."""
    iterations = ITERATIONS if iterations is None else iterations
    rotation = _rotation_of(rvec)
    translation = np.asarray(tvec, np.float64).reshape(3).copy()
    camera_in_world = -rotation.T @ translation
    kept = []
    for tag_id in tag_ids:
        tag = target.tag(tag_id)
        sight = camera_in_world - tag.center
        if float(tag.normal @ sight) >= np.cos(np.radians(MAX_VIEW_ANGLE_DEG)) * float(np.linalg.norm(sight)):
            kept.append(tag_id)
    if not kept:
        return None
    if samples_per_cell is None:
        # A profile every PIXELS_PER_PROFILE pixels along the edges, within limits.
        tag = target.tag(kept[0])
        depth = float((rotation @ tag.center + translation)[2])
        cell_px = calibration.camera_matrix[0, 0] * tag.size_m / tag_edges(target.family, kept[0]).cells / depth
        samples_per_cell = int(np.clip(round(cell_px / PIXELS_PER_PROFILE), *SAMPLES_PER_CELL))
    model = edge_model(target, tuple(kept), samples_per_cell)
    # Coarse to fine: the iterations before the last measure half the profiles (half as
    # many a cell, at least two); they only bring the pose near, and the last measures
    # every profile at the pose it starts from (the fit is its). A measurement costs
    # ~0.45 ms + 0.55 us a profile (648 instead of 1188 at 2 m: 0.3 ms less); over the
    # range map's 480 views the poses moved 0.004 mm (median). One profile a cell was as
    # close there, but behind the wide lens (its tags get two a cell) agile went 3.4 -> 4.2 mm
    # RMS and turn_after_init 30.8 -> 36.5 mm, and behind the narrow lens at 90 deg/s the
    # tracker lost 7 % of the frames (python -m bench intrinsics, tests/test_tracking_*).
    coarse = edge_model(target, tuple(kept), max(SAMPLES_PER_CELL[0], samples_per_cell // 2))
    fit = None
    iterations = max(iterations, 1)
    for iteration in range(iterations):
        measured = _measure(image, model if iteration == iterations - 1 else coarse, rotation, translation,
                            calibration)
        if measured is None or len(measured[0]) < MIN_PROFILES:
            return None
        offset, jacobian, _ = measured
        # Robust: a step further than 4 sigma (median-based) from the rest is not this edge.
        centre = np.median(offset)
        sigma = 1.4826 * np.median(np.abs(offset - centre)) + 1e-3
        inlier = np.abs(offset - centre) <= 4.0 * sigma + 0.05
        a, b = jacobian[inlier], offset[inlier]
        step = np.linalg.solve(a.T @ a, a.T @ b)  # normal equations: 6 unknowns, well posed
        if not np.all(np.isfinite(step)):
            return None
        small = _rotation_of(step[:3])
        rotation, translation = small @ rotation, small @ translation + step[3:]
        fit = (a, b - a @ step)
    a, residuals = fit
    return EdgeFit(rotation, translation, residuals, a, len(residuals))


def refine_pose_on_edges(image: np.ndarray, pose: TargetPose, target: Target,
                         calibration: CameraCalibration, max_shift_m: float = 0.05,
                         iterations: int | None = None,
                         sharp_corner_rms_px: float = SHARP_CORNER_RMS_PX) -> TargetPose:
    """``pose`` aligned to every cell edge of its tags (or unchanged when that fails or
    moves the camera further than ``max_shift_m``, which a right start never needs).

    The aligned pose's ``reproj_rms_px`` is the RMS of the edge profiles' offsets (pixels
    along the edges' normals) it was fitted to; ``residuals_px`` stay the corners'.
    ``sharp_corner_rms_px``: the corners' RMS about the aligned pose on a sharp image of
    this camera (more is taken for blur)."""
    if pose.rvec is None or pose.tvec is None:
        return pose
    try:
        fit = align_to_edges(image, target, calibration, pose.tag_ids, pose.rvec, pose.tvec, iterations)
    except (np.linalg.LinAlgError, ValueError):
        fit = None
    if fit is None:
        return pose
    rvec, tvec = fit.rvec, fit.tvec
    T_world_camera = Transform.from_rvec_tvec(rvec, tvec).inverse()
    if float(np.linalg.norm(T_world_camera.translation - pose.T_world_camera.translation)) > max_shift_m:
        return pose
    corners = pose.points_world
    observed = pose.residuals_px + project_pose(corners, pose.rvec, pose.tvec, calibration)
    residuals = observed - project_pose(corners, rvec, tvec, calibration)
    # The profiles' residuals do not show what motion blur does to the edges (they stay
    # ~0.04 px while the pose is 1-3 mm off: agile); the tag corners do, by disagreeing
    # with the aligned pose. As far as they disagree beyond a sharp image's RMS, the
    # covariance is scaled (agile: 84 -> 98 % of the tracker's poses inside 3 sigma).
    corner_rms = float(np.sqrt(np.mean(residuals**2)))
    covariance = fit.covariance() * max(1.0, corner_rms / sharp_corner_rms_px) ** 2
    return dataclasses.replace(
        pose, T_world_camera=T_world_camera, rvec=rvec, tvec=tvec, covariance=covariance,
        residuals_px=residuals, reproj_rms_px=float(np.sqrt(np.mean(fit.residuals_px**2))),
    )
