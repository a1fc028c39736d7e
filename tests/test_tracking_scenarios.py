"""The tracker through the motions a robot really makes (fakes/scenarios.py), at half
resolution (640x512) and with bundle adjustment in the frame loop, so every run is the
same. Each test asserts the issue's goals with a margin below what was measured; the
full-resolution figures, and today's tracker side by side, come from ``python -m bench
scenarios``.

The previous tracker (commit 9580d93) on these sequences, for the record: turn_after_init
13 % of frames with a pose, spin_on_axis 40 % (the whole turn lost), passers_by 98 %.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from helpers import half_resolution

from cubeloc.daemon.replay import track_sequence
from cubeloc.fakes.lenses import lens_calibration
from cubeloc.fakes.sequence import write_synthetic_sequence
from cubeloc.positioning.estimator import PoseSource, PoseState
from cubeloc.positioning.evaluation import score_estimates
from cubeloc.positioning.tracking.processor import ProcessorOptions
from cubeloc.positioning.trajectory_io import read_tum

SYNC = ProcessorOptions.in_frame_loop()


def replay(tmp_path_factory, name: str, seconds: float | None = None, seed: int = 11, calibration=None,
           poses=None, effects=None):
    """Render scenario ``name`` at half resolution (or through ``calibration``; ``poses`` and
    ``effects`` in place of the scenario's) and run the tracker over it: (score, results, truth)."""
    calibration = calibration or half_resolution()
    out = tmp_path_factory.mktemp(name) / name
    write_synthetic_sequence(out, name, seconds=seconds, seed=seed, calibration=calibration, poses=poses,
                             effects=effects)
    truth = read_tum(out / "groundtruth.tum")
    results = track_sequence(out, calibration).results
    return score_results(results, truth), results, truth


def score_results(results, truth):
    """The score of a run's results (one per frame) against the ground truth."""
    return score_estimates(truth, [r.estimate for r in results])


def tracking_score(results, truth):
    """The score of the map's poses alone (the target's own single-frame poses left out)."""
    return score_estimates(truth, [None if r.estimate is None or r.estimate.state is PoseState.TARGET
                                   else r.estimate for r in results])


def test_a_brisk_turn_right_after_initialisation_keeps_the_map_round_the_room(tmp_path_factory):
    """The scale drifts on the lap, which looks ahead along the motion (little parallax),
    and by how much depends on the noise and the texture, so the bounds come from 16
    renders, not from this one: noise seeds 2-8 and 11, the room's texture as OpenCV 5.0.0
    and 5.1.0 draw it (anti-aliased shapes changed). In all 16: every frame with a pose;
    RMS 5.8-30.8 mm (median 21.8), max 9.0-47.5 mm, the error up to 2.7 % of the distance
    from the start; back on the cube 0.6-1.1 mm. This render (seed 11, constraints.txt's
    OpenCV): RMS 7.6, max 11.2 mm. Full resolution, 6 renders: RMS 1.8-13.3 mm (bench seeds)."""
    score, results, truth = replay(tmp_path_factory, "turn_after_init", seconds=75.0)
    assert score.coverage >= 0.99, score
    assert score.max_m < 0.060 and score.rmse_m < 0.040, score
    back = results[-1].estimate
    assert back.state is PoseState.TARGET
    assert np.linalg.norm(back.T_world_camera.translation - truth[-1].T_world_camera.translation) < 0.003
    tracked = tracking_score(results, truth)
    assert tracked.with_pose > 600 and tracked.consistent >= 0.97 and tracked.beyond_5_sigma == 0, tracked
    assert tracked.without_covariance == 0


@pytest.mark.parametrize("name, rmse_mm", [("spin_in_place", 8.0), ("spin_in_place_fast", 8.0)])
def test_turning_on_the_spot_with_the_camera_ahead_of_the_axis_keeps_the_map(tmp_path_factory, name, rmse_mm):
    """45 deg/s at 10 fps and 90 deg/s at 30 fps, 0.2 m lever arm, right after
    initialisation. Measured: 100 %, 3.1 and 2.8 mm RMS."""
    score, results, truth = replay(tmp_path_factory, name, seconds=14.0 if name == "spin_in_place" else 10.0)
    assert score.coverage >= 0.99 and score.max_m < 0.030 and score.rmse_m < rmse_mm / 1000, score
    tracked = tracking_score(results, truth)
    assert tracked.consistent >= 0.97 and tracked.beyond_5_sigma == 0, tracked


def test_behind_a_wide_lens_the_cube_anchors_the_map_before_the_turn(tmp_path_factory):
    """Behind a wide lens (f 450 px, k1 -0.25: fakes.lenses) the library's corners are
    0.4-0.55 px off a right pose; judged against the paper camera's sharp 0.05 px, every
    cube pose claimed 18-25 mm, none anchored the map, and the spin right after found no
    map (55 % of frames with a pose). Measured: 100 %, 5.5 mm RMS, 10 mm max."""
    score, results, truth = replay(tmp_path_factory, "spin_in_place", seconds=14.0,
                                   calibration=lens_calibration("wide"))
    assert score.coverage >= 0.99 and score.max_m < 0.030 and score.rmse_m < 0.010, score
    tracked = tracking_score(results, truth)
    assert tracked.consistent >= 0.9 and tracked.beyond_5_sigma <= 5, tracked


def test_behind_a_wide_lens_agile_swings_start_the_map_on_the_poses_the_cube_gives(tmp_path_factory):
    """Behind the wide lens the small, swinging cube's poses are 5-10 mm sure: none met the
    5 mm that anchors a keyframe, so the map never started (12 s: 80 % of frames with a
    pose, the poses held on rays meanwhile up to 0.42 m off). A map may now start on poses
    up to 10 mm sure (init.max_position_std_m). Measured: 100 %, 3.4 mm RMS, 8.4 mm max,
    every pose inside 3 sigma (python -m bench intrinsics)."""
    score, results, truth = replay(tmp_path_factory, "agile", seconds=12.0, calibration=lens_calibration("wide"))
    assert score.coverage >= 0.99 and score.max_m < 0.030 and score.rmse_m < 0.010, score
    assert sum(r.estimate is not None and r.estimate.state is PoseState.TRACKING for r in results) >= 20
    tracked = tracking_score(results, truth)
    assert tracked.consistent >= 0.95 and tracked.beyond_5_sigma == 0, tracked


def test_a_brisk_spin_with_motion_blur_keeps_the_pose(tmp_path_factory):
    """120 deg/s at 10 fps (12 deg a frame) with 8 ms exposure (~1 deg of blur). Measured
    over noise seeds 2, 3, 5, 7, 11: every frame with a pose, 10.3-12.8 mm RMS, 28-35 mm
    max (the two turns drift up to 0.7 deg, inside the covariance), back on the cube within
    1 mm, every pose inside 3 sigma. Other rates and lenses: python -m bench turns."""
    score, results, truth = replay(tmp_path_factory, "spin_brisk")
    assert score.coverage >= 0.99 and score.max_m < 0.050 and score.rmse_m < 0.020, score
    last = results[-1].estimate
    assert np.linalg.norm(last.T_world_camera.translation - truth[-1].T_world_camera.translation) < 0.003
    tracked = tracking_score(results, truth)
    assert tracked.consistent >= 0.95 and tracked.beyond_5_sigma == 0, tracked


def test_behind_a_narrow_lens_a_brisk_spin_refuses_a_pose_turned_far_from_the_prediction(tmp_path_factory):
    """Behind the narrow lens (HFOV 29 deg) at 90 deg/s and 10 fps, where the second turn
    came round to the first turn's points (drifted 1 deg), PnP took a pose 7.7 deg from the
    motion model's prediction and the track went on 16 deg and 0.7 m off (254 mm RMS). A pose
    turned more than motion.max_deg (5) from the prediction is refused now. Measured: 100 %,
    64 mm RMS, 160 mm max; 52 mm, 130 mm since the edge alignment's coarse first iteration
    (the drift itself is not solved: 64-76 % inside 3 sigma)."""
    from cubeloc.fakes.scenarios import Effects
    from cubeloc.fakes.trajectories import spin_trajectory

    score, results, truth = replay(tmp_path_factory, "spin_in_place", calibration=lens_calibration("narrow"),
                                   poses=spin_trajectory(90.0, 14.0, 10.0), effects=Effects(exposure_s=0.008))
    assert score.coverage >= 0.99 and score.max_m < 0.3 and score.rmse_m < 0.12, score
    worst_turn = max(np.degrees(r.estimate.T_world_camera.rotation_angle_to(t.T_world_camera))
                     for r, t in zip(results, truth, strict=True) if r.estimate is not None)
    assert worst_turn < 5.0


def test_pure_rotation_on_the_axis_holds_the_orientation_throughout_and_the_position(tmp_path_factory):
    """Nothing can be triangulated: the orientation comes from the tracks' rays and the
    position is held (measured: 100 % of frames, 6.7 mm RMS, orientation within 0.1 deg)."""
    score, results, truth = replay(tmp_path_factory, "spin_on_axis", seconds=14.0)
    assert score.coverage >= 0.95 and score.max_m < 0.030, score
    held = [r for r in results if r.estimate is not None and r.estimate.source is PoseSource.HELD]
    assert len(held) >= 40 and all(r.detail.startswith("held") for r in held)
    for r, t in zip(results, truth, strict=True):
        if r.estimate is not None:
            assert np.degrees(r.estimate.T_world_camera.rotation_angle_to(t.T_world_camera)) < 0.5
    tracked = tracking_score(results, truth)
    assert tracked.consistent >= 0.97 and tracked.beyond_5_sigma == 0, tracked


def test_passers_by_neither_enter_the_map_nor_lose_the_pose(tmp_path_factory):
    """Three person-sized panels walk across at 0.6-1.8 m, the first over the cube while
    the tracker initialises. Measured: 100 % of frames, 2.6 mm RMS, 12 mm max."""
    score, results, truth = replay(tmp_path_factory, "passers_by", seconds=24.0)
    assert score.coverage >= 0.99 and score.max_m < 0.030 and score.rmse_m < 0.005, score
    tracked = tracking_score(results, truth)
    assert tracked.consistent >= 0.97 and tracked.beyond_5_sigma == 0, tracked


def test_agile_swings_with_blur_and_exposure_steps_keep_the_pose(tmp_path_factory):
    """30 fps, +-50 deg yaw swings, 4 ms exposure integrated over the motion, gain steps.
    Measured at half resolution: 100 %, 5.7 mm RMS, 12 mm max (full resolution: 2.7 mm).
    The covariance is short of the 97 % goal here: 96.4 % of the map's poses inside their
    3-sigma ellipsoid (the map, anchored on blurred target views at the image edge, is
    off by more than it agreed with the target); 99.9 % at full resolution (bench)."""
    score, results, truth = replay(tmp_path_factory, "agile", seconds=12.0)
    assert score.coverage >= 0.99 and score.max_m < 0.030 and score.rmse_m < 0.008, score
    tracked = tracking_score(results, truth)
    assert tracked.consistent >= 0.95 and tracked.beyond_5_sigma == 0, tracked


def test_laps_of_the_room_close_the_loop_on_the_first(tmp_path_factory):
    """Three laps round the cube (the ``laps`` scenario, 150 s at half resolution, ~50 m,
    the cube out of view for ~140 s): when the view comes round to the places of the first
    lap, several matches against their keyframes agree on how far the map has drifted, the
    map being tracked is moved onto them, and from then on their points are followed as the
    reference. Measured with noise seed 0: 2 closures, the first bringing the pose nearer
    the truth, the second (on the third lap) 1-2 mm further; RMS 9.4 mm, the laps 10.3 /
    10.8 / 7.7 mm; without following the places 15.0 mm, the laps 10.4 / 16.0 / 18.4 mm;
    without loop closure 20.5 mm, the laps 10.4 / 21.4 / 26.3 mm (at 1280x1024:
    docs/benchmarks.md "laps"). The same code on another CPU (AVX-512 FP16: other rounding
    in NumPy's and OpenBLAS's kernels) closes once: RMS 11.2 mm, the laps 10.4 / 12.1 / 12.0.
    So the goal of the last lap no worse than the first is not asserted here: it is met on
    some runs and not others (the laps bench reports it per seed), where the run within
    1.5 times the first lap holds on all of them."""
    out = tmp_path_factory.mktemp("laps") / "laps"
    write_synthetic_sequence(out, "laps", seconds=150.0, seed=0, calibration=half_resolution())
    truth = read_tum(out / "groundtruth.tum")
    options = replace(SYNC, tracker=replace(SYNC.tracker, loop=replace(SYNC.tracker.loop, enabled=True)))
    errors, nearer, closed = [], [], [0]

    def closures(frame, image, processor) -> None:
        result, tracker = frame.result, processor.tracker
        where = truth[frame.seq].T_world_camera.translation
        assert result.estimate is not None, (frame.seq, result.status, result.detail)
        errors.append(np.linalg.norm(result.estimate.T_world_camera.translation - where))
        if tracker.loops_closed > closed[0]:
            closed[0] = tracker.loops_closed
            _, before, after = tracker.last_closure
            nearer.append(np.linalg.norm(after.translation - where) < np.linalg.norm(before.translation - where))

    track_sequence(out, half_resolution(), options=options, on_frame=closures)
    closed = closed[0]
    errors, seconds = np.array(errors), np.arange(len(errors)) / 10.0
    laps = [float(np.sqrt(np.mean(errors[(seconds >= a) & (seconds < b)] ** 2)))
            for a, b in ((3.0, 49.3), (49.3, 95.7), (95.7, 142.0))]  # the laps' bounds at 150 s
    run = float(np.sqrt(np.mean(errors**2)))
    assert closed >= 1 and nearer[0], nearer
    # the trusted-pose issue's goal: the run at most 1.5x the first lap
    assert run <= 1.5 * laps[0] and run < 0.013, (run, laps)
