"""One frame's camera pose from map points *and* tracks whose depth is not known yet.

Map points (triangulated, metric) constrain all six degrees of freedom. A track without a
point is a ray: from the camera centre where the track was born, along the direction it
was seen in. Its point lies somewhere on that ray, so in the current image it lies on the
ray's projection (the epipolar line): across the line it constrains the pose exactly, and
along the line only as far as a loose prior on its inverse depth says (mean ``rho0``,
standard deviation ``rho0``: anywhere from half the scene's median depth to infinity).
With no translation since its birth the ray projects to a point and the track is a full
bearing: that keeps the orientation in a pure rotation, where nothing can be triangulated.
The position is then unobservable from the tracks, and ``prior_position`` (the motion
model's) holds it, with the standard deviation the caller gives.

Residuals are whitened (pixel noise ``sigma_px``, plus the along-ray spread for rays), so
one Gauss-Newton solve on the 6-DoF pose weighs both kinds, with Huber weights and a
chi-square cut. The covariance is the inverse of the whitened normal matrix: what these
measurements say given the map, nothing about the map's own error (the tracker adds that).

SYNOPSIS

    >>> import numpy as np
    >>> from cubeloc.positioning.geometry import Transform
    >>> rng = np.random.default_rng(0)
    >>> points = rng.uniform([-2, -2, 3], [2, 2, 6], (40, 3))          # world = camera frame
    >>> truth = Transform.from_rvec_tvec(np.array([0.0, 0.05, 0.0]), np.array([0.02, 0, 0]))
    >>> from cubeloc.positioning.camera_model import project_normalised
    >>> xn = project_normalised(truth.inverse(), points)[0]
    >>> fit = fit_pose(Transform.identity(), points, xn, None, fx=1000.0, sigma_px=0.2)
    >>> bool(np.allclose(fit.T_world_camera.matrix(), truth.matrix(), atol=1e-6)), fit.covariance.shape
    (True, (6, 6))
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from cubeloc.positioning.camera_model import normalised_jacobian, project_normalised
from cubeloc.positioning.geometry import Transform, robust_sigma, skew

if TYPE_CHECKING:
    from cubeloc.positioning.tracking.map import Map
    from cubeloc.positioning.tracking.options import TrackerOptions
    from cubeloc.positioning.tracking.types import Tracks

HUBER = 2.0  # whitened units: residuals beyond 2 sigma count linearly
CHI2_CUT = 3.03  # whitened norm of a 2-D residual: chi-square 99 % for 2 dof


def pnp_ransac(obj: np.ndarray, xn: np.ndarray, threshold: float, iterations: int, flags: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """OpenCV's RANSAC PnP on normalised coordinates: (rvec, tvec, inlier indices), or None
    when it finds no pose. Degenerate points (collinear, nearly coincident: a map gone bad)
    make SQPnP raise an assertion instead of failing; that too is no pose, not a dead frame
    loop."""
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(obj, xn, np.eye(3), None, iterationsCount=iterations,
                                                     reprojectionError=threshold, confidence=0.999, flags=flags)
    except cv2.error:
        return None
    if not ok or inliers is None:
        return None
    return rvec, tvec, inliers.ravel()


def deleted_residuals(T_camera_world: Transform, points_world: np.ndarray, xn: np.ndarray, fx: float
                      ) -> np.ndarray:
    """Each observation's reprojection error (px) as the least-squares pose fit to all of
    them would leave it without that observation: ``(I - H_i)^-1 r_i``, ``H_i`` its 2 x 2
    block of the fit's hat matrix (its leverage). A point whose leverage is near 1 is fit
    whatever it says, so its own residual tells nothing of it; its deleted residual does."""
    residual, jac, _ = _blocks(T_camera_world.rotation, T_camera_world.translation, points_world, xn, fx)
    flat = jac.reshape(-1, 6)
    normal = flat.T @ flat
    if not np.all(np.isfinite(normal)) or np.linalg.cond(normal) > 1e12:
        return np.linalg.norm(residual, axis=1)
    hat = np.einsum("nij,jk,nlk->nil", jac, np.linalg.inv(normal), jac)  # (N, 2, 2)
    keep = np.eye(2)[None] - hat
    det = keep[:, 0, 0] * keep[:, 1, 1] - keep[:, 0, 1] * keep[:, 1, 0]
    deleted = np.full(len(residual), np.inf)
    ok = det > 1e-9
    deleted[ok] = np.linalg.norm(np.linalg.solve(keep[ok], residual[ok][:, :, None])[:, :, 0], axis=1)
    return deleted


def pose_from_map(world_map: Map, tracks: Tracks, xn: np.ndarray, prediction: Transform | None,
                  o: TrackerOptions, fx: float) -> tuple[Transform | None, int, np.ndarray, float, np.ndarray | None]:
    """The tracker's pose from the tracks with map points (``xn`` their normalised
    coordinates): PnP with RANSAC, refined with Levenberg-Marquardt on the inliers (each
    re-selected by its deleted residual, ``deleted_residuals``), refused beyond
    ``max_motion_*`` from ``prediction``. Returns (pose or None, inliers, outlier
    ids, RMS px, 6x6 covariance from the inliers' reprojection errors)."""
    has = world_map.mapped(tracks.ids)
    # a loaded map's points: they alone when enough. Not the places kept (Map.place_points):
    # made from other viewpoints, they fit the tracks to ~1 px, and a pose on them alone
    # jumps by several millimetres as they come and go (bundle adjustment holds them fixed)
    reference = has & world_map.is_reference(tracks.ids, loaded_only=True)
    has = reference if reference.sum() >= o.reloc.min_reference_points else has
    ids = tracks.ids[has]
    if len(ids) < o.pnp.min_inliers:
        return None, len(ids), np.zeros(0, np.int64), 0.0, None
    obj = np.array([world_map.points[int(t)] for t in ids])
    img = xn[has]
    eye = np.eye(3)
    found = pnp_ransac(obj, img, o.pnp.reproj_px / fx, o.pnp.iterations, cv2.SOLVEPNP_SQPNP)
    if found is None or len(found[2]) < o.pnp.min_inliers:
        return None, 0 if found is None else len(found[2]), np.zeros(0, np.int64), 0.0, None
    rvec, tvec, inl = found
    mask = np.zeros(len(ids), bool)
    mask[inl] = True
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-12)
    for _ in range(2):  # refine on the inliers, then re-select them with the refined pose
        rvec, tvec = cv2.solvePnPRefineLM(obj[mask], img[mask], eye, None, rvec, tvec, criteria)
        T_c_w = Transform.from_rvec_tvec(rvec, tvec)
        proj, z = project_normalised(T_c_w, obj)
        err = np.linalg.norm(proj - img, axis=1) * fx
        # Tracks that drifted along an edge or sit on an occlusion boundary err by a few
        # tenths of a pixel: a robust (MAD) threshold keeps them out of the refinement.
        # Each inlier is judged by its deleted residual (as if the fit had been made
        # without it): a point the pose bent to fit (near the camera, on a passer-by) has
        # a small residual of its own but a large deleted one.
        err[mask] = deleted_residuals(T_c_w, obj[mask], img[mask], fx)
        spread = robust_sigma(err[mask], 0.0, times=3.0) if mask.any() else o.pnp.reproj_px
        mask = (z > 0) & (err <= min(o.pnp.reproj_px, max(o.pnp.min_reproj_px, spread)))
        if mask.sum() < o.pnp.min_inliers:
            return None, int(mask.sum()), ids[~mask], 0.0, None
    pose = T_c_w.inverse()
    drop = ids[~mask]
    if not np.all(np.isfinite(pose.matrix())):
        return None, 0, drop, 0.0, None
    if prediction is not None and beyond_motion(pose, prediction, o):
        return None, int(mask.sum()), drop, 0.0, None
    rms = float(np.sqrt(np.mean(err[mask] ** 2)))
    fit = fit_pose(pose, obj[mask], img[mask], None, fx=fx, sigma_px=max(rms, o.track_sigma_px),
                   iterations=0)
    return pose, int(mask.sum()), drop, rms, None if fit is None else fit.covariance


def beyond_motion(pose: Transform, prediction: Transform, options: TrackerOptions) -> bool:
    """Is ``pose`` further from the motion model's ``prediction`` than a tracker pose may be
    (``motion.max_m``, ``motion.max_deg``)?"""
    return bool(np.linalg.norm(pose.translation - prediction.translation) > options.motion.max_m
                or np.degrees(pose.rotation_angle_to(prediction)) > options.motion.max_deg)


def pose_from_target_and_map(world_map: Map, corners_world: np.ndarray, corners_xn: np.ndarray, tracks: Tracks,
                             xn: np.ndarray, start: Transform, max_reproj_px: float, fx: float) -> Transform | None:
    """One pose from the target's corners (fixed world points, ``corners_xn`` their
    normalised coordinates) and the map points together, refined from ``start`` with the
    map points within ``max_reproj_px`` of it: the map, anchored on many target frames by
    bundle adjustment, averages out the corner noise of a single frame. None when the
    refinement gives no finite pose."""
    has = world_map.mapped(tracks.ids)
    obj = np.concatenate([corners_world, np.array([world_map.points[int(t)] for t in tracks.ids[has]]).reshape(-1, 3)])
    img = np.concatenate([corners_xn, xn[has]])
    T_c_w = start.inverse()
    proj, z = project_normalised(T_c_w, obj)
    keep = (z > 0) & (np.linalg.norm(proj - img, axis=1) * fx <= max_reproj_px)
    keep[: len(corners_world)] = True
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-12)
    # (3, 1) vectors: OpenCV 5 leaves (3,) ones untouched without a word
    rvec, tvec = cv2.solvePnPRefineLM(obj[keep], img[keep], np.eye(3), None, T_c_w.rvec().reshape(3, 1),
                                      T_c_w.translation.reshape(3, 1).copy(), criteria)
    fused = Transform.from_rvec_tvec(rvec, tvec).inverse()
    return fused if np.all(np.isfinite(fused.matrix())) else None


@dataclass(frozen=True)
class Rays:
    """Tracks without a point: where each was born and how it is seen now."""

    centres: np.ndarray  # (K, 3) world camera centre at the track's birth
    directions: np.ndarray  # (K, 3) world unit direction of the track's birth ray
    xn: np.ndarray  # (K, 2) normalised coordinates in the current frame
    rho0: float  # prior inverse depth (1 / the scene's median depth), 1/m


@dataclass(frozen=True)
class PoseFit:
    T_world_camera: Transform
    covariance: np.ndarray  # (6, 6) x y z, rotation about world X Y Z (ROS order)
    point_inliers: np.ndarray  # (M,) bool
    ray_inliers: np.ndarray  # (K,) bool
    rms_px: float  # RMS reprojection error of the map-point inliers, pixels


def _projection(camera: np.ndarray, fx: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalised projections (N, 2) of camera-frame points (N, 3), the Jacobians of their
    pixels (N, 2, 3) and the depths (N,) (clamped away from zero for the division)."""
    z = camera[:, 2]
    safe = np.where(z > 1e-6, z, 1e-6)
    return camera[:, :2] / safe[:, None], normalised_jacobian(camera, safe, fx), z


def _blocks(rotation: np.ndarray, translation: np.ndarray, points: np.ndarray, xn: np.ndarray, fx: float):
    """Pixel residuals (N, 2), their Jacobians (N, 2, 6) in (d_omega, d_t) of
    ``R <- exp(d_omega) R, t <- t + d_t`` (camera from world) and depths (N,)."""
    rotated = points @ rotation.T
    projected, proj, z = _projection(rotated + translation, fx)
    jac = np.concatenate([proj @ -skew(rotated), proj], axis=2)
    return (projected - xn) * fx, jac, z


def _ray_blocks(R: np.ndarray, t: np.ndarray, rays: Rays, fx: float, sigma_px: float):
    """Whitened residuals (K, 2), Jacobians (K, 2, 6) and depths (K,) of the rays.

    A ray's point ``C + d / rho`` projects to ``pi(R d + rho w)``, ``w = R (C - c)`` the
    baseline since its birth in the current camera (``c`` the camera centre). The
    predicted position is at the prior ``rho0``; its spread along the ray's image, one
    sigma of ``rho`` (= ``rho0``), joins the pixel noise there. The rays constrain the
    orientation only (their translation columns are zero): with no depth, what they say
    about the position is what the prior depth assumes, and that is no measurement."""
    d_cam = rays.directions @ R.T
    w = (rays.centres @ R.T) + t  # R C + t = R (C - c)
    predicted, proj, z = _projection(d_cam + rays.rho0 * w, fx)
    residual = (predicted - rays.xn) * fx
    v = np.einsum("kij,kj->ki", proj, w) * rays.rho0  # px moved by one sigma of rho
    norm2 = np.sum(v * v, axis=1)
    unit = v / np.sqrt(np.maximum(norm2, 1e-18))[:, None]
    along_gain = 1.0 / np.sqrt(sigma_px**2 + norm2) - 1.0 / sigma_px
    whiten = np.eye(2)[None] / sigma_px + along_gain[:, None, None] * unit[:, :, None] * unit[:, None, :]
    jac = np.zeros((len(z), 2, 6))
    jac[:, :, :3] = proj @ -skew(d_cam)
    return np.einsum("kij,kj->ki", whiten, residual), whiten @ jac, z


def fit_pose(start: Transform, points_world: np.ndarray, points_xn: np.ndarray, rays: Rays | None, *,
             fx: float, sigma_px: float, prior_position: tuple[np.ndarray, float] | None = None,
             iterations: int = 9) -> PoseFit | None:
    """The pose (T_world_camera) that best explains the map points' and rays'
    observations, from ``start`` after ``iterations`` Gauss-Newton steps (0: the
    covariance of ``start`` itself); None when the normal matrix is singular (nothing
    holds the pose: no points, rays all in one direction and no prior)."""
    R = start.rotation.T.copy()  # camera from world
    t = -R @ start.translation
    points_world = np.asarray(points_world, np.float64).reshape(-1, 3)
    points_xn = np.asarray(points_xn, np.float64).reshape(-1, 2)
    m = len(points_world)
    k = 0 if rays is None else len(rays.xn)
    p_in = np.ones(m, bool)
    r_in = np.ones(k, bool)
    for it in range(iterations + 1):
        rows, jacs = [], []
        # map points: isotropic pixel noise
        res_p, jac_p, z_p = _blocks(R, t, points_world, points_xn, fx)
        res_p, jac_p = res_p / sigma_px, jac_p / sigma_px
        if k:
            res_r, jac_r, z_r = _ray_blocks(R, t, rays, fx, sigma_px)
        else:
            res_r, jac_r, z_r = np.zeros((0, 2)), np.zeros((0, 2, 6)), np.zeros(0)
        # which observations count: the chi-square cut, once the solve has settled
        huber = max(HUBER, 64.0 / 4**it)  # graduated: far from the answer, all pull
        if it >= iterations // 2:
            p_in = (np.linalg.norm(res_p, axis=1) <= CHI2_CUT) & (z_p > 0)
            r_in = (np.linalg.norm(res_r, axis=1) <= CHI2_CUT) & (z_r > 0)
        for res, jac, keep in ((res_p, jac_p, p_in), (res_r, jac_r, r_in)):
            if not keep.any():
                continue
            norm = np.linalg.norm(res[keep], axis=1)
            weight = np.sqrt(np.where(norm <= huber, 1.0, huber / np.maximum(norm, 1e-12)))
            rows.append((res[keep] * weight[:, None]).reshape(-1))
            jacs.append((jac[keep] * weight[:, None, None]).reshape(-1, 6))
        if prior_position is not None:
            mean, sigma_m = prior_position
            c = -R.T @ t
            rows.append((c - mean) / sigma_m)
            jacs.append(np.hstack([-R.T @ skew(t), -R.T]) / sigma_m)
        if not rows:
            return None
        jac = np.concatenate(jacs)
        res = np.concatenate(rows)
        normal = jac.T @ jac
        if not np.all(np.isfinite(normal)) or np.linalg.cond(normal) > 1e12:
            return None
        if it == iterations:
            break
        step = np.linalg.solve(normal, -jac.T @ res)
        R = cv2.Rodrigues(step[:3])[0] @ R
        t = t + step[3:]
    cov_solver = np.linalg.inv(normal)
    # (d_omega, d_t) -> (camera centre, rotation about world axes)
    g = np.zeros((6, 6))
    g[:3, :3] = -R.T @ skew(t)
    g[:3, 3:] = -R.T
    g[3:, :3] = -R.T
    cov = g @ cov_solver @ g.T
    pose = Transform(R.T, -R.T @ t)
    # the last evaluation was at this pose (no step after it)
    rms = float(sigma_px * np.sqrt(np.mean(np.sum(res_p[p_in] ** 2, axis=1)))) if p_in.any() else 0.0
    if not (np.all(np.isfinite(pose.matrix())) and np.all(np.isfinite(cov))):
        return None
    return PoseFit(pose, (cov + cov.T) / 2.0, p_in, r_in, rms)
