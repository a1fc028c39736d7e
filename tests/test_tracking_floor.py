"""The floor a robot drives on (positioning/tracking/floor.py): found from the frames the
target posed, and holding a bundle adjustment window's scale once the target has left."""

from __future__ import annotations

import numpy as np
from test_tracking_core import CAL

from cubeloc.positioning.geometry import Transform, look_at
from cubeloc.positioning.tracking.bundle import apply_solution, build_problem, solve
from cubeloc.positioning.tracking.floor import Floor, TargetView, find_floor, floor_from_views
from cubeloc.positioning.tracking.map import Map
from cubeloc.positioning.tracking.options import BundleOptions, FloorOptions

FLOOR_Z, CAMERA_Z = -0.87, 0.30  # the cube on a 0.78 m table, the camera 1.17 m above the floor
ON = FloorOptions(enabled=True)  # off by default (docs/tracker.md, "The floor")


def scene(seed: int = 3, skirting: bool = False) -> np.ndarray:
    """Floor points, a table top under the cube (at the cube's base) and walls; with
    ``skirting``, boxes along the way whose faces carry points 2-5 cm above the floor."""
    rng = np.random.default_rng(seed)
    floor = np.column_stack([rng.uniform(-1, 8, 600), rng.uniform(-3, 3, 600), np.full(600, FLOOR_Z)])
    table = np.column_stack([rng.uniform(-0.35, 0.35, 40), rng.uniform(-0.35, 0.35, 40), np.full(40, -0.09)])
    wall = np.column_stack([np.full(400, 9.0), rng.uniform(-3, 3, 400), rng.uniform(FLOOR_Z, 2.0, 400)])
    low = np.column_stack([rng.uniform(2, 8, 200), rng.choice([-1.5, 1.5], 200), FLOOR_Z + rng.uniform(0.02, 0.05, 200)])
    return np.concatenate([floor, table, wall] + ([low] if skirting else []))


def pose_at(x: float, z: float = CAMERA_Z) -> Transform:
    """Driving along +x at the camera's height, looking ahead and down at the floor."""
    return look_at(np.array([x, 0.0, z]), np.array([x + 4.0, 0.0, FLOOR_Z]))


def seen(pose: Transform, points: np.ndarray, rng: np.random.Generator, noise_px: float = 0.3
         ) -> tuple[np.ndarray, np.ndarray]:
    """(ids, normalised coordinates) of the points in view, with noise."""
    pc = pose.inverse().apply(points)
    xn = pc[:, :2] / np.maximum(pc[:, 2:], 1e-9)
    inside = (pc[:, 2] > 0.3) & (np.abs(xn[:, 0]) < 0.6) & (np.abs(xn[:, 1]) < 0.45)
    ids = np.flatnonzero(inside)
    return ids, xn[ids] + rng.normal(0, noise_px / CAL.fx, (len(ids), 2))


def test_the_floor_is_the_lowest_dense_layer_under_a_camera_that_keeps_its_height():
    points = scene()
    heights = CAMERA_Z + np.random.default_rng(1).normal(0, 0.0005, 30)
    floor = find_floor(heights, points, FloorOptions())
    assert floor is not None
    assert abs(floor.floor_z - FLOOR_Z) < 1e-3 and abs(floor.camera_z - CAMERA_Z) < 1e-3  # not the table top
    # a camera carried by hand (heights 3 cm apart) is not on a floor
    assert find_floor(heights + np.linspace(0, 0.03, 30), points, FloorOptions()) is None
    # a plain floor: the table top and the walls are no floor
    assert find_floor(heights, points[600:], FloorOptions()) is None
    # too few target poses to tell
    assert find_floor(heights[:5], points, FloorOptions()) is None


def test_the_frames_the_target_posed_give_the_floor_to_a_millimetre():
    points, rng = scene(), np.random.default_rng(2)
    views = []
    for k in range(30):  # 30 frames over 60 cm, each pose 0.3 mm off
        pose = pose_at(0.02 * k)
        ids, xn = seen(pose, points, rng)
        noisy = Transform(pose.rotation, pose.translation + rng.normal(0, 0.0003, 3))
        views.append(TargetView(noisy, ids, xn))
    floor = floor_from_views(views, FloorOptions())
    assert floor is not None
    # 1.17 m below the camera: 0.04 mm here (the two rays' midpoints gave 2.4 mm; the map's
    # own first keyframes are ~1 % off, 12 mm)
    assert abs(floor.floor_z - FLOOR_Z) < 0.001 and abs(floor.camera_z - CAMERA_Z) < 0.001
    assert floor_from_views(views[:5], FloorOptions()) is None


def drifted_map(scale: float, seed: int = 4) -> tuple[Map, list[Transform], np.ndarray]:
    """Twelve keyframes 10 cm apart, none anchored, whose map (keyframes and points) is the
    truth scaled by ``scale`` about the first camera: the scale a monocular map walks to.
    (map, true poses, points)."""
    points, rng = scene(skirting=True), np.random.default_rng(seed)
    poses = [pose_at(3.0 + 0.1 * k) for k in range(12)]
    centre = poses[0].translation
    world_map = Map()
    for k, pose in enumerate(poses):
        ids, xn = seen(pose, points, rng)
        world_map.add_keyframe(k, Transform(pose.rotation, centre + scale * (pose.translation - centre)), ids, xn)
    for t in {int(t) for kf in world_map.keyframes.values() for t in kf.track_ids}:
        world_map.add_point(t, centre + scale * (points[t] - centre), 0)
    return world_map, poses, points


def window_scale(world_map: Map, poses: list[Transform], points: np.ndarray) -> float:
    """The newest keyframe's distances to the points it sees, over the true ones (median)."""
    kf = list(world_map.keyframes.values())[-1]
    ids = [int(t) for t in kf.track_ids if int(t) in world_map.points]
    estimated = np.linalg.norm(np.array([world_map.points[t] for t in ids]) - kf.T_world_camera.translation, axis=1)
    true = np.linalg.norm(points[ids] - poses[-1].translation, axis=1)
    return float(np.median(estimated / true))


def test_a_window_the_floor_holds_comes_back_to_the_floors_scale():
    options = BundleOptions(window_keyframes=6, max_iterations=30, floor=ON)
    for floor, expected in ((Floor(CAMERA_Z, FLOOR_Z), "mended"), (None, "kept")):
        world_map, poses, points = drifted_map(1.05)
        problem = build_problem(world_map, options, floor=floor)
        assert problem is not None
        assert (problem.floor is not None) == (floor is not None)
        if floor is not None:  # the older keyframes move with the window in height
            assert len(problem.older_kf) == 6 and problem.free.all()
            assert len(problem.floor_pt) > 100
            # the floor's layer, not the boxes' faces a few centimetres above it
            assert not np.isin(problem.point_ids[problem.floor_pt], np.arange(1040, 1240)).any()
        assert apply_solution(world_map, solve(problem, options, CAL.fx))
        scale = window_scale(world_map, poses, points)
        if expected == "mended":
            assert abs(scale - 1.0) < 0.01, scale
            heights = [kf.T_world_camera.translation[2] for kf in list(world_map.keyframes.values())[-6:]]
            assert np.max(np.abs(np.array(heights) - CAMERA_Z)) < 0.003
        else:  # without it nothing tells the window its scale
            assert abs(scale - 1.05) < 0.005, scale


def test_a_window_the_target_holds_takes_no_floor():
    world_map, poses, points = drifted_map(1.0)
    kf = list(world_map.keyframes.values())[-1]
    kf.anchored, kf.target_world, kf.target_xn = True, np.zeros((4, 3)) + [8.0, 0, 0], np.zeros((4, 2))
    problem = build_problem(world_map, BundleOptions(floor=ON), floor=Floor(CAMERA_Z, FLOOR_Z))
    assert problem is not None and problem.held_by_target and problem.floor is None
    assert not len(problem.floor_pt) and not len(problem.height_kf) and not len(problem.older_kf)


def test_scipys_solver_reaches_the_same_floor():
    """The reference solver (``solver="scipy"``) on the same window: the floor's rows have
    their place in its sparse Jacobian too (in 30 evaluations it comes most of the way:
    1.05 -> 1.013, ours 1.006)."""
    scales = []
    for solver in ("schur", "scipy"):
        options = BundleOptions(window_keyframes=6, max_iterations=30, solver=solver, floor=ON)
        world_map, poses, points = drifted_map(1.05)
        problem = build_problem(world_map, options, floor=Floor(CAMERA_Z, FLOOR_Z))
        assert apply_solution(world_map, solve(problem, options, CAL.fx))
        scales.append(window_scale(world_map, poses, points))
    assert abs(scales[0] - 1.0) < 0.01 and abs(scales[1] - 1.0) < 0.02, scales
