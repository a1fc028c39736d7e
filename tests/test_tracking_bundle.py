"""Sliding-window bundle adjustment and the scale it measures, on the synthetic geometry
of ``test_tracking_core`` (a window of keyframes seeing a textured room, seeded noise)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_tracking_core import CAL, CUBE, SyntheticTracks, room_points, visible_ids

from cubeloc.positioning.camera_model import undistort
from cubeloc.positioning.geometry import Transform, look_at
from cubeloc.positioning.tracking.bundle import apply_solution, build_problem, solve
from cubeloc.positioning.tracking.hold import Drift
from cubeloc.positioning.tracking.map import Map
from cubeloc.positioning.tracking.options import BundleOptions, TrackerOptions


def perturbed_window(seed: int = 5) -> tuple[Map, SyntheticTracks, list[Transform], np.ndarray]:
    """Five anchored keyframes 10 cm apart, 1 cm off in position, seeing points 3 cm off,
    with 0.3 px noise on the tracks: (map, source, true poses, point ids)."""
    source = SyntheticTracks(room_points(3), seed=4)
    poses = [look_at(np.array([-1.5 + 0.1 * k, -1.8, 0.5]), np.zeros(3)) for k in range(5)]
    ids = visible_ids(source, poses)
    rng = np.random.default_rng(seed)
    world_map = Map()
    for k, pose in enumerate(poses):
        pc = pose.inverse().apply(source.points[ids])
        xn = pc[:, :2] / pc[:, 2:] + rng.normal(0, 0.3 / CAL.fx, (len(ids), 2))
        observation = source.target(pose)
        noisy = Transform(pose.rotation, pose.translation + (rng.normal(0, 0.01, 3) if k else 0))
        world_map.add_keyframe(k, noisy, ids, xn, observation.corners_world,
                               undistort(observation.corners_px, CAL))
    for t in ids:
        world_map.add_point(int(t), source.points[t] + rng.normal(0, 0.03, 3), 0)
    return world_map, source, poses, ids


def test_bundle_adjustment_pulls_a_perturbed_window_back_onto_the_target():
    world_map, source, poses, ids = perturbed_window()
    before = np.median(np.linalg.norm(np.array([world_map.points[int(t)] for t in ids]) - source.points[ids], axis=1))
    problem = build_problem(world_map, BundleOptions(window_keyframes=5, max_iterations=30))
    assert problem is not None and problem.free.all()  # anchored: no keyframe needs holding
    solution = solve(problem, BundleOptions(max_iterations=30), CAL.fx)
    assert solution.final_rms_px < solution.initial_rms_px / 10
    assert apply_solution(world_map, solution)
    after = np.array([world_map.points[int(t)] for t in ids]) - source.points[ids]
    # Across the rays the points come back to a few millimetres. Along them they do not:
    # the depth of points 5-6 m away from a 40 cm baseline follows that baseline's scale,
    # which only the target's corners fix (2 mm in 40 cm is 3 cm at 6 m).
    rays = source.points[ids] - poses[2].translation
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    across = after - np.einsum("ij,ij->i", after, rays)[:, None] * rays
    assert np.median(np.linalg.norm(across, axis=1)) < before / 10
    pose_errors = [np.linalg.norm(kf.T_world_camera.translation - p.translation)
                   for kf, p in zip(world_map.keyframes.values(), poses, strict=True)]
    assert max(pose_errors) < 0.003  # metres: held by the target's corners
    # a solution for a map that has moved since is not applied
    world_map.correct(Transform.identity())
    assert not apply_solution(world_map, solution)


def test_the_scale_variance_bundle_adjustment_claims_covers_its_scale_error():
    """Thirty windows of five keyframes held by their two oldest (no target), each with new
    0.3 px noise on the tracks: the window's scale error (the mean relative error of its
    points' distances from the newest keyframe) squared, over the variance the solution
    claims for it, averages about 1 (1 degree of freedom): neither far above (claims too
    much) nor far below (claims too little). Every point here is placed alike, so the
    weighted mean the solution means is the plain mean."""
    source = SyntheticTracks(room_points(3), seed=4)
    poses = [look_at(np.array([-1.5 + 0.1 * k, -1.8, 0.5]), np.zeros(3)) for k in range(5)]
    ids = visible_ids(source, poses)
    ratios = []
    for trial in range(30):
        rng = np.random.default_rng(100 + trial)
        world_map = Map()
        for k, pose in enumerate(poses):
            pc = pose.inverse().apply(source.points[ids])
            xn = pc[:, :2] / pc[:, 2:] + rng.normal(0, 0.3 / CAL.fx, (len(ids), 2))
            start = Transform(pose.rotation, pose.translation + (rng.normal(0, 0.01, 3) if k >= 2 else 0))
            world_map.add_keyframe(k, start, ids, xn)
        for t in ids:
            world_map.add_point(int(t), source.points[t] + rng.normal(0, 0.03, 3), 0)
        problem = build_problem(world_map, BundleOptions(window_keyframes=5))
        assert list(problem.free) == [False, False, True, True, True]  # the gauge: the two oldest held
        solution = solve(problem, BundleOptions(max_iterations=30), CAL.fx, sigma_px=0.3)
        assert not solution.held_by_target
        rays = solution.points - solution.T_world_camera[-1].translation
        distance = np.linalg.norm(rays, axis=1)
        true_distance = np.linalg.norm(source.points[solution.point_ids] - poses[-1].translation, axis=1)
        scale_error = np.mean(distance / true_distance - 1.0)
        ratios.append(scale_error**2 / solution.scale_var)
    assert 0.4 < np.mean(ratios) < 2.5
    assert np.mean(np.array(ratios) < 9.0) >= 0.9  # inside 3 sigma


def test_the_drift_grows_with_the_path_at_the_scale_bundle_adjustment_measured():
    """Windows held by keyframes walk the scale on (each adds the share of the window's
    variance its new points are); one held by the target sets it; the position's standard deviation
    grows by the scale's per metre travelled, never by less than ``drift.per_m``."""
    options = TrackerOptions()
    drift = Drift(options)
    step = Transform(np.eye(3), np.array([1.0, 0.0, 0.0]))
    start, measured = Transform.identity(), np.zeros((6, 6))
    drift.covariance(None, start, measured)
    sigma = np.sqrt(drift.covariance(start, step, measured)[0, 0])  # 1 m at the floor's rate
    assert sigma == pytest.approx(options.drift.floor_m + options.drift.per_m * 1.0)
    for _ in range(4):  # four windows measuring a 2 % scale across them, each with a quarter of its points new
        drift.scale_measured(0.02**2, 0.25, held_by_target=False)
    assert np.sqrt(drift.scale_var) == pytest.approx(0.02)
    sigma = np.sqrt(drift.covariance(step, Transform(np.eye(3), np.array([2.0, 0.0, 0.0])), measured)[0, 0])
    assert sigma == pytest.approx(options.drift.floor_m + options.drift.per_m + 0.02)
    drift.scale_measured(0.001**2, 0.5, held_by_target=True)  # the target's window: its scale
    assert np.sqrt(drift.scale_var) == pytest.approx(0.001)
    drift.reset()
    assert drift.scale_var == 0.0 and drift.scaled_m == 0.0


def test_a_map_is_no_surer_of_its_scale_than_its_best_pair_of_anchored_keyframes():
    """``Map.anchored_scale_var``: two target poses a baseline apart, each unsure by its
    own covariance along it, fix the scale to that over the baseline; the best pair
    counts, keyframes without the target (or a covariance) do not. A window held by the
    target claims no surer a scale (``Drift.scale_measured``): a map begun on 3 cm
    between poses 6 and 7.7 mm unsure (the family's seed 2) has it to ~30 %, where its
    window's points said 0.5 %."""
    world_map = Map()

    def keyframe(x: float, sigmas: tuple[float, float, float] | None, anchored: bool = True):
        kf = world_map.add_keyframe(0, Transform(np.eye(3), np.array([x, 0.0, 0.0])), np.zeros(0, np.int64),
                                    np.zeros((0, 2)), np.ones((4, 3)) if anchored else None,
                                    np.ones((4, 2)) if anchored else None)
        kf.anchor_covariance = None if sigmas is None else np.diag(np.square(sigmas))
        return kf

    keyframe(0.0, (0.006, 0.05, 0.05))  # unsure across the baseline: that does not count
    assert world_map.anchored_scale_var() == 0.0  # one anchor fixes no scale
    keyframe(0.032, (0.0077, 0.05, 0.05))
    assert np.sqrt(world_map.anchored_scale_var()) == pytest.approx(np.hypot(0.006, 0.0077) / 0.032)
    keyframe(1.0, None)  # anchored, no covariance: not counted
    keyframe(2.0, (0.001, 0.001, 0.001), anchored=False)  # not anchored: not counted
    assert np.sqrt(world_map.anchored_scale_var()) == pytest.approx(np.hypot(0.006, 0.0077) / 0.032)
    keyframe(0.5, (0.002, 0.05, 0.05))  # 0.5 m from the first: the best pair now
    best = world_map.anchored_scale_var()
    assert np.sqrt(best) == pytest.approx(np.hypot(0.006, 0.002) / 0.5)
    drift = Drift(TrackerOptions())
    drift.scale_measured(0.005**2, 1.0, held_by_target=True, anchored_var=best)
    assert drift.scale_var == pytest.approx(best)
    drift.scale_measured(0.05**2, 1.0, held_by_target=True, anchored_var=best)  # the window less sure: its own
    assert drift.scale_var == pytest.approx(0.05**2)


def test_a_loop_closed_onto_a_surer_keyframe_rewinds_the_drift_to_its():
    """Drift.rewind: path, turn and scale walk shrink alike until the growth is the
    reference keyframe's, so the position's standard deviation comes down with it; a
    reference less sure than now changes nothing."""
    options = TrackerOptions()
    drift = Drift(options)
    measured, pose = np.zeros((6, 6)), Transform.identity()
    drift.covariance(None, pose, measured)
    for k in range(1, 11):  # 10 m, turning 0.1 rad a metre
        nxt = Transform.from_rvec_tvec(np.array([0.0, 0.1 * k, 0.0]), np.array([float(k), 0.0, 0.0]))
        drift.covariance(pose, nxt, measured)
        pose = nxt
    grown, sigma = drift.grown_m, np.sqrt(drift.covariance(pose, pose, measured)[0, 0])
    drift.rewind(2 * grown)
    assert drift.grown_m == pytest.approx(grown)
    drift.rewind(grown / 4)
    assert drift.grown_m == pytest.approx(grown / 4)
    after = np.sqrt(drift.covariance(pose, pose, measured)[0, 0])
    assert after - drift.floor_m == pytest.approx((sigma - drift.floor_m) / 4)


@pytest.mark.parametrize("seed", [5, 6, 7])
def test_our_solver_reaches_the_same_solution_as_scipys(seed):
    """The Schur-complement Levenberg-Marquardt (the default) against SciPy's
    least_squares on the same window: at least as low a reprojection error, the poses
    within a millimetre or two, the same dropped points. They are not closer because
    SciPy's LSMR steps stop short along the window's weak direction (its scale, which only
    the target's corners fix): ours goes on to the minimum, and from there a second solve
    finds nothing more. Its speed is measured by ``python -m bench tracker``."""
    world_map, _, poses, _ = perturbed_window(seed)
    problem = build_problem(world_map, BundleOptions(window_keyframes=5))
    ours = solve(problem, BundleOptions(solver="schur"), CAL.fx)
    scipys = solve(problem, BundleOptions(solver="scipy"), CAL.fx)
    assert ours.final_rms_px < ours.initial_rms_px / 10
    assert ours.final_rms_px <= scipys.final_rms_px
    for a, b in zip(ours.T_world_camera, scipys.T_world_camera, strict=True):
        assert np.linalg.norm(a.translation - b.translation) < 2e-3
        assert np.degrees(a.rotation_angle_to(b)) < 0.05
    assert set(ours.bad_point_ids) == set(scipys.bad_point_ids)
    assert apply_solution(world_map, ours)
    again = solve(build_problem(world_map, BundleOptions(window_keyframes=5)), BundleOptions(solver="schur"), CAL.fx)
    assert again.final_rms_px > ours.final_rms_px * 0.999


def test_our_solver_refines_points_alone_when_every_pose_is_held():
    """No free pose (the reduced system is empty): the points still come back, onto the
    held (here: true) poses' rays."""
    world_map, source, poses, _ = perturbed_window()
    problem = build_problem(world_map, BundleOptions(window_keyframes=5))
    held = replace(problem, free=np.zeros(len(problem.kf_ids), bool), T_camera_world=tuple(p.inverse() for p in poses),
                   tgt_kf=np.zeros(0, np.int64), tgt_world=np.zeros((0, 3)), tgt_xn=np.zeros((0, 2)))
    solution = solve(held, BundleOptions(max_iterations=30), CAL.fx)
    assert all(np.all(np.isfinite(p.matrix())) for p in solution.T_world_camera)
    assert solution.final_rms_px < solution.initial_rms_px / 3
    error_before = np.median(np.linalg.norm(held.points - source.points[held.point_ids], axis=1))
    error_after = np.median(np.linalg.norm(solution.points - source.points[held.point_ids], axis=1))
    assert error_after < error_before / 2


def test_the_window_keeps_the_newest_anchored_keyframes_that_share_its_points():
    """Four anchored keyframes, then six without the target: the window (6) is the six,
    and the three newest anchored keyframes join it, adjusted and held by their corners;
    the oldest anchored one stays as a fixed constraint."""
    world_map = Map()
    pose = look_at(np.array([-1.5, -1.8, 0.5]), np.zeros(3))
    ids = np.arange(4, dtype=np.int64)
    corners = CUBE.tags[0].corners
    for k in range(10):
        anchored = k < 4
        world_map.add_keyframe(k, pose, ids, np.zeros((4, 2)), corners if anchored else None,
                               np.zeros((4, 2)) if anchored else None)
    for t in ids:
        world_map.add_point(int(t), np.array([0.0, 0.0, 1.0 + t]), 0)
    problem = build_problem(world_map, BundleOptions(window_keyframes=6, anchored_keyframes=3))
    free = dict(zip(problem.kf_ids.tolist(), problem.free.tolist(), strict=True))
    assert free == {0: False, 1: True, 2: True, 3: True, 4: True, 5: True, 6: True, 7: True, 8: True, 9: True}
    assert len(problem.tgt_kf) == 3 * 4  # the corners of the three adjusted anchored keyframes
    plain = build_problem(world_map, BundleOptions(window_keyframes=6, anchored_keyframes=0))
    assert sorted(plain.kf_ids[plain.free].tolist()) == [4, 5, 6, 7, 8, 9] and len(plain.tgt_kf) == 0
    # only the newest eight are the map's working set (the rest places kept for loop
    # closure, Map.places): the newest anchored keyframe in it joins, the next is a fixed
    # constraint, the places take no part
    recent = build_problem(world_map, BundleOptions(window_keyframes=6, anchored_keyframes=1), recent=8)
    free = dict(zip(recent.kf_ids.tolist(), recent.free.tolist(), strict=True))
    assert free == {2: False, 3: True, 4: True, 5: True, 6: True, 7: True, 8: True, 9: True}
    assert len(recent.tgt_kf) == 4
    world_map.places_agree = True  # once a loop has closed they are fixed constraints again
    closed = build_problem(world_map, BundleOptions(window_keyframes=6, anchored_keyframes=1), recent=8)
    assert closed.kf_ids[~closed.free].tolist() == [0, 1, 2] and len(closed.tgt_kf) == 4
    world_map.places_agree = False
    places = build_problem(world_map, BundleOptions(window_keyframes=6, anchored_keyframes=3), recent=6)
    # nothing holds this window (the anchored keyframes are all places): its two oldest hold the gauge
    assert places.kf_ids.tolist() == [4, 5, 6, 7, 8, 9] and len(places.tgt_kf) == 0
    assert places.kf_ids[places.free].tolist() == [6, 7, 8, 9]


def test_a_late_solution_carries_the_keyframes_and_points_built_meanwhile():
    """A background solution lands after a keyframe and points were added on the old
    poses: they move with the newest adjusted keyframe, including a point triangulated
    against an old keyframe (its birth keyframe is old, but it was added after the
    snapshot); a point the solution knew keeps the solved position."""
    world_map = Map()
    pose = look_at(np.array([-1.5, -1.8, 0.5]), np.zeros(3))
    ids = np.arange(3, dtype=np.int64)
    for k in range(2):
        world_map.add_keyframe(k, pose, ids, np.zeros((3, 2)))
    world_map.add_point(0, np.array([1.0, 0.0, 0.0]), 0)
    problem = build_problem(world_map, BundleOptions(window_keyframes=2))
    assert problem is not None and list(problem.point_ids) == [0]
    # meanwhile, in the frame loop: a keyframe, a point born at keyframe 0, one at keyframe 2
    world_map.add_keyframe(2, pose, ids, np.zeros((3, 2)))
    world_map.add_point(1, np.array([0.0, 1.0, 0.0]), 0)
    world_map.add_point(2, np.array([0.0, 0.0, 1.0]), 2)
    shift = Transform(np.eye(3), np.array([0.0, 0.0, 0.01]))  # the solution moved both keyframes 1 cm up
    solution = replace(solve(problem, BundleOptions(max_iterations=1), CAL.fx),
                       T_world_camera=(shift @ pose, shift @ pose), points=np.array([[1.0, 0.0, 0.01]]),
                       bad_point_ids=np.zeros(0, np.int64))
    assert apply_solution(world_map, solution)
    np.testing.assert_allclose(world_map.keyframes[2].T_world_camera.translation, pose.translation + [0, 0, 0.01], atol=1e-12)
    np.testing.assert_allclose(world_map.points[0], [1.0, 0.0, 0.01], atol=1e-12)
    np.testing.assert_allclose(world_map.points[1], [0.0, 1.0, 0.01], atol=1e-12)
    np.testing.assert_allclose(world_map.points[2], [0.0, 0.0, 1.01], atol=1e-12)




def test_the_places_followed_after_a_loop_are_held_as_the_reference():
    """Points of the places kept, found again after a loop closed (``Map.place_points``),
    enter bundle adjustment as fixed world points, as a loaded map's do: they are not
    adjusted, and the keyframes seeing them are held to them. The pose alone does not take
    them as a loaded map's reference (``is_reference(loaded_only=True)``)."""
    world_map, source, poses, ids = perturbed_window()
    places = {int(t) for t in ids[::2]}
    world_map.place_points.update(places)
    problem = build_problem(world_map, BundleOptions(window_keyframes=5))
    assert problem is not None
    assert places.isdisjoint(int(p) for p in problem.point_ids)
    held = len(problem.tgt_world) - sum(len(kf.target_world) for kf in world_map.keyframes.values())
    assert held == sum(int(t) in places for kf in world_map.keyframes.values() for t in kf.track_ids)
    assert world_map.is_reference(ids).sum() == len(places)
    assert not world_map.is_reference(ids, loaded_only=True).any()
    world_map.remove_point(int(ids[0]))
    assert int(ids[0]) not in world_map.place_points
