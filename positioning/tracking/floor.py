"""The floor a robot drives on: the camera's height and the floor's, as the target measured them.

A camera on a wheeled robot stays at one height over a flat floor, and the floor's corners
lie in one plane. The target measures both once, in metres: while it holds the map, the
heights of the poses it anchored keyframes with give the camera's (the target's z is up,
docs/target.md), and the lowest dense layer of the points their frames triangulate below the camera gives the
floor's (each track between the first and the last of those frames that saw it: the widest
baseline the target measured, where the map's first keyframes may be a few centimetres
apart and their points ~1 % off in depth). Bundle
adjustment then holds every window the target no longer holds to both
(``bundle.build_problem``): the floor's points in view fix the window's scale, which a
monocular map otherwise carries only by its points and which walks a few percent over tens
of metres (docs/tracker.md, "The floor").

Nothing is assumed that the target does not show: a camera whose heights differ by more
than ``FloorOptions.max_height_spread_m`` (carried by hand, or a target not
standing level) has no floor, and neither has a map without a dense layer of points below
the camera (a plain floor, or one out of view).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from positioning.geometry import Transform
from positioning.tracking.options import FloorOptions


@dataclass(frozen=True)
class Floor:
    camera_z: float  # the camera's height in the world frame (z up)
    floor_z: float  # the floor's


def find_floor(camera_heights: np.ndarray, points: np.ndarray, options: FloorOptions) -> Floor | None:
    """The floor under a camera that the target saw at ``camera_heights`` (world z of the
    poses it anchored keyframes with), among the map's ``points`` ((N, 3), world); None when
    they do not show one.

    >>> import numpy as np
    >>> heights = np.array([0.5, 0.501, 0.499, 0.5] * 3)
    >>> floor = np.array([[0.1 * i, 1.0, -0.09 + 0.001 * (i % 3)] for i in range(40)])
    >>> find_floor(heights, floor, FloorOptions())
    Floor(camera_z=0.5, floor_z=-0.089)
    >>> find_floor(heights + np.arange(12) * 0.005, floor, FloorOptions()) is None  # carried by hand
    True
    """
    if len(camera_heights) < options.min_target_poses:
        return None
    low, camera_z, high = np.percentile(camera_heights, [10, 50, 90])
    if high - low > options.max_height_spread_m:
        return None
    z = np.asarray(points, np.float64).reshape(-1, 3)[:, 2]
    below = np.sort(z[z < camera_z - options.min_camera_height_m])
    if len(below) < options.min_points:
        return None
    needed = max(options.min_points, options.min_share * len(below))
    # the lowest layer holding enough points: its thickness grows with its depth below the
    # camera, as the points' height errors do (the map's scale and depth errors)
    thickness = options.layer_thickness * (camera_z - below)
    ends = np.searchsorted(below, below + thickness, side="right")
    dense = np.flatnonzero(ends - np.arange(len(below)) >= needed)
    if not len(dense):
        return None
    first = int(dense[0])
    centre = float(np.median(below[first:ends[first]]))
    for _ in range(2):  # centred on the layer, not begun at its lowest point
        half = options.layer_thickness * (camera_z - centre) / 2
        centre = float(np.median(below[np.abs(below - centre) <= half]))
    return Floor(float(camera_z), centre)


@dataclass(frozen=True)
class TargetView:
    """A frame the target posed well enough to anchor a keyframe: its pose and its tracks."""

    T_world_camera: Transform
    track_ids: np.ndarray  # (N,)
    xn: np.ndarray  # (N, 2) normalised coordinates


def floor_from_views(views: Sequence[TargetView], options: FloorOptions) -> Floor | None:
    """``find_floor`` on the views' heights and on the heights their tracks give. A track
    counts when its rays in the first and the last view that saw it meet at
    ``options.min_parallax_deg`` or more, in front of both; its height is then the one at
    which the rays of every view that saw it meet a horizontal plane in one point (least
    squares over all of them: the target poses' own errors average out)."""
    if len(views) < options.min_target_poses:
        return None
    heights = np.array([v.T_world_camera.translation[2] for v in views])
    ids = np.concatenate([v.track_ids for v in views])
    view_of = np.concatenate([np.full(len(v.track_ids), k) for k, v in enumerate(views)])
    xn = np.concatenate([v.xn for v in views]).reshape(-1, 2)
    tracks, first, track_of = np.unique(ids, return_index=True, return_inverse=True)
    _, last_reversed = np.unique(ids[::-1], return_index=True)
    last = len(ids) - 1 - last_reversed
    rotations = np.array([v.T_world_camera.rotation for v in views])
    centres = np.array([v.T_world_camera.translation for v in views])
    rays = np.einsum("nij,nj->ni", rotations[view_of], np.column_stack([xn, np.ones(len(xn))]))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    da, db = rays[first], rays[last]
    # the closest points of the first and the last ray: ca + s da and cb + t db
    w, ab = centres[view_of[first]] - centres[view_of[last]], np.einsum("ni,ni->n", da, db)
    wa, wb = np.einsum("ni,ni->n", w, da), np.einsum("ni,ni->n", w, db)
    denominator = np.maximum(1.0 - ab**2, 1e-12)
    s_a, t_b = (ab * wb - wa) / denominator, (wb - ab * wa) / denominator
    parallax = np.degrees(np.arccos(np.clip(ab, -1.0, 1.0)))
    good = (view_of[last] > view_of[first]) & (parallax >= options.min_parallax_deg) & (s_a > 0) & (t_b > 0)
    rows = np.flatnonzero(good[track_of] & (rays[:, 2] < -1e-3))  # looking down at the plane
    if not len(rows):
        return find_floor(heights, np.zeros((0, 3)), options)
    # a ray c + u r/r_z meets the plane z = h at (c_xy + (h - c_z) r_xy / r_z): all of a
    # track's meet at one (X, Y) when  X - (r_x / r_z) h = c_x - c_z r_x / r_z  (and for y)
    slope = rays[rows, :2] / rays[rows, 2:]
    c = centres[view_of[rows]]
    a = np.zeros((len(rows), 2, 3))
    a[:, 0, 0] = a[:, 1, 1] = 1.0
    a[:, :, 2] = -slope
    b = c[:, :2] - c[:, 2:] * slope
    normal = np.zeros((len(tracks), 3, 3))
    rhs = np.zeros((len(tracks), 3))
    np.add.at(normal, track_of[rows], np.einsum("nki,nkj->nij", a, a))
    np.add.at(rhs, track_of[rows], np.einsum("nki,nk->ni", a, b))
    counted = np.flatnonzero(np.bincount(track_of[rows], minlength=len(tracks)) >= 2)
    solvable = counted[np.abs(np.linalg.det(normal[counted])) > 1e-12]
    points = np.linalg.solve(normal[solvable], rhs[solvable][:, :, None])[:, :, 0]
    return find_floor(heights, points, options)
