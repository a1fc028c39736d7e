"""The tracker's constant-velocity motion model: where it looks for the tracks, and what a
relocalisation does to it (helpers from tests/test_tracking_core.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from test_tracking_core import CAL, SYNC, SyntheticTracks, room_points, run, trolley_path

from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking.tracker import Tracker
from cubeloc.positioning.tracking.types import Tracks


def test_motion_model_predicts_where_tracks_land_after_a_skipped_frame():
    """The front end starts KLT at ``predict_pixels``: after two frames of one step each
    (100 ms) and a gap of two (a frame skipped), the guesses are a small fraction of the
    distance the features moved, for tracks with map points and for those without."""
    poses = trolley_path(50)  # twice the speed of the other tests
    tracker = Tracker(CAL, SYNC)
    source = SyntheticTracks(room_points(12), seed=13, noise_px=0.0)
    run(tracker, source, poses[:21], lambda i: i < 12)
    last = source.tracks(poses[20])  # the live tracks in the last frame stepped (noise-free)
    predicted = tracker.predict_pixels(22 * 100_000_000, last.ids, last.pixels)
    assert predicted is not None and predicted.shape == last.pixels.shape
    source._view(poses[22])
    truth = source._uv[last.ids]
    moved = np.linalg.norm(truth - last.pixels, axis=1)
    missed = np.linalg.norm(truth - predicted, axis=1)
    has_point = np.array([int(t) in tracker.map.points for t in last.ids])
    assert has_point.sum() >= 50 and (~has_point).sum() >= 5  # both kinds are there
    assert np.median(moved) > 15  # a turn: KLT would start ~20 px off (measured 22)
    assert np.median(missed[has_point]) < 0.2 * np.median(moved[has_point])  # measured 2.0 px
    assert np.median(missed[~has_point]) < 0.3 * np.median(moved[~has_point])  # measured 2.7 px
    # nothing in view: coasted for 0.5 s, then lost: nothing to predict, KLT starts where it was
    statuses = [tracker.step(k * 100_000_000, Tracks.empty(), None).result.status for k in range(23, 30)]
    assert statuses[0] == "ok" and statuses[-1] == "lost", statuses
    assert tracker.predict_pixels(30 * 100_000_000, last.ids, last.pixels) is None


def test_a_relocalisation_keeps_the_motion_model():
    """A relocalisation corrects where the camera is, not how it moves: the next frame is
    still predicted one step on (without it KLT starts unguided; at 4.5 deg a frame
    spin_on_axis lost 3/4 of its tracks and then the track)."""
    poses = trolley_path(50)
    tracker = Tracker(CAL, SYNC)
    source = SyntheticTracks(room_points(12), seed=13, noise_px=0.0)
    run(tracker, source, poses[:21], lambda i: i < 12)
    before = tracker.predict(21 * 100_000_000)
    step = tracker.last_pose.inverse() @ before
    # it is moving and turning (measured: 52 mm and 0.4 deg a frame)
    assert np.linalg.norm(step.translation) > 0.02 and np.degrees(step.rotation_angle_to(Transform.identity())) > 0.2
    corrected = Transform(poses[20].rotation, poses[20].translation + [0.004, 0.0, 0.0])
    tracker.relocalised(20 * 100_000_000, corrected, source.tracks(poses[20]), np.eye(6) * 1e-6)
    after = tracker.predict(21 * 100_000_000)
    assert np.allclose((corrected @ step).matrix(), after.matrix(), atol=1e-9)
    # and the next frame's step, measured from the relocalised pose, is its 4 mm
    # correction, not motion: the velocity stays as it was for one more frame
    out = tracker.step(21 * 100_000_000, source.tracks(poses[21]), None)
    assert out.result.estimate is not None
    predicted = tracker.last_pose.inverse() @ tracker.predict(22 * 100_000_000)
    assert np.allclose(predicted.translation, step.translation, atol=1e-9)


def test_two_relocalisations_in_a_row_give_the_motion_model_the_turn_between_them():
    """Lost in a spin, the velocity is none (held steps then make it a standstill); the
    relocaliser finds the camera again, 9 deg a frame on. A relocalised pose that the
    velocity cannot have brought there from the last pose measured (PnP's refusal bound,
    ``max_motion_*``) sets it to the step between them; else the spin's next frame, 9 deg
    from a standstill's prediction, was refused by PnP and found by relocalisation alone,
    frame after frame (narrow lens at 90 deg/s: 30 frames)."""
    tracker = Tracker(CAL, SYNC)
    tracker.initialised = True
    turn = [Transform.from_rvec_tvec(np.array([0.0, np.radians(9.0 * k), 0.0]), np.zeros(3)) for k in range(3)]
    tracks = Tracks(np.arange(30), np.random.default_rng(1).uniform(0, 500, (30, 2)))
    tracker.relocalised(0, turn[0], tracks, np.eye(6) * 1e-6)
    assert tracker.predict(100_000_000) == turn[0]  # nothing measured before it: a standstill
    tracker.relocalised(100_000_000, turn[1], tracks, np.eye(6) * 1e-6)
    assert np.degrees(tracker.predict(200_000_000).rotation_angle_to(turn[2])) < 1e-6


def test_lost_two_relocalisations_in_a_row_measure_the_velocity_between_them():
    """Lost, the velocity is unknown. Two relocalisations a frame apart measure it, even a
    step PnP would take (1 deg and 1 cm): the next frame's KLT starts where the motion puts
    the tracks (unguided, in a turn it lost 92 of the 120 tracks a relocalisation had given
    back: blank_wall). The velocity is as unsure as the two matches over the step."""
    tracker = Tracker(CAL, SYNC)
    tracker.initialised = True
    step = Transform.from_rvec_tvec(np.array([0.0, np.radians(1.0), 0.0]), np.array([0.01, 0.0, 0.0]))
    poses = [Transform.identity(), step, step @ step]
    tracks = Tracks(np.arange(30), np.random.default_rng(1).uniform(0, 500, (30, 2)))
    match = np.diag([1e-6, 4e-6, 9e-6, 1e-8, 1e-8, 1e-8])
    tracker.relocalised(0, poses[0], tracks, match)
    assert tracker.predict(100_000_000) == poses[0]
    tracker.relocalised(100_000_000, poses[1], tracks, match)
    predicted = tracker.predict(200_000_000)
    assert np.degrees(predicted.rotation_angle_to(poses[2])) < 1e-6
    assert np.allclose(predicted.translation, poses[2].translation, atol=1e-9)
    assert np.allclose(tracker.motion.velocity_covariance, 2 * match[:3, :3] / 0.1**2)


def _wheels_under(poses: list[Transform], mount: Transform, as_prior: bool):
    """An odometry prior whose samples are the base's true poses under camera ``poses``
    (one a frame, 100 ms apart, and one more frame ahead)."""
    from cubeloc.positioning.tracking.odometry import OdometryBuffer, OdometryPrior

    buffer = OdometryBuffer()
    for k, pose in enumerate([*poses, poses[-1]]):
        base = pose @ mount.inverse()
        buffer.add(k * 100_000_000, base.translation, base.quaternion(), now_ns=k * 100_000_000)
    return OdometryPrior(buffer, mount, as_prior=as_prior)


def test_each_map_pose_goes_through_the_wheels_relative_motion_factor():
    """With the odometry as the prior, every pose from the map is the relative-motion
    factor's combination of the map's pose and the wheels' motion since the last pose
    (``OdometryPrior.fuse``, measured in tests/test_odometry.py; on full-resolution
    blank_wall it took the prior from 531 to 16.8 mm RMS: python -m bench odometry)."""
    from cubeloc.fakes.odometry import mount_of
    from cubeloc.positioning.tracking.odometry import OdometryPrior

    calls = []

    class Recording(OdometryPrior):
        def fuse(self, tracked, covariance, last, t0_ns, t1_ns):
            fused = super().fuse(tracked, covariance, last, t0_ns, t1_ns)
            calls.append((tracked, last, t0_ns, t1_ns, fused[0]))
            return fused

    poses = trolley_path(50)
    tracker = Tracker(CAL, SYNC)
    source = SyntheticTracks(room_points(12), seed=13, noise_px=0.3)
    run(tracker, source, poses[:21], lambda i: i < 12)
    xyz, quaternion = mount_of(poses[0])
    wheels = _wheels_under(poses[:23], Transform.from_quaternion(xyz, quaternion), True)
    tracker.odometry = Recording(wheels.buffer, wheels.T_base_camera, as_prior=True)
    last = tracker.last_pose
    out = tracker.step(21 * 100_000_000, source.tracks(poses[21]), None)
    assert len(calls) == 1
    tracked, given_last, t0, t1, fused = calls[0]
    assert given_last is last and (t0, t1) == (20 * 100_000_000, 21 * 100_000_000)
    assert fused is not tracked and out.result.estimate.T_world_camera is fused


def test_a_position_held_on_rays_alone_claims_no_more_than_the_robot_s_motion_allows():
    """Held with no map point in view while the robot drives on (0.3 m/s among features
    20-40 m away, each frame's fresh tracks born on the held pose, as the tracker adds
    them): the rays keep agreeing with a position that stays behind, so nothing measures
    it. Its covariance must grow as the motion allows (the speed when the hold began, and
    1 m/s^2 of change): every held pose inside 3 sigma. The old 5 cm/s growth claimed
    0.16 m at 0.88 m off (NEES 30)."""
    from cubeloc.positioning.camera_model import project_normalised
    from cubeloc.positioning.tracking.hold import RayHold
    from cubeloc.positioning.tracking.map import Map
    from cubeloc.positioning.tracking.motion import MotionModel
    from cubeloc.positioning.tracking.options import TrackerOptions

    fx = 800.0
    rng = np.random.default_rng(3)
    points = rng.uniform([-8, -4, 20], [8, 4, 40], (300, 3))

    def seen(pose: Transform) -> np.ndarray:
        return project_normalised(pose.inverse(), points)[0] + rng.normal(0, 0.3 / fx, (300, 2))

    hold, motion = RayHold(TrackerOptions(), fx), MotionModel(TrackerOptions())
    last, last_stamp, ids = Transform.identity(), 0, np.arange(300)
    hold.rebase(last, ids, seen(last))
    nees = []
    for k in range(1, 31):  # 3 s at 10 fps
        truth = Transform(np.eye(3), np.array([0.0, 0.0, 0.03 * k]))
        xn = seen(truth)
        # the motion model's first prediction carries the speed it had; later ones the held poses'
        prediction = Transform(np.eye(3), np.array([0.0, 0.0, 0.03])) if k == 1 else last
        motion.last, motion.stamp = last, last_stamp
        held = hold.hold(k * 100_000_000, motion, prediction, Tracks(ids, xn * fx), xn, Map())
        assert held is not None, k
        last, last_stamp = held[0], k * 100_000_000
        error = last.translation - truth.translation
        nees.append(float(error @ np.linalg.solve(held[1][:3, :3], error)))
        ids = np.arange(300) + 1000 * k
        hold.rebase(None, ids, xn)
        hold.add(last, ids, xn)
    assert np.linalg.norm(last.translation - truth.translation) > 0.5  # the position really was not measured
    assert max(nees) < 14.16, nees


def test_a_hold_is_as_unsure_as_the_pose_it_began_on():
    """Rays born on a far target pose (0.18 m off, and saying so: 0.1 m a side), then held
    while the robot stands still: the held position stays where that pose put it, so it
    must claim that pose's uncertainty as well as its own. Each held pose inside 3 sigma;
    without the base pose's covariance the same poses reach a NEES of 77."""
    from cubeloc.positioning.camera_model import project_normalised
    from cubeloc.positioning.tracking.hold import RayHold
    from cubeloc.positioning.tracking.map import Map
    from cubeloc.positioning.tracking.motion import MotionModel
    from cubeloc.positioning.tracking.options import TrackerOptions

    fx = 600.0
    rng = np.random.default_rng(5)
    points = rng.uniform([-3, -2, 2], [3, 2, 6], (200, 3))
    truth = Transform.identity()
    xn = project_normalised(truth.inverse(), points)[0]
    base = Transform(np.eye(3), np.array([0.12, -0.08, 0.10]))  # where the target pose put it
    base_covariance = np.diag([0.1**2] * 3 + [0.002**2] * 3)
    hold, motion = RayHold(TrackerOptions(), fx), MotionModel(TrackerOptions())
    ids = np.arange(200)
    hold.rebase(base, ids, xn, base_covariance)
    last, nees = base, []
    for k in range(1, 11):  # 1 s at 10 fps
        seen = xn + rng.normal(0, 0.3 / fx, xn.shape)
        motion.last, motion.stamp = last, (k - 1) * 100_000_000
        held = hold.hold(k * 100_000_000, motion, last, Tracks(ids, seen * fx), seen, Map())
        assert held is not None, k
        last = held[0]
        error = last.translation - truth.translation
        assert np.linalg.norm(error) > 0.15  # the hold stays where the base put it
        nees.append(float(error @ np.linalg.solve(held[1][:3, :3], error)))
        hold.rebase(None, ids, seen)
    assert max(nees) < 14.16, nees


def test_a_velocity_is_as_unsure_as_the_poses_it_was_measured_between():
    """The step from a held pose 1.6 m off (and saying so) to a target pose 30 ms later is
    a velocity of 48 m/s that the robot, standing still, never had. A coast on it one frame
    later lands 1.6 m off: its covariance must say so (it claimed 10 mm, a NEES of ~23000).
    Between two poses a millimetre sure, the same coast claims under a centimetre."""
    from cubeloc.positioning.tracking.motion import MotionModel
    from cubeloc.positioning.tracking.options import TrackerOptions

    frame_ns = 33_000_000
    motion = MotionModel(TrackerOptions())
    held = Transform(np.eye(3), np.array([1.6, 0.0, 0.0]))
    motion.update(held, 0, own=np.eye(6) * 1.6**2, held=True)
    motion.update(Transform.identity(), frame_ns, own=np.eye(6) * 0.1**2)  # the target: the truth, 0.1 m unsure
    prediction = motion.predict(2 * frame_ns)
    error = prediction.translation
    assert np.linalg.norm(error) > 1.5
    _, covariance = motion.coast(prediction, frame_ns / 1e9)
    assert error @ np.linalg.solve(covariance[:3, :3], error) < 14.16

    sure = MotionModel(TrackerOptions())
    sure.update(Transform.identity(), 0, own=np.eye(6) * 0.001**2)
    sure.update(Transform(np.eye(3), np.array([0.0, 0.0, 0.01])), frame_ns, own=np.eye(6) * 0.001**2)
    _, covariance = sure.coast(sure.predict(2 * frame_ns), frame_ns / 1e9)
    assert np.sqrt(np.max(np.linalg.eigvalsh(covariance[:3, :3]))) < 0.012


def test_a_target_pose_too_uncertain_to_anchor_is_published_but_neither_moves_nor_maps():
    """Lost, the cube comes back too far away to anchor: its poses, each 10 cm off on its
    own, go out (with their covariance) but make no keyframe, and the steps between them are
    not taken for the camera's motion: the motion model does not run off after them."""
    poses = trolley_path(80, turn_at=1e6)  # the cube in view throughout
    source = SyntheticTracks(room_points(3), seed=3)
    tracker = Tracker(CAL, SYNC)
    rng = np.random.default_rng(5)
    try:
        run(tracker, source, poses[:50], lambda i: i < 20, blank=lambda i: i >= 40)  # lost from ~46 on
        assert tracker.lost
        keyframes = len(tracker.map.keyframes)
        uncertain = np.diag([0.05**2] * 3 + [0.01**2] * 3)
        for i in range(50, 60):
            seen = source.target(poses[i])
            assert seen is not None
            off = Transform(seen.T_world_camera.rotation, seen.T_world_camera.translation + rng.normal(0, 0.1, 3))
            out = tracker.step(i * 100_000_000, source.tracks(poses[i]),
                               replace(seen, T_world_camera=off, covariance=uncertain))
            assert out.result.estimate is not None and out.result.estimate.planes == seen.planes
            assert not out.keyframe
        assert len(tracker.map.keyframes) == keyframes
        predicted = tracker.predict(60 * 100_000_000)
        assert np.linalg.norm(predicted.translation - tracker.last_pose.translation) < 0.05  # a trolley's frame
    finally:
        tracker.close()
