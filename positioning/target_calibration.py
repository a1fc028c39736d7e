"""Calibrating a hand-built target: every tag's true placement from images of it.

A real cube is never exact: a tag glued 2 mm off centre or 1 degree askew costs more than
everything the pose estimator gains (at 2 m, 1 mm of tag placement is ~1 mm of camera
position). From 20-50 images of the target from around it, a bundle adjustment solves
for every camera pose and every tag's 6-DoF placement (a rotation about its nominal
centre and a translation), the first tag of the target file held fixed as the frame. The
tags stay squares of their nominal size (scale is what the printed size fixes), so the
refined file is the nominal one moved tag by tag: an explicit-tag target file.

Observations are the tags' outer corners from the AprilTag detector with the edge
refinement of ``detection.refine_corners``. A view needs two tags to say anything about
their relative placement; tags never seen together with the frame's tag (directly or
through others) cannot be placed and keep their nominal corners (the report says so).

Pure computation: images and a nominal Target in, a ``TargetCalibration`` out.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.errors import InputFileError
from cubeloc.positioning.camera_model import project_pose
from cubeloc.positioning.detection import TagDetection, TagDetector, refine_corners
from cubeloc.positioning.geometry import robust_sigma
from cubeloc.positioning.target import Tag, Target, validate_target
from cubeloc.positioning.target_pose import (
    PoseOptions,
    estimate_target_pose,
    unique_target_detections,
)

MIN_VIEWS = 5  # usable images (two tags or more) below which nothing is solved
MIN_TAG_VIEWS = 2  # a tag needs this many usable views to be placed
# The nominal placement may be off by millimetres: the first poses must not be refused.
INITIAL_POSE_OPTIONS = PoseOptions(max_reproj_rms_px=50.0, max_tag_angle_deg=80.0, min_oblique_edge_px=15.0)
OUTLIER_FACTOR = 5.0  # a tag view whose RMS exceeds this times the median is left out
MIN_OUTLIER_PX = 0.5
EDGE_ITERATIONS = 4


@dataclass(frozen=True)
class ViewObservation:
    """The refined corners of the target's tags in one image."""

    name: str
    detections: tuple[TagDetection, ...]
    image: np.ndarray | None = None  # kept for the edge refinement


@dataclass(frozen=True)
class TagResult:
    tag_id: int
    views: int  # usable images in which it was observed
    placed: bool  # False: not connected to the frame's tag, nominal corners kept
    fixed: bool  # the frame's tag
    shift_mm: np.ndarray  # (3,) centre moved from nominal, mm (world frame)
    rotation_deg: float  # angle from the nominal orientation
    sigma_shift_mm: np.ndarray  # (3,) 1-sigma of the centre, mm
    sigma_rotation_deg: np.ndarray  # (3,) 1-sigma of the rotation (about world x, y, z), deg
    rms_px: float  # RMS corner residual over its observations


@dataclass(frozen=True)
class TargetCalibration:
    refined: Target
    tags: tuple[TagResult, ...]
    views_used: int
    views_skipped: tuple[tuple[str, str], ...]  # (image, why)
    rms_px: float  # corner residual RMS after the adjustment
    nominal_rms_px: float  # the same observations against the nominal target (poses refitted)
    per_view_rms_px: tuple[tuple[str, float], ...] = field(default=())
    edge_profiles: int = 0  # edge profiles of the final edge iteration (0: corners only)
    edge_rms_px: float = float("nan")

    def report(self) -> str:
        lines = [
            f"views used: {self.views_used}, skipped: {len(self.views_skipped)}",
            f"corner residual RMS: {self.rms_px:.3f} px (nominal target: {self.nominal_rms_px:.3f} px)",
            *([f"edge refinement: {self.edge_profiles} edge profiles, RMS {self.edge_rms_px:.3f} px"]
              if self.edge_profiles else []),
            "tag  views  shift from nominal (x, y, z) mm   |shift| mm  rotation deg   1-sigma: shift mm, rotation deg   RMS px",
        ]
        for t in self.tags:
            if t.fixed:
                lines.append(f"{t.tag_id:>3}  {t.views:>5}  (the frame: fixed)" + " " * 48 + f"{t.rms_px:.3f}")
            elif not t.placed:
                lines.append(f"{t.tag_id:>3}  {t.views:>5}  not placed (never seen with the others): nominal kept")
            else:
                shift = " ".join(f"{v:+7.3f}" for v in t.shift_mm)
                lines.append(
                    f"{t.tag_id:>3}  {t.views:>5}  {shift}        {np.linalg.norm(t.shift_mm):6.3f}     "
                    f"{t.rotation_deg:6.3f}        {t.sigma_shift_mm.max():.3f}, {t.sigma_rotation_deg.max():.4f}"
                    f"                  {t.rms_px:.3f}"
                )
        for name, why in self.views_skipped:
            lines.append(f"skipped {name}: {why}")
        return "\n".join(lines)


def observe(images: Iterable[tuple[str, np.ndarray]], target: Target, calibration: CameraCalibration,
            detector: TagDetector | None = None) -> tuple[list[ViewObservation], list[tuple[str, str]]]:
    """Refined tag corners of each image; images with fewer than two of the target's
    tags are skipped (with the reason)."""
    detector = detector or TagDetector(target.family, border_bits=target.border_bits)
    cells = detector.cells
    views, skipped = [], []
    for name, image in images:
        found = unique_target_detections(detector.detect(image), target)
        refined = []
        for detection in found:
            better = refine_corners(image, detection, calibration, cells, saddles=target.grid is not None)
            if better is not None:
                refined.append(better)
        if len(refined) < 2:
            skipped.append((name, f"{len(refined)} tag(s) of the target found, 2 needed"))
            continue
        views.append(ViewObservation(name, tuple(refined), image))
    return views, skipped


def _rotation(omega: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(omega, np.float64).reshape(3, 1))[0]


def _connected_tags(views: list[ViewObservation], first: int) -> set[int]:
    """Tags linked to ``first`` through views that see two or more tags."""
    linked = {first}
    changed = True
    while changed:
        changed = False
        for view in views:
            ids = {d.tag_id for d in view.detections}
            if ids & linked and not ids <= linked:
                linked |= ids
                changed = True
    return linked


def calibrate_target(views: list[ViewObservation], nominal: Target, calibration: CameraCalibration,
                     skipped: list[tuple[str, str]] | None = None,
                     progress: Callable[[str], None] | None = None, edge_iterations: int = EDGE_ITERATIONS,
                     ) -> TargetCalibration:
    """Bundle adjustment of the tags' placements (first tag fixed) and the camera poses:
    on the refined corners, then (when the views keep their images) on every cell edge."""
    skipped = list(skipped or [])
    first = nominal.tags[0].tag_id
    counts: dict[int, int] = {}
    for view in views:
        for d in view.detections:
            counts[d.tag_id] = counts.get(d.tag_id, 0) + 1
    if counts.get(first, 0) == 0:
        raise InputFileError(
            f"tag {first}, the first tag of the target file, which fixes the frame, is not in any usable image "
            "(images need two tags or more)"
        )
    linked = _connected_tags(views, first)
    free = [t.tag_id for t in nominal.tags[1:] if t.tag_id in linked and counts.get(t.tag_id, 0) >= MIN_TAG_VIEWS]
    solved = {first, *free}
    # Initial camera poses from the nominal target.
    poses, used = [], []
    for view in views:
        detections = [d for d in view.detections if d.tag_id in solved]
        if len(detections) < 2:
            skipped.append((view.name, "its tags cannot be placed relative to the first tag"))
            continue
        outcome = estimate_target_pose(detections, nominal, calibration, INITIAL_POSE_OPTIONS, with_covariance=False)
        if outcome.pose is None:
            skipped.append((view.name, f"no initial pose ({outcome.detail})"))
            continue
        poses.append(np.concatenate([outcome.pose.rvec, outcome.pose.tvec]))
        used.append(ViewObservation(view.name, tuple(detections), view.image))
    if len(used) < MIN_VIEWS:
        raise InputFileError(
            f"only {len(used)} usable image(s) showing two tags or more with a pose; "
            f"{MIN_VIEWS} or more are needed (20-50 from all around the target are best)"
        )
    if progress:
        progress(f"{len(used)} views, {len(free)} tags to place")

    problem = _Problem(used, nominal, calibration, first, free)
    x0 = np.concatenate([np.zeros(6 * len(free)), np.concatenate(poses)])
    # Nominal fit (tags fixed): what the nominal file explains, for the report.
    nominal_fit = problem.solve(x0, tags_free=False)
    nominal_rms = problem.rms(nominal_fit)
    solution = problem.solve(nominal_fit)
    # Leave out tag views that do not fit (a bad quad), then solve again.
    per_obs = problem.observation_rms(solution)
    limit = max(OUTLIER_FACTOR * float(np.median(per_obs)), MIN_OUTLIER_PX)
    if np.any(per_obs > limit):
        problem.keep = per_obs <= limit
        solution = problem.solve(solution)
    result = problem.result(solution, nominal_rms, skipped, counts)
    if edge_iterations > 0 and all(v.image is not None for v in used):
        result = _refine_on_edges(used, problem, solution, result, calibration, edge_iterations, progress)
    return result


def _refine_on_edges(views: list[ViewObservation], problem: _Problem, x: np.ndarray, corners_result: TargetCalibration,
                     calibration: CameraCalibration, iterations: int,
                     progress: Callable[[str], None] | None) -> TargetCalibration:
    """Gauss-Newton on every cell edge of every tag in every view (edge_alignment's
    measurement), jointly over the free tags' placements and the view poses, from the
    corners' solution. The corners fix where the tags are to ~0.05 mm; the edges, many
    more and measured without fitting lines, take that further."""
    from cubeloc.positioning.edge_alignment import EDGES, edge_model, measure_edges
    from cubeloc.positioning.geometry import rotation_from_rvec

    nominal, first, free = problem.nominal, problem.first, problem.free
    solved = (first, *free)
    tag_rotation = {t: np.eye(3) for t in solved}
    tag_centre = {t: problem.centres[t].copy() for t in solved}
    for t in free:
        p = x[6 * problem.tag_slot[t]: 6 * problem.tag_slot[t] + 6]
        tag_rotation[t] = rotation_from_rvec(p[:3])
        tag_centre[t] = problem.centres[t] + p[3:]
    view_rotation, view_translation = [], []
    for v in range(len(views)):
        pose = x[problem.offset + 6 * v: problem.offset + 6 * v + 6]
        view_rotation.append(rotation_from_rvec(pose[:3]))
        view_translation.append(pose[3:].copy())
    models = {}
    for v, view in enumerate(views):
        ids = tuple(d.tag_id for d in view.detections if d.tag_id in solved)
        models[v] = (ids, edge_model(nominal, ids, 4))
    n_free, n_views = len(free), len(views)
    size = 6 * (n_free + n_views)
    sigma2, hessian, meat, profiles = 0.0, np.eye(size), np.zeros((size, size)), 0
    for iteration in range(iterations):
        hessian = np.zeros((size, size))
        gradient = np.zeros(size)
        meat = np.zeros((size, size))
        squares, profiles = 0.0, 0
        for v, view in enumerate(views):
            ids, model = models[v]
            which = np.array(ids)[model.tag_index]
            rotation = np.stack([tag_rotation[t] for t in ids])[model.tag_index]  # (M, 3, 3)
            centre_nominal = np.stack([problem.centres[t] for t in ids])[model.tag_index]
            centre = np.stack([tag_centre[t] for t in ids])[model.tag_index]
            points = np.einsum("mij,mj->mi", rotation, model.points - centre_nominal) + centre
            moved = type(model)(points, np.einsum("mij,mj->mi", rotation, model.tangents),
                                np.einsum("mij,mj->mi", rotation, model.normals), model.cell_m, model.tag_index,
                                model.run_index)
            measured = measure_edges(view.image, moved, view_rotation[v], view_translation[v], calibration)
            if measured is None or len(measured[0]) < EDGES.min_profiles:
                continue
            offset, camera_j, kept, _ = measured
            middle = np.median(offset)
            spread = robust_sigma(offset, middle) + 1e-3
            inlier = np.abs(offset - middle) <= 4.0 * spread + 0.05
            offset, camera_j, kept = offset[inlier], camera_j[inlier], kept[inlier]
            # d(offset)/d(tag perturbation about its current centre): m = R_view^T n_j
            m = camera_j[:, 3:] @ view_rotation[v]
            lever = points[kept] - centre[kept]
            tag_j = np.concatenate([np.cross(lever, m), m], axis=1)
            # The normal equations block by block (each profile touches one view, one tag).
            view_cols = slice(6 * (n_free + v), 6 * (n_free + v) + 6)
            hessian[view_cols, view_cols] += camera_j.T @ camera_j
            gradient[view_cols] += camera_j.T @ offset
            for t in free:
                rows = which[kept] == t
                if rows.any():
                    slot = problem.tag_slot[t]
                    tag_cols = slice(6 * slot, 6 * slot + 6)
                    hessian[tag_cols, tag_cols] += tag_j[rows].T @ tag_j[rows]
                    cross = tag_j[rows].T @ camera_j[rows]
                    hessian[tag_cols, view_cols] += cross
                    hessian[view_cols, tag_cols] += cross.T
                    gradient[tag_cols] += tag_j[rows].T @ offset[rows]
            # Per edge run, the gradient of its profiles: errors within one run (sampling,
            # print) are shared, so the uncertainty counts runs, not profiles (sandwich).
            runs = model.run_index[kept]
            unique_runs, run_of = np.unique(runs, return_inverse=True)
            run_gradient = np.zeros((len(unique_runs), size))
            np.add.at(run_gradient[:, view_cols], run_of, camera_j * offset[:, None])
            for t in free:
                rows = which[kept] == t
                if rows.any():
                    slot = problem.tag_slot[t]
                    block = np.zeros((len(unique_runs), 6))
                    np.add.at(block, run_of[rows], tag_j[rows] * offset[rows, None])
                    run_gradient[:, 6 * slot: 6 * slot + 6] += block
            meat += run_gradient.T @ run_gradient
            squares += float(offset @ offset)
            profiles += len(offset)
        damped = hessian + 1e-9 * np.eye(size)
        try:
            step = np.linalg.solve(damped, gradient)
        except np.linalg.LinAlgError:
            step = np.linalg.lstsq(damped, gradient, rcond=None)[0]
        for t in free:
            slot = problem.tag_slot[t]
            small = rotation_from_rvec(step[6 * slot: 6 * slot + 3])
            tag_rotation[t] = small @ tag_rotation[t]
            tag_centre[t] = tag_centre[t] + step[6 * slot + 3: 6 * slot + 6]
        for v in range(n_views):
            small = rotation_from_rvec(step[6 * (n_free + v): 6 * (n_free + v) + 3])
            view_rotation[v] = small @ view_rotation[v]
            view_translation[v] = small @ view_translation[v] + step[6 * (n_free + v) + 3: 6 * (n_free + v) + 6]
        sigma2 = squares / max(profiles - size, 1)
        if progress:
            progress(f"edge iteration {iteration + 1}: {profiles} profiles, RMS {np.sqrt(squares / max(profiles, 1)):.3f} px")
    try:
        inverse = np.linalg.inv(hessian)
    except np.linalg.LinAlgError:
        inverse = np.linalg.pinv(hessian)
    # The larger of the two: white noise over all profiles, or the run-clustered sandwich.
    covariance = np.maximum(sigma2 * inverse, inverse @ meat @ inverse)
    tags, refined_tags = [], []
    for tag, before in zip(nominal.tags, corners_result.tags, strict=True):
        if tag.tag_id not in free:
            refined_tags.append(corners_result.refined.tag(tag.tag_id))
            tags.append(before)
            continue
        corners = problem.local[tag.tag_id] @ tag_rotation[tag.tag_id].T + tag_centre[tag.tag_id]
        refined_tags.append(Tag(tag.tag_id, corners, tag.face))
        slot = problem.tag_slot[tag.tag_id]
        sd = np.sqrt(np.clip(np.diag(covariance)[6 * slot: 6 * slot + 6], 0.0, None))
        angle = float(np.degrees(np.linalg.norm(cv2.Rodrigues(tag_rotation[tag.tag_id])[0])))
        tags.append(TagResult(tag.tag_id, before.views, True, False, (tag_centre[tag.tag_id] - problem.centres[tag.tag_id]) * 1000,
                              angle, sd[3:] * 1000, np.degrees(sd[:3]), before.rms_px))
    refined = Target(nominal.family, tuple(refined_tags), None, "", nominal.border_bits)
    validate_target(refined, "refined target")
    return dataclasses.replace(corners_result, refined=refined, tags=tuple(tags), edge_profiles=profiles,
                               edge_rms_px=float(np.sqrt(sigma2)))


class _Problem:
    """Parameters: 6 per free tag (rotation vector about its nominal centre, centre
    shift), then 6 per view (rvec, tvec of T_camera_world)."""

    def __init__(self, views: list[ViewObservation], nominal: Target, calibration: CameraCalibration, first: int,
                 free: list[int]) -> None:
        self.views, self.nominal, self.calibration = views, nominal, calibration
        self.first, self.free = first, free
        self.tag_slot = {tag_id: k for k, tag_id in enumerate(free)}
        self.offset = 6 * len(free)
        # One observation = one tag in one view (4 corners, 8 residuals).
        self.obs_view, self.obs_tag, pixels = [], [], []
        for v, view in enumerate(views):
            for d in view.detections:
                self.obs_view.append(v)
                self.obs_tag.append(d.tag_id)
                pixels.append(d.corners)
        self.obs_view = np.array(self.obs_view)
        self.obs_tag = np.array(self.obs_tag)
        self.pixels = np.array(pixels)  # (O, 4, 2)
        self.keep = np.ones(len(self.obs_view), bool)
        self.centres = {t.tag_id: t.center for t in nominal.tags}
        self.local = {t.tag_id: t.corners - t.center for t in nominal.tags}

    def tag_corners(self, x: np.ndarray, tag_id: int) -> np.ndarray:
        local, centre = self.local[tag_id], self.centres[tag_id]
        slot = self.tag_slot.get(tag_id)
        if slot is None:
            return local + centre
        p = x[6 * slot: 6 * slot + 6]
        return local @ _rotation(p[:3]).T + centre + p[3:]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        corners = {tag_id: self.tag_corners(x, tag_id) for tag_id in (self.first, *self.free)}
        out = np.zeros((len(self.obs_view), 4, 2))
        for v in range(len(self.views)):
            rows = np.flatnonzero((self.obs_view == v) & self.keep)
            if len(rows) == 0:
                continue
            pose = x[self.offset + 6 * v: self.offset + 6 * v + 6]
            points = np.concatenate([corners[self.obs_tag[r]] for r in rows])
            out[rows] = project_pose(points, pose[:3], pose[3:], self.calibration).reshape(-1, 4, 2) - self.pixels[rows]
        return out.ravel()

    def sparsity(self, tags_free: bool):
        rows = len(self.obs_view) * 8
        pattern = lil_matrix((rows, self.offset + 6 * len(self.views)), dtype=np.int8)
        for o, (v, tag_id) in enumerate(zip(self.obs_view, self.obs_tag, strict=True)):
            if not self.keep[o]:
                continue
            block = slice(8 * o, 8 * o + 8)
            pattern[block, self.offset + 6 * v: self.offset + 6 * v + 6] = 1
            slot = self.tag_slot.get(int(tag_id))
            if tags_free and slot is not None:
                pattern[block, 6 * slot: 6 * slot + 6] = 1
        return pattern

    def solve(self, x0: np.ndarray, tags_free: bool = True) -> np.ndarray:
        if tags_free:
            fit = least_squares(self.residuals, x0, jac_sparsity=self.sparsity(True), method="trf",
                                x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
            self._last_fit = fit
            return fit.x
        # Tags held at nominal: only the view poses move.
        head = x0[: self.offset]

        def views_only(poses: np.ndarray) -> np.ndarray:
            return self.residuals(np.concatenate([head, poses]))

        fit = least_squares(views_only, x0[self.offset:], jac_sparsity=self.sparsity(False)[:, self.offset:],
                            method="trf", x_scale="jac", max_nfev=100)
        return np.concatenate([head, fit.x])

    def rms(self, x: np.ndarray) -> float:
        r = self.residuals(x).reshape(-1, 4, 2)[self.keep]
        return float(np.sqrt(np.mean(np.sum(r**2, axis=2))))

    def observation_rms(self, x: np.ndarray) -> np.ndarray:
        r = self.residuals(x).reshape(-1, 4, 2)
        return np.sqrt(np.mean(np.sum(r**2, axis=2), axis=1))

    def result(self, x: np.ndarray, nominal_rms: float, skipped: list[tuple[str, str]],
               counts: dict[int, int]) -> TargetCalibration:
        residuals = self.residuals(x)
        dof = max(int(self.keep.sum()) * 8 - len(x), 1)
        sigma2 = float(np.sum(residuals**2)) / dof
        jacobian = self._last_fit.jac
        jacobian = jacobian.toarray() if hasattr(jacobian, "toarray") else np.asarray(jacobian)
        jacobian = jacobian[np.repeat(self.keep, 8)]
        covariance = sigma2 * np.linalg.pinv(jacobian.T @ jacobian)
        per_obs = np.sqrt(np.mean(np.sum(residuals.reshape(-1, 4, 2) ** 2, axis=2), axis=1))
        tags, refined_tags = [], []
        for tag in self.nominal.tags:
            corners = self.tag_corners(x, tag.tag_id)
            refined_tags.append(Tag(tag.tag_id, corners, tag.face))
            mine = (self.obs_tag == tag.tag_id) & self.keep
            rms = float(np.sqrt(np.mean(per_obs[mine] ** 2))) if mine.any() else float("nan")
            slot = self.tag_slot.get(tag.tag_id)
            if slot is None:
                zero = np.zeros(3)
                tags.append(TagResult(tag.tag_id, counts.get(tag.tag_id, 0), tag.tag_id == self.first,
                                      tag.tag_id == self.first, zero, 0.0, zero, zero, rms))
                continue
            p = x[6 * slot: 6 * slot + 6]
            block = covariance[6 * slot: 6 * slot + 6, 6 * slot: 6 * slot + 6]
            sd = np.sqrt(np.clip(np.diag(block), 0.0, None))
            tags.append(TagResult(tag.tag_id, counts.get(tag.tag_id, 0), True, False, p[3:] * 1000,
                                  float(np.degrees(np.linalg.norm(p[:3]))), sd[3:] * 1000, np.degrees(sd[:3]), rms))
        refined = Target(self.nominal.family, tuple(refined_tags), None, "", self.nominal.border_bits)
        validate_target(refined, "refined target")
        per_view = []
        for v, view in enumerate(self.views):
            mine = (self.obs_view == v) & self.keep
            per_view.append((view.name, float(np.sqrt(np.mean(per_obs[mine] ** 2))) if mine.any() else float("nan")))
        return TargetCalibration(refined, tuple(tags), len(self.views), tuple(skipped), self.rms(x), nominal_rms,
                                 tuple(per_view))
