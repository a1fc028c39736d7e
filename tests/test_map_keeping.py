"""How the tracker's map keeps up with the place: the cube's return spreads its correction
along the drift (Map.correct), and a loaded map's points that are no longer there retire
(Map.retire)."""

from __future__ import annotations

import numpy as np

from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking.map import Map
from cubeloc.positioning.tracking.options import TrackerOptions


def test_the_targets_return_spreads_its_correction_along_the_drift():
    """Map.correct with the drift's growth: a keyframe made just after the target moves by
    a third of the correction when a third of the drift had grown by then, the newest by
    all of it, the anchored one and a loaded map's (``fixed``) not at all; each point as
    the keyframe it was triangulated at (one whose keyframe is gone as the oldest left)."""
    world_map = Map()
    for k in range(5):
        kf = world_map.add_keyframe(k, Transform.from_rvec_tvec(np.zeros(3), np.array([k, 0.0, 0.0])),
                                    np.array([k]), np.zeros((1, 2)))
        kf.drift_m = 0.01 * k
        world_map.add_point(k, np.array([k, 1.0, 0.0]), k)
    world_map.keyframes[0].anchored = True
    world_map.fixed = {4}
    world_map.add_point(9, np.array([9.0, 1.0, 0.0]), 7)  # its keyframe culled
    correction = Transform.from_rvec_tvec(np.array([0.0, 0.0, 0.003]), np.array([0.0, 0.03, 0.0]))
    before = {k: kf.T_world_camera for k, kf in world_map.keyframes.items()}
    points = {k: p.copy() for k, p in world_map.points.items()}
    world_map.correct(correction, grown_m=0.03)
    for k, share in ((0, 0.0), (1, 1 / 3), (2, 2 / 3), (3, 1.0), (4, 0.0)):
        part = Transform.from_rvec_tvec(share * correction.rvec(), share * correction.translation)
        np.testing.assert_allclose(world_map.keyframes[k].T_world_camera.matrix(), (part @ before[k]).matrix(),
                                   atol=1e-12)
        np.testing.assert_allclose(world_map.points[k], part.apply(points[k][None])[0], atol=1e-12)
    oldest = Transform.from_rvec_tvec(correction.rvec() / 3, correction.translation / 3)
    np.testing.assert_allclose(world_map.points[9], oldest.apply(points[9][None])[0], atol=1e-12)
    # without the drift's growth: all of it, everywhere drifted (the correction before)
    world_map.correct(correction)
    np.testing.assert_allclose(world_map.keyframes[1].T_world_camera.matrix(),
                               (correction @ Transform.from_rvec_tvec(correction.rvec() / 3,
                                                                      correction.translation / 3)
                                @ before[1]).matrix(), atol=1e-12)


def test_a_loaded_point_not_found_where_it_should_be_seen_retires():
    """Map.retire: a point seen in at most one of its last ten chances goes (and is counted);
    one found twice in ten, or not yet given ten chances, stays; a chance counts only 10 cm
    or more from where the point's last one was."""
    world_map, options = Map(), TrackerOptions()
    for point_id in range(3):
        world_map.add_point(point_id, np.zeros(3), -2)
    gone = 0
    for chance in range(options.refind.retire_after_visible):
        found = [0] + ([1] if chance in (3, 7) else []) + ([2] if chance == 5 else [])
        for again in range(3):  # the same place three times: one chance
            here = np.array([0.12 * chance, 0.01 * again, 0.0])
            gone += world_map.retire(np.array([0, 1, 2]), np.array(found), here, options)
        if chance < options.refind.retire_after_visible - 1:
            assert set(world_map.points) == {0, 1, 2}
    assert gone == 1 and world_map.points_retired == 1
    assert set(world_map.points) == {0, 1}


def test_a_loop_closure_moves_only_what_was_made_after_its_reference():
    """Map.correct onto a loop keyframe (``since_m``: its drift, ``after_ns``: when it was
    made): the reference and everything before it stay, the keyframes after it take the
    share of the drift grown since it, and then have only what is left of that drift, and
    are marked as moved; a point whose keyframe is gone takes the share of the first
    keyframe kept after it."""
    world_map = Map()
    for k in range(6):
        kf = world_map.add_keyframe(10 * k, Transform.from_rvec_tvec(np.zeros(3), np.array([k, 0.0, 0.0])),
                                    np.array([k]), np.zeros((1, 2)))
        kf.drift_m = 0.01 * k
        world_map.add_point(k, np.array([k, 1.0, 0.0]), k)
    world_map.add_point(20, np.array([3.5, 1.0, 0.0]), 4)  # born in keyframe 4, culled below
    world_map.add_point(21, np.array([0.5, 1.0, 0.0]), -1)  # born before the reference, its keyframe gone
    del world_map.keyframes[4]
    correction = Transform.from_rvec_tvec(np.array([0.0, 0.0, 0.002]), np.array([0.02, 0.0, 0.0]))
    before = {k: kf.T_world_camera for k, kf in world_map.keyframes.items()}
    points = {k: p.copy() for k, p in world_map.points.items()}
    # the reference: keyframe 1 (drift 0.01, made at 10); now the drift has grown to 0.05
    world_map.correct(correction, grown_m=0.05, since_m=0.01, after_ns=10)
    for k, share in ((0, 0.0), (1, 0.0), (2, 0.25), (3, 0.5), (5, 1.0)):
        part = Transform.from_rvec_tvec(share * correction.rvec(), share * correction.translation)
        np.testing.assert_allclose(world_map.keyframes[k].T_world_camera.matrix(), (part @ before[k]).matrix(),
                                   atol=1e-12)
        np.testing.assert_allclose(world_map.points[k], part.apply(points[k][None])[0], atol=1e-12)
    np.testing.assert_allclose(world_map.keyframes[3].drift_m, 0.01 + 0.5 * 0.02)
    np.testing.assert_allclose(world_map.keyframes[5].drift_m, 0.01)
    np.testing.assert_allclose(world_map.keyframes[1].drift_m, 0.01)  # the reference: as it was
    # what a loop closure moved is no reference for another; the reference and before it are
    assert [kf.loop_moved for kf in world_map.keyframes.values()] == [False, False, True, True, True]
    np.testing.assert_allclose(world_map.points[20], correction.apply(points[20][None])[0], atol=1e-12)
    np.testing.assert_allclose(world_map.points[21], points[21], atol=0)
