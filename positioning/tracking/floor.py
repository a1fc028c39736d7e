"""The floor a robot drives on: the camera's height and the floor's, as the target measured them.

A camera on a wheeled robot stays at one height over a flat floor, and the floor's corners
lie in one plane. The target measures both once, in metres: while it holds the map, the
heights of the poses sure enough to anchor keyframes give the camera's (the target's z is
up, docs/target.md), and the lowest dense layer of the tracks their frames followed gives
the floor's (each track where all its rays meet one horizontal plane: the target's whole
baseline, where the map's first keyframes may be a few centimetres apart and their points
~1 % off in depth). Bundle adjustment then holds every window the target no longer holds
to both (``bundle.build_problem`` with ``on_the_floor``, ``FloorRows``): the floor's points
in view fix the window's scale, which a monocular map otherwise carries only by its points
and which walks a few percent over tens of metres (docs/tracker.md, "The floor").

Nothing is assumed that the target does not show: a camera whose heights differ by more
than ``FloorOptions.max_height_spread_m`` (carried by hand, or a target not
standing level) has no floor, and neither has a map without a dense layer of points below
the camera (a plain floor, or one out of view).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from cubeloc.positioning.geometry import Transform, skew
from cubeloc.positioning.tracking.options import FloorOptions

if TYPE_CHECKING:
    from cubeloc.positioning.tracking.bundle import BundleProblem


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


def on_the_floor(heights: np.ndarray, floor: Floor, options: FloorOptions) -> np.ndarray:
    """Which of a window's points (their ``heights``) lie on the floor: its own floor layer,
    found near the floor's height (within ``band`` of the camera's height above it, however
    far the window's scale has walked) and as thin as ``find_floor``'s, about the median of
    the points there. A map off in scale has its whole floor layer off together; a point a
    few centimetres up a wall or a box lies apart from it, and pulled down to the floor would
    pull the map with it."""
    above = floor.camera_z - floor.floor_z
    near = np.abs(heights - floor.floor_z) < options.band * above
    if not near.any():
        return np.zeros(0, np.int64)
    level = float(np.median(heights[near]))
    return np.flatnonzero(near & (np.abs(heights - level) <= options.layer_thickness * above / 2))


class FloorRows:
    """The floor's residual pairs in a bundle adjustment window (``problem.floor`` set), in
    pixels: on a point alone, each floor point's height (``(dz, 0)``); on a pose alone, each
    free keyframe's height (``(dz, 0)``), then per older keyframe three pairs, its rotation
    update and its move along the floor. ``points`` and ``poses`` say which point and which
    free pose (``free_index``) each pair is on; ``r0``, ``t0`` are the starting
    camera-from-world poses of all the problem's keyframes."""

    def __init__(self, problem: BundleProblem, free_index: np.ndarray, r0: np.ndarray, t0: np.ndarray,
                 options: FloorOptions) -> None:
        self.problem, self.free_index = problem, free_index
        self.floor_w, self.camera_w = options.floor_px_per_m, options.camera_px_per_m
        self.older_w = options.older_px_per_mm * 1000.0  # per metre and per radian
        self.points = problem.floor_pt
        self.poses = np.concatenate([free_index[problem.height_kf], np.repeat(free_index[problem.older_kf], 3)])
        self.start = -np.einsum("nji,nj->ni", r0[problem.older_kf], t0[problem.older_kf])  # older centres

    def residuals(self, deltas: np.ndarray, rotations: np.ndarray, translations: np.ndarray, points: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """(pairs on a point, pairs on a pose) at the free poses' updates ``deltas`` ((F, 6))
        and the problem's ``rotations``, ``translations`` (camera-from-world) and ``points``."""
        p = self.problem
        on_points = np.zeros((len(p.floor_pt), 2))
        on_points[:, 0] = (points[p.floor_pt, 2] - p.floor.floor_z) * self.floor_w
        centres = -np.einsum("nji,nj->ni", rotations, translations)  # -R^T t
        height = np.zeros((len(p.height_kf), 2))
        height[:, 0] = (centres[p.height_kf, 2] - p.floor.camera_z) * self.camera_w
        older = np.zeros((len(p.older_kf), 3, 2))
        turn = deltas[self.free_index[p.older_kf], :3] * self.older_w
        older[:, 0], older[:, 1, 0] = turn[:, :2], turn[:, 2]
        older[:, 2] = (centres[p.older_kf] - self.start)[:, :2] * self.older_w
        return on_points, np.concatenate([height, older.reshape(-1, 2)])

    def jacobian(self, rotations: np.ndarray, translations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((P, 2, 3) of the pairs on a point, (Q, 2, 6) of the pairs on a pose)."""
        p = self.problem
        on_points = np.zeros((len(p.floor_pt), 2, 3))
        on_points[:, 0, 2] = self.floor_w
        # a camera centre c = -R^T t moves by -R^T dt - R^T [t]x dw (the update exp(dw) R)
        r_t = rotations.transpose(0, 2, 1)
        d_centre = np.concatenate([-r_t @ skew(translations), -r_t], axis=2)  # (K, 3, 6)
        height = np.zeros((len(p.height_kf), 2, 6))
        height[:, 0] = d_centre[p.height_kf, 2] * self.camera_w
        older = np.zeros((len(p.older_kf), 3, 2, 6))
        older[:, 0, 0, 0] = older[:, 0, 1, 1] = older[:, 1, 0, 2] = self.older_w
        older[:, 2] = d_centre[p.older_kf, :2] * self.older_w
        return on_points, np.concatenate([height, older.reshape(-1, 2, 6)])
