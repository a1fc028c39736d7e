"""Two-view geometry on normalised image coordinates: triangulation and parallax.

Everything inside the tracker works on undistorted normalised coordinates ``(x, y)`` of the
ray ``(x, y, 1)``: the distortion is removed once per observation, and reprojection errors
are scaled back to pixels by ``fx`` so thresholds read in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cubeloc.positioning.camera_model import project_normalised
from cubeloc.positioning.geometry import Transform


@dataclass(frozen=True)
class Triangulated:
    points_world: np.ndarray  # (N, 3)
    good: np.ndarray  # (N,) bool: in front of both cameras, reprojects, enough parallax
    parallax_deg: np.ndarray  # (N,) angle between the two rays at the point
    reproj_px: np.ndarray  # (N,) the worse of the two views' reprojection errors


def triangulate(
    T_world_a: Transform,
    T_world_b: Transform,
    xn_a: np.ndarray,
    xn_b: np.ndarray,
    fx: float,
    max_reproj_px: float,
    min_parallax_deg: float,
) -> Triangulated:
    """Linear (DLT) triangulation of matched normalised points from two posed cameras.

    The poses are metric (from the target or the map), so the points are too. A point is
    ``good`` when it lies in front of both cameras (cheirality), reprojects within
    ``max_reproj_px`` in both, and its rays meet at ``min_parallax_deg`` or more (depth
    from a smaller angle is mostly noise).
    """
    xn_a = np.asarray(xn_a, dtype=np.float64).reshape(-1, 2)
    xn_b = np.asarray(xn_b, dtype=np.float64).reshape(-1, 2)
    n = len(xn_a)
    if n == 0:
        empty = np.zeros(0)
        return Triangulated(np.zeros((0, 3)), np.zeros(0, bool), empty, empty)
    T_a_world = T_world_a.inverse()
    T_b_world = T_world_b.inverse()
    pa = T_a_world.matrix()[:3]
    pb = T_b_world.matrix()[:3]
    homogeneous = cv2.triangulatePoints(pa, pb, xn_a.T.copy(), xn_b.T.copy())
    w = homogeneous[3]
    with np.errstate(divide="ignore", invalid="ignore"):
        points = (homogeneous[:3] / w).T
    finite = np.all(np.isfinite(points), axis=1) & (np.abs(w) > 1e-12)
    points = np.where(finite[:, None], points, 0.0)
    proj_a, z_a = project_normalised(T_a_world, points)
    proj_b, z_b = project_normalised(T_b_world, points)
    err_a = np.linalg.norm(proj_a - xn_a, axis=1) * fx
    err_b = np.linalg.norm(proj_b - xn_b, axis=1) * fx
    reproj = np.where(finite, np.maximum(err_a, err_b), np.inf)
    ray_a = points - T_world_a.translation
    ray_b = points - T_world_b.translation
    cos = np.sum(ray_a * ray_b, axis=1) / np.maximum(
        np.linalg.norm(ray_a, axis=1) * np.linalg.norm(ray_b, axis=1), 1e-12
    )
    parallax = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    good = finite & (z_a > 0) & (z_b > 0) & (reproj <= max_reproj_px) & (parallax >= min_parallax_deg)
    return Triangulated(points, good, parallax, np.nan_to_num(reproj, nan=np.inf))


def baseline_scale_var(baselines: np.ndarray, covariance_a: np.ndarray, covariance_b: np.ndarray) -> np.ndarray:
    """The variance of the relative length of baselines between two positions, each off by
    its own covariance along it: (b^T C_a b + b^T C_b b) / |b|^4, the relative scale a map
    begun (or anchored) on the two has. ``baselines`` (..., 3) and the (..., 3, 3)
    covariances broadcast together; a zero baseline gives inf.

    >>> cov = np.eye(3) * 0.01**2  # 10 mm on each axis, 100 mm apart: 14 mm over 100 mm
    >>> round(float(np.sqrt(baseline_scale_var(np.array([0.1, 0.0, 0.0]), cov, cov))), 3)
    0.141
    """
    b = np.asarray(baselines, np.float64)
    along = (np.einsum("...k,...kl,...l->...", b, covariance_a, b)
             + np.einsum("...k,...kl,...l->...", b, covariance_b, b))
    squared = np.einsum("...k,...k->...", b, b)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(squared > 0.0, along / np.where(squared > 0.0, squared, 1.0) ** 2, np.inf)


def rotation_compensated_parallax_deg(
    T_world_a: Transform, T_world_b: Transform, xn_a: np.ndarray, xn_b: np.ndarray
) -> np.ndarray:
    """Per match, the angle between B's ray and A's ray rotated into B (N,), degrees.

    Pure rotation gives zero whatever the rotation, so this measures the baseline's effect
    only: the parallax that triangulation will have to work with.
    """
    rays_a = np.column_stack([xn_a, np.ones(len(xn_a))])
    rays_b = np.column_stack([xn_b, np.ones(len(xn_b))])
    r_b_a = T_world_b.rotation.T @ T_world_a.rotation
    rotated = rays_a @ r_b_a.T
    cos = np.sum(rotated * rays_b, axis=1) / (np.linalg.norm(rotated, axis=1) * np.linalg.norm(rays_b, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
