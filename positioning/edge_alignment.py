"""Model-based refinement of a target pose on every known edge of its tags.

The corners-only pose uses 4 points per tag, each the meeting of two fitted lines. The
tag's code gives many more: every boundary between a black and a white cell is a straight
3-D segment known as well as the corners are (``positioning.tag_bits``). Here the pose is
aligned directly to all of them: each edge is projected at the current pose with the lens
distortion applied to the model (``camera_model.project_with_jacobian``, OpenCV's
model: nothing is undistorted, curved edges stay curved), short intensity profiles across
it measure where the image's step really is, and Gauss-Newton moves the pose to cancel
those offsets along the edges' normals. Two re-measured iterations, the first on half the
profiles; profiles that are not a clean single step (an occluder, glare, a neighbouring
edge) are dropped, and then the residual outliers.

The step's position comes from its area, as in ``detection.refine_corners``: pixels
average light over their area, which keeps the area of a step whether blurred or not.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.camera_model import project_pose, project_with_jacobian
from cubeloc.positioning.corner_pose import MIN_CORNER_SIGMA_PX, TargetPose
from cubeloc.positioning.geometry import Transform, robust_sigma, rotation_from_rvec
from cubeloc.positioning.jit import compiled, read_only
from cubeloc.positioning.step_profiles import step_positions
from cubeloc.positioning.tag_bits import grid_to_world, tag_edges
from cubeloc.positioning.target import Target


@dataclass(frozen=True)
class EdgeOptions:
    """How a target's cell edges are measured (``measure_edges``), a pose aligned to them
    (``align_to_edges``) and the aligned pose's covariance claimed (``EdgeFit.covariances``,
    ``refine_pose_on_edges``). ``PoseOptions.edges`` carries them."""

    # profiles: sampled every profile_step_px, from profile_half_cells into the cell on one
    # side to as far into the other, within [min_half_width_px, max_half_width_px] each way
    # (cells under ~3 px: the edges blur into each other); none nearer a run's ends than
    # end_margin_cells (the perpendicular edges)
    profile_step_px: float = 0.5
    profile_half_cells: float = 0.4
    max_half_width_px: float = 4.0
    min_half_width_px: float = 1.25
    end_margin_cells: float = 0.3
    min_contrast: float = 25.0  # grey levels between the black and the white side
    min_profile_cosine: float = 0.3  # profiles further than 73 deg off the edge's image normal are left out
    max_view_angle_deg: float = 75.0  # tags seen more obliquely give poor edges
    # a profile every pixels_per_profile pixels along the edges, samples_per_cell (low, high)
    # along a cell's length at most and at least
    pixels_per_profile: float = 2.0
    samples_per_cell: tuple[int, int] = (2, 8)
    min_profiles: int = 40  # fewer measured: no alignment
    iterations: int = 2  # Gauss-Newton steps, each measuring every profile afresh
    min_profile_sigma_px: float = 0.01  # floor on the profile noise used for the covariance
    # Every edge of an image may be found off its place towards one side, by an amount the
    # profiles' noise does not show and the fit cannot tell from the pose: a blurred step
    # through a non-linear response (a camera's gamma of 0.8-1.25 moves it by 0.06-0.14 of
    # the blur's sigma, depending on the levels), ink spread. Its standard deviation is
    # edge_bias_per_blur of the steps' measured spread (``EdgeFit.blur_px``, which includes
    # the pixels' own ~0.5 px): 0.04 px on a sharp image, 0.07-0.1 px at 0.8-1.5 px of
    # defocus. Each tag's edges move apart from the others' by tag_bias_share of that
    # besides (a face's own light and ink). Checked on the range map's views through a gamma
    # of 0.8 or 1.25 (``python -m bench target_nees``, docs/benchmarks.md).
    edge_bias_per_blur: float = 0.08
    tag_bias_share: float = 0.5
    # The corners' RMS about the aligned pose on a sharp image (0.02-0.05 px on the
    # synthetic camera at noise sigma 2, slow frames of agile); more is blur or a bad image.
    # A camera's own: the 10th percentile of its last sharp_history_frames steady frames,
    # once there are sharp_min_frames, never below this (``TargetObserver``).
    sharp_corner_rms_px: float = 0.05
    sharp_history_frames: int = 100
    sharp_min_frames: int = 10


EDGES = EdgeOptions()  # the defaults


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


def edge_model(target: Target, tag_ids: tuple[int, ...], samples_per_cell: int,
               end_margin_cells: float = EDGES.end_margin_cells) -> EdgeModel:
    """Edge samples of the given tags, ``samples_per_cell`` along each cell length, none
    nearer a run's ends than ``end_margin_cells`` (cached: a target's tags do not move, and
    building the model costs milliseconds)."""
    key = (target.family, target.border_bits, samples_per_cell, end_margin_cells,
           tuple((i, target.tag(i).corners.tobytes()) for i in tag_ids))
    model = _MODELS.get(key)
    if model is None:
        if len(_MODELS) >= _MODEL_CACHE_SIZE:
            _MODELS.pop(next(iter(_MODELS)))
        model = _MODELS[key] = _build_edge_model(target, tag_ids, samples_per_cell, end_margin_cells)
    return model


def _build_edge_model(target: Target, tag_ids: tuple[int, ...], samples_per_cell: int,
                      end_margin_cells: float) -> EdgeModel:
    points, tangents, normals, cell_m, tag_index, run_index = [], [], [], [], [], []
    run_base = 0
    for index, tag_id in enumerate(tag_ids):
        tag = target.tag(tag_id)
        edges = tag_edges(target.family, tag_id, target.border_bits)
        n = edges.cells
        c = tag.corners
        right, down = (c[1] - c[0]) / n, (c[3] - c[0]) / n  # one cell, in metres
        cell = float(np.linalg.norm(right))
        for k in range(len(edges.start)):
            start, end = edges.start[k], edges.end[k]
            length = float(np.abs(end - start).sum())
            along = (end - start) / length
            usable = length - 2 * end_margin_cells
            count = max(2, int(round(usable * samples_per_cell)))
            t = end_margin_cells + (np.arange(count) + 0.5) * (usable / count)
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
    # (6, 6) what the corners fitted beside the edges tell of (omega, delta_t): J^T J / sigma^2
    corner_information: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((6, 6)))
    blur_px: float = 0.0  # the steps' spread (a Gaussian blur's sigma, pixels along the normal), median
    tags: np.ndarray | None = None  # (K,) each profile's tag (index into the fit's tags)

    @property
    def rvec(self) -> np.ndarray:
        return cv2.Rodrigues(self.rotation)[0].reshape(3)

    @property
    def tvec(self) -> np.ndarray:
        return self.translation

    def covariances(self, options: EdgeOptions = EDGES) -> tuple[np.ndarray, np.ndarray]:
        """6x6 covariances of T_world_camera (ROS order: position, world rotation): the
        noise's (the profiles and the corners fitted with them), and the systematic share,
        what the edges' shift towards their white side (``edge_bias_per_blur``) moves the
        pose by: all of them alike, and each tag's apart (its own levels and ink) by
        ``tag_bias_share`` of that.

        With X_c' = exp(omega) X_c + delta_t, the camera position moves by -R^T delta_t
        and the world-frame rotation by -R^T omega (to first order)."""
        dof = max(self.residuals_px.size - 6, 1)
        sigma2 = max(float(np.sum(self.residuals_px**2)) / dof, options.min_profile_sigma_px**2)
        if self.corner_information.any():
            noise = np.linalg.pinv(self.jacobian.T @ self.jacobian / sigma2 + self.corner_information)
        else:
            noise = sigma2 * np.linalg.pinv(self.jacobian.T @ self.jacobian)
        # J^T of a unit shift of every profile, and of each tag's (by tag_bias_share)
        shifts = [self.jacobian.sum(axis=0)[None]]
        if self.tags is not None:
            each = (self.tags[:, None] == np.unique(self.tags)[None]).astype(np.float64)  # (K, tags)
            shifts.append(options.tag_bias_share * (self.jacobian.T @ each).T)
        moved = noise @ np.vstack(shifts).T / sigma2  # (6, groups): the pose's move for each shift
        systematic = (options.edge_bias_per_blur * self.blur_px) ** 2 * moved @ moved.T
        g = np.zeros((6, 6))
        g[:3, 3:] = -self.rotation.T
        g[3:, :3] = -self.rotation.T
        return tuple((c + c.T) / 2.0 for c in (g @ noise @ g.T, g @ systematic @ g.T))


@dataclass(frozen=True)
class Corners:
    """Tag corners fitted beside the edges: world points (N, 3), their pixels (N, 2), and
    the pixel noise their pose's residuals show (``corner_pose.MIN_CORNER_SIGMA_PX`` at
    least)."""

    points_world: np.ndarray
    pixels: np.ndarray
    sigma_px: float

    def normal_equations(self, rotation: np.ndarray, translation: np.ndarray,
                         calibration: CameraCalibration) -> tuple[np.ndarray, np.ndarray]:
        """(J^T J, J^T r) / sigma^2 at the pose, for the left perturbation (omega, delta_t)."""
        points = self.points_world @ rotation.T + translation
        pixels, point_j = project_with_jacobian(points, calibration)
        cross = np.zeros((len(points), 3, 3))  # -[X]x: d(exp(omega) X)/d(omega)
        cross[:, 0, 1], cross[:, 0, 2] = points[:, 2], -points[:, 1]
        cross[:, 1, 0], cross[:, 1, 2] = -points[:, 2], points[:, 0]
        cross[:, 2, 0], cross[:, 2, 1] = points[:, 1], -points[:, 0]
        jacobian = np.concatenate([point_j @ cross, point_j], axis=2).reshape(-1, 6)
        residuals = (self.pixels - pixels).reshape(-1)
        weight = 1.0 / self.sigma_px**2
        return jacobian.T @ jacobian * weight, jacobian.T @ residuals * weight


def _layout(pixels, point_j, tangents, normals, cell_m, width, height, half_cells, max_half, min_half,
            step_px, min_cosine):
    """The compiled loop under ``measure_edges``: each edge sample's profile from the black cell
    to the white one. Returns (usable samples' indices, starts, deltas, steps: a profile
    has 2 * steps + 1 samples, scale and shift: a step found at s samples lies
    s * scale - shift pixels from the projected edge along its image normal, normals)."""
    count = pixels.shape[0]
    direction = np.empty((count, 2))
    normal = np.empty((count, 2))
    half = np.empty(count)
    cosine = np.empty(count)
    usable = np.zeros(count, np.bool_)
    widest = 0.0
    for i in range(count):
        # the images of the edge's tangent and of one cell across it (the tag-plane normal)
        tx = point_j[i, 0, 0] * tangents[i, 0] + point_j[i, 0, 1] * tangents[i, 1] + point_j[i, 0, 2] * tangents[i, 2]
        ty = point_j[i, 1, 0] * tangents[i, 0] + point_j[i, 1, 1] * tangents[i, 1] + point_j[i, 1, 2] * tangents[i, 2]
        ax = (point_j[i, 0, 0] * normals[i, 0] + point_j[i, 0, 1] * normals[i, 1]
              + point_j[i, 0, 2] * normals[i, 2]) * cell_m[i]
        ay = (point_j[i, 1, 0] * normals[i, 0] + point_j[i, 1, 1] * normals[i, 1]
              + point_j[i, 1, 2] * normals[i, 2]) * cell_m[i]
        nx, ny = -ty, tx
        length = np.hypot(nx, ny) + 1e-300
        nx, ny = nx / length, ny / length
        if nx * ax + ny * ay < 0:  # towards the white side
            nx, ny = -nx, -ny
        # Profiles run along the image of the tag-plane normal (not the image normal:
        # under shear that would reach into the neighbouring cells along the edge); a step
        # found at s along it is s * cos(angle) from the projected edge along the normal.
        cell_px = np.hypot(ax, ay)  # one cell across the edge, foreshortened
        dx, dy = ax / (cell_px + 1e-300), ay / (cell_px + 1e-300)
        direction[i, 0], direction[i, 1] = dx, dy
        normal[i, 0], normal[i, 1] = nx, ny
        cosine[i] = dx * nx + dy * ny
        half[i] = min(half_cells * cell_px, max_half)
        usable[i] = (half[i] >= min_half and cosine[i] > min_cosine and pixels[i, 0] > 4 and pixels[i, 1] > 4
                     and pixels[i, 0] < width - 5 and pixels[i, 1] < height - 5)
        if usable[i]:
            widest = max(widest, half[i])
    index = np.flatnonzero(usable)
    kept = index.shape[0]
    steps = max(int(np.ceil(widest / step_px)), 1)
    starts = np.empty((kept, 2))
    deltas = np.empty((kept, 2))
    scale = np.empty(kept)
    shift = np.empty(kept)
    kept_normals = np.empty((kept, 2))
    for r in range(kept):
        i = index[r]
        reach_x, reach_y = half[i] * direction[i, 0], half[i] * direction[i, 1]
        starts[r, 0], starts[r, 1] = pixels[i, 0] - reach_x, pixels[i, 1] - reach_y
        deltas[r, 0], deltas[r, 1] = reach_x / steps, reach_y / steps
        scale[r] = half[i] / steps * cosine[i]
        shift[r] = half[i] * cosine[i]
        kept_normals[r, 0], kept_normals[r, 1] = normal[i, 0], normal[i, 1]
    return index, starts, deltas, steps, scale, shift, kept_normals


def _offsets(position, good, clean, runs, scale, shift, normals, point_j, points, index):
    """The compiled loop under ``measure_edges`` after the step profiles: the clean profiles'
    offsets from the model's edges, and their rows of d(offset)/d(omega, delta_t) (the
    projected point moves by J (omega x X_c + delta_t)). Returns (offsets, jacobian, model
    indices)."""
    rows = 0
    for r in range(position.shape[0]):
        good[r] = good[r] and clean[runs[r]] >= 2
        rows += good[r]
    offset = np.empty(rows)
    jacobian = np.empty((rows, 6))
    kept = np.empty(rows, np.int64)
    k = 0
    for r in range(position.shape[0]):
        if not good[r]:
            continue
        i = index[r]
        offset[k] = position[r] * scale[r] - shift[r]
        # d(offset)/d(X_c) = n^T J; and n_j . (omega x X) = omega . (X x n_j)
        a = normals[r, 0] * point_j[i, 0, 0] + normals[r, 1] * point_j[i, 1, 0]
        b = normals[r, 0] * point_j[i, 0, 1] + normals[r, 1] * point_j[i, 1, 1]
        c = normals[r, 0] * point_j[i, 0, 2] + normals[r, 1] * point_j[i, 1, 2]
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        jacobian[k, 0], jacobian[k, 1], jacobian[k, 2] = y * c - z * b, z * a - x * c, x * b - y * a
        jacobian[k, 3], jacobian[k, 4], jacobian[k, 5] = a, b, c
        kept[k] = i
        k += 1
    return offset, jacobian, kept


def _warm_up() -> None:  # through measure_edges, on a tag's worth of synthetic edges
    from cubeloc.calib.camera_info import CameraCalibration

    rng = np.random.default_rng(0)
    count = EDGES.min_profiles
    model = EdgeModel(np.column_stack([rng.uniform(-0.05, 0.05, (count, 2)), np.ones(count)]),
                      np.tile([1.0, 0.0, 0.0], (count, 1)), np.tile([0.0, 1.0, 0.0], (count, 1)),
                      np.full(count, 0.01), np.zeros(count, np.int64), np.zeros(count, np.int64))
    camera = CameraCalibration(200, 200, np.array([[1000.0, 0, 100], [0, 1000.0, 100], [0, 0, 1]]), np.zeros(5))
    measure_edges(np.zeros((200, 200), np.uint8), model, np.eye(3), np.zeros(3), camera)


_compiled_layout = compiled(_layout, _warm_up)  # see positioning/jit.py
_compiled_offsets = compiled(_offsets, lambda: None)  # warmed up with the layout's, by measure_edges


def measure_edges(image: np.ndarray, model: EdgeModel, rotation: np.ndarray, translation: np.ndarray,
                  calibration: CameraCalibration, spread: bool = False, options: EdgeOptions = EDGES):
    """Offsets (pixels along the projected edge's normal) of the image's steps from the
    model's projected edges, with their Jacobian for the left perturbation of the pose;
    profiles that are not clean single steps are left out. Returns (offsets (K,),
    jacobian (K, 6), model indices (K,), the steps' spreads (K,): their blur's variance in
    pixels^2 along the normal, with ``spread``, else zeros) or None. The loops around the step profiles are
    compiled too (``_layout``, ``_offsets``): 1188 profiles in 0.60-0.65 ms, where the
    thirty-odd numpy array operations they replace took 1.46-1.53 ms, timed side by side."""
    points = model.points @ rotation.T + translation
    if np.any(points[:, 2] <= 1e-3):
        return None
    pixels, point_j = project_with_jacobian(points, calibration)
    index, starts, deltas, steps, scale, shift, normals = _compiled_layout()(
        pixels, point_j, read_only(model.tangents @ rotation.T), read_only(model.normals @ rotation.T),
        read_only(model.cell_m, np.float64), calibration.width, calibration.height, options.profile_half_cells,
        options.max_half_width_px, options.min_half_width_px, options.profile_step_px, options.min_profile_cosine)
    if len(index) < options.min_profiles:
        return None
    # Profiles from the black cell to the white one, 2 * steps + 1 samples each.
    runs = model.run_index[index]
    found = step_positions(image, starts, deltas, 2 * steps + 1, runs, int(runs.max()) + 1, options.min_contrast,
                           spread=spread)
    position, good, clean = found[:3]
    spreads = found[3] if spread else np.zeros(len(position))
    offset, jacobian, kept = _compiled_offsets()(position, good, clean, runs, scale, shift, normals, point_j,
                                                 read_only(points), index)
    return offset, jacobian, kept, spreads[good] * scale[good] ** 2  # (the kernel leaves only the rows kept good)


def align_to_edges(image: np.ndarray, target: Target, calibration: CameraCalibration, tag_ids: tuple[int, ...],
                   rvec: np.ndarray, tvec: np.ndarray, iterations: int | None = None,
                   samples_per_cell: int | None = None, corners: Corners | None = None,
                   options: EdgeOptions = EDGES) -> EdgeFit | None:
    """The pose (solver convention: T_camera_world as rvec, tvec) aligned to the edges of
    ``tag_ids`` in ``image``; None when too few edges could be measured. Each iteration
    measures every profile afresh at the current pose and takes one Gauss-Newton step.

    Where every edge measured runs one way (the cells across them foreshortened below
    ``min_half_width_px`` in an oblique view) the pose slides along them unseen: the normal
    equations are singular. There, and only there, ``corners`` are fitted with the edges,
    each set weighed by its own noise (the edges' step alone moved the pose by noise along
    that direction: 30 mm on 752x480 boards). Wherever the edges measure the whole pose
    they are fitted alone: the corners, biased by blur, would pull the directions the
    edges measure weakly their way (a two-face cube at 640x512: 1.3 -> 1.7 mm median)."""
    iterations = options.iterations if iterations is None else iterations
    rotation = rotation_from_rvec(rvec)
    translation = np.asarray(tvec, np.float64).reshape(3).copy()
    camera_in_world = -rotation.T @ translation
    kept = []
    for tag_id in tag_ids:
        tag = target.tag(tag_id)
        sight = camera_in_world - tag.center
        if float(tag.normal @ sight) >= np.cos(np.radians(options.max_view_angle_deg)) * float(np.linalg.norm(sight)):
            kept.append(tag_id)
    if not kept:
        return None
    if samples_per_cell is None:
        # A profile every pixels_per_profile pixels along the edges, within limits.
        tag = target.tag(kept[0])
        depth = float((rotation @ tag.center + translation)[2])
        cell_px = (calibration.camera_matrix[0, 0] * tag.size_m
                   / tag_edges(target.family, kept[0], target.border_bits).cells / depth)
        samples_per_cell = int(np.clip(round(cell_px / options.pixels_per_profile), *options.samples_per_cell))
    model = edge_model(target, tuple(kept), samples_per_cell, options.end_margin_cells)
    # Coarse to fine: the iterations before the last measure half the profiles (half as
    # many a cell, at least two); they only bring the pose near, and the last measures
    # every profile at the pose it starts from (the fit is its). A measurement costs
    # ~0.08 ms + 0.46 us a profile (the numpy one it replaced, timed beside it: 0.39 ms +
    # 0.93 us; 648 instead of 1188 at 2 m: 0.25 ms less); over the
    # range map's 480 views the poses moved 0.004 mm (median). One profile a cell was as
    # close there, but behind the wide lens (its tags get two a cell) agile went 3.4 -> 4.2 mm
    # RMS and turn_after_init 30.8 -> 36.5 mm, and behind the narrow lens at 90 deg/s the
    # tracker lost 7 % of the frames (python -m bench intrinsics, tests/test_tracking_*).
    coarse = edge_model(target, tuple(kept), max(options.samples_per_cell[0], samples_per_cell // 2),
                        options.end_margin_cells)
    fit = None
    iterations = max(iterations, 1)
    for iteration in range(iterations):
        last = iteration == iterations - 1
        measured = measure_edges(image, model if last else coarse, rotation, translation, calibration, spread=last,
                                 options=options)
        if measured is None or len(measured[0]) < options.min_profiles:
            return None
        offset, jacobian, rows, spread = measured
        # Robust: a step further than 4 sigma (median-based) from the rest is not this edge.
        centre = np.median(offset)
        sigma = robust_sigma(offset, centre) + 1e-3
        inlier = np.abs(offset - centre) <= 4.0 * sigma + 0.05
        a, b = jacobian[inlier], offset[inlier]
        normal = a.T @ a
        with_corners = corners is not None and np.linalg.matrix_rank(normal) < 6
        if with_corners:
            profile_weight = 1.0 / max(sigma, options.min_profile_sigma_px) ** 2
            corner_normal, corner_gradient = corners.normal_equations(rotation, translation, calibration)
            step = np.linalg.solve(normal * profile_weight + corner_normal, a.T @ b * profile_weight + corner_gradient)
        else:
            step = np.linalg.solve(normal, a.T @ b)  # normal equations: 6 unknowns
        if not np.all(np.isfinite(step)):
            return None
        small = rotation_from_rvec(step[:3])
        rotation, translation = small @ rotation, small @ translation + step[3:]
        fit = (a, b - a @ step, spread[inlier], rows[inlier])
    a, residuals, spread, rows = fit  # the last iteration's: of ``model``
    tags = model.tag_index[rows]
    corner_information = corners.normal_equations(rotation, translation, calibration)[0] if with_corners \
        else np.zeros((6, 6))
    blur = float(np.sqrt(max(np.median(spread), 0.0)))
    return EdgeFit(rotation, translation, residuals, a, len(residuals), corner_information, blur, tags)


def refine_pose_on_edges(image: np.ndarray, pose: TargetPose, target: Target,
                         calibration: CameraCalibration, max_shift_m: float = 0.05,
                         iterations: int | None = None, sharp_corner_rms_px: float | None = None,
                         options: EdgeOptions = EDGES) -> TargetPose:
    """``pose`` aligned to every cell edge of its tags (or unchanged when that fails or
    moves the camera further than ``max_shift_m``, which a right start never needs).

    The aligned pose's ``reproj_rms_px`` is the RMS of the edge profiles' offsets (pixels
    along the edges' normals) it was fitted to; ``residuals_px`` stay the corners'.
    ``sharp_corner_rms_px``: the corners' RMS about the aligned pose on a sharp image of
    this camera (more is taken for blur; None: ``options.sharp_corner_rms_px``)."""
    if pose.rvec is None or pose.tvec is None:
        return pose
    corners = pose.points_world
    observed = pose.residuals_px + project_pose(corners, pose.rvec, pose.tvec, calibration)
    dof = max(pose.residuals_px.size - 6, 1)
    corner_sigma = max(float(np.sqrt(np.sum(pose.residuals_px**2) / dof)), MIN_CORNER_SIGMA_PX)
    try:
        fit = align_to_edges(image, target, calibration, pose.tag_ids, pose.rvec, pose.tvec, iterations,
                             corners=Corners(corners, observed, corner_sigma), options=options)
    except (np.linalg.LinAlgError, ValueError):
        fit = None
    if fit is None:
        return pose
    rvec, tvec = fit.rvec, fit.tvec
    T_world_camera = Transform.from_rvec_tvec(rvec, tvec).inverse()
    if float(np.linalg.norm(T_world_camera.translation - pose.T_world_camera.translation)) > max_shift_m:
        return pose
    residuals = observed - project_pose(corners, rvec, tvec, calibration)
    # The profiles' residuals do not show what motion blur does to the edges (they stay
    # ~0.04 px while the pose is 1-3 mm off: agile); the tag corners do, by disagreeing
    # with the aligned pose. As far as they disagree beyond a sharp image's RMS, the
    # noise's covariance is scaled (agile: 84 -> 98 % of the tracker's poses inside 3
    # sigma); the systematic share grows with the blur by itself (edge_bias_per_blur).
    corner_rms = float(np.sqrt(np.mean(residuals**2)))
    noise, systematic = fit.covariances(options)
    sharp = options.sharp_corner_rms_px if sharp_corner_rms_px is None else sharp_corner_rms_px
    noise = noise * max(1.0, corner_rms / sharp) ** 2
    return dataclasses.replace(
        pose, T_world_camera=T_world_camera, rvec=rvec, tvec=tvec, covariance=noise + systematic,
        systematic_covariance=systematic,
        residuals_px=residuals, reproj_rms_px=float(np.sqrt(np.mean(fit.residuals_px**2))),
    )
