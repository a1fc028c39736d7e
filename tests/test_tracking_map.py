"""The map's triangulation (positioning.tracking.twoview and Map.triangulate) on exact
rays: which points it makes, and from which keyframes."""

from __future__ import annotations

import numpy as np

from cubeloc.calib.camera_info import paper_camera
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking.map import Map
from cubeloc.positioning.tracking.options import TrackerOptions
from cubeloc.positioning.tracking.twoview import triangulate

CAL = paper_camera()


def test_triangulation_rejects_points_behind_and_without_parallax():
    a = Transform.identity()
    b = Transform(np.eye(3), np.array([0.2, 0.0, 0.0]))
    points = np.array([[0.0, 0.0, 3.0], [0.1, 0.2, 40.0], [0.0, 0.0, -3.0]])
    xa = points[:, :2] / points[:, 2:]
    xb = (points - b.translation)[:, :2] / (points - b.translation)[:, 2:]
    result = triangulate(a, b, xa, xb, CAL.fx, max_reproj_px=1.0, min_parallax_deg=1.0)
    assert result.good.tolist() == [True, False, False]  # ok; 0.3 deg parallax; behind
    assert np.allclose(result.points_world[0], points[0], atol=1e-9)


def test_map_triangulates_only_across_baselines_that_outweigh_the_poses_own_errors():
    """The oldest keyframe 20 mm from the newest, the next 80 mm: points come from the
    oldest when every pose is sure to 2 mm; from the next when the oldest is 20 mm
    uncertain (its errors, not the parallax, would set the depths: the map's scale); none
    when the newest itself is 100 mm uncertain."""
    k = TrackerOptions().triangulation.min_baseline_sigmas
    points = np.array([[0.1 * j, 0.05 * j, 1.0 + 0.02 * j] for j in range(-5, 6)])
    ids = np.arange(len(points), dtype=np.int64)

    def seen_from(x: float) -> np.ndarray:
        return (points - [x, 0, 0])[:, :2] / (points - [x, 0, 0])[:, 2:]

    for sigmas, expected_birth in (((0.002, 0.002, 0.002), 0), ((0.020, 0.002, 0.002), 1),
                                   ((0.002, 0.002, 0.100), None)):
        world = Map()
        frames = [world.add_keyframe(i, Transform(np.eye(3), np.array([x, 0.0, 0.0])), ids, seen_from(x))
                  for i, x in enumerate((0.04, -0.02, 0.06))]
        for kf, sigma in zip(frames, sigmas, strict=True):
            kf.position_sigma_m = sigma
        world.triangulate(frames[2], CAL.fx, min_parallax_deg=0.5, max_reproj_px=1.0, min_baseline_sigmas=k)
        if expected_birth is None:
            assert not world.points, sigmas
        else:
            assert len(world.points) == len(points), sigmas
            assert set(world.point_birth.values()) == {frames[expected_birth].kf_id}, sigmas
            assert np.allclose(np.array([world.points[int(t)] for t in ids]), points, atol=1e-6)



def test_the_places_kept_for_loop_closure_take_no_part_in_triangulation():
    """Four keyframes on a line, all seeing the same points: against all of them the points
    come from the oldest; when only the newest two before the last are the tracker's (the
    oldest a place kept for loop closure, Map.places) from the second, until a loop has
    closed or agreed."""
    points = np.array([[0.1 * j, 0.05 * j, 1.0 + 0.02 * j] for j in range(-5, 6)])
    ids = np.arange(len(points), dtype=np.int64)
    for recent, agree, expected_birth in ((None, False, 0), (3, False, 0), (2, False, 1), (2, True, 0)):
        world = Map()
        world.places_agree = agree
        frames = [world.add_keyframe(i, Transform(np.eye(3), np.array([x, 0.0, 0.0])), ids,
                                     (points - [x, 0, 0])[:, :2] / (points - [x, 0, 0])[:, 2:])
                  for i, x in enumerate((-0.1, -0.05, 0.0, 0.1))]
        if recent is not None:
            assert world.places(recent + 1, idle=True) == ({0} if (recent, agree) == (2, False) else set())
        world.triangulate(frames[3], CAL.fx, min_parallax_deg=0.5, max_reproj_px=1.0, min_baseline_sigmas=1.0,
                          recent=recent)
        assert len(world.points) == len(points), recent
        assert set(world.point_birth.values()) == {frames[expected_birth].kf_id}, recent
