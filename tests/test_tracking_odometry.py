"""Wheel odometry through a blank wall (fakes/scenarios.py ``blank_wall``, half resolution,
bundle adjustment in the frame loop): the same frames with and without simulated odometry
(fakes/odometry.py: 50 Hz, 30 ms late, 1.5 % scale, 1 % turn, 0.2 deg/s drift)."""

from __future__ import annotations

import numpy as np
from helpers import half_resolution
from test_tracking_scenarios import SYNC, score_results

from cubeloc.daemon.replay import OdometryReplay, track_sequence
from cubeloc.fakes.odometry import mount_of, simulate_odometry
from cubeloc.fakes.sequence import write_synthetic_sequence
from cubeloc.fakes.trajectories import make_trajectory
from cubeloc.positioning.estimator import PoseSource, PoseState
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.target import make_cube
from cubeloc.positioning.tracking.odometry import OdometryBuffer, OdometryPrior
from cubeloc.positioning.trajectory_io import read_tum

SECONDS = 26.0


def _run(sequence, truth, odometry_rows, mount):
    buffer = OdometryBuffer()
    rows = [(r["arrival_ns"], r["stamp_ns"], r["position"], r["orientation"]) for r in odometry_rows or []]
    results = track_sequence(sequence, half_resolution(), make_cube(), SYNC,
                             odometry_prior=None if odometry_rows is None else OdometryPrior(buffer, mount),
                             odometry=OdometryReplay(rows, buffer)).results
    return score_results(results, truth), results


def test_wheel_odometry_carries_the_pose_across_a_blank_wall(tmp_path_factory):
    """Measured: vision alone 85.4 % of frames with a pose (38 frames lost at the wall), RMS
    6.1 mm, max 16.7; with the odometry as the bridge (the default) 100 %, RMS 6.6 mm, max
    16.7, every pose inside its 3-sigma ellipsoid; and where vision had a pose, the same pose:
    the bridge publishes, it does not touch the map."""
    sequence = tmp_path_factory.mktemp("blank_wall") / "blank_wall"
    write_synthetic_sequence(sequence, "blank_wall", seconds=SECONDS, seed=11, calibration=half_resolution())
    truth = read_tum(sequence / "groundtruth.tum")
    xyz, quaternion = mount_of(make_trajectory("blank_wall", SECONDS)[0].T_world_camera)
    mount = Transform.from_quaternion(xyz, quaternion)
    rows = simulate_odometry("blank_wall", SECONDS, mount)
    vision, alone = _run(sequence, truth, None, mount)
    both, bridged = _run(sequence, truth, rows, mount)
    assert vision.coverage < 0.9  # the wall does take the pose away without it
    assert both.coverage == 1.0 and both.longest_gap_frames == 0, both
    assert both.rmse_m < 0.025 and both.max_m < 0.060, both
    assert both.consistent >= 0.97 and both.beyond_5_sigma == 0, both
    for a, b in zip(alone, bridged, strict=True):
        if a.estimate is not None:
            assert b.status != "bridged" and b.estimate.source is a.estimate.source is not PoseSource.ODOMETRY
            np.testing.assert_allclose(b.estimate.T_world_camera.matrix(), a.estimate.T_world_camera.matrix(), atol=1e-9)
        else:
            assert b.status in ("bridged", "initialising") or b.estimate is not None
        if b.status == "bridged":  # the wheels alone: a tracking pose that says so
            assert b.estimate.source is PoseSource.ODOMETRY and b.estimate.state is PoseState.TRACKING
    # the bridge gives every frame vision lost at the wall, and nothing else
    lost = sum(a.status == "lost" for a in alone)
    assert lost >= 30 and sum(r.status == "bridged" for r in bridged) == lost
