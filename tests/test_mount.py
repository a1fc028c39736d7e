"""``cubeloc calibrate-mount``: the camera's mount from a drive with wheel odometry
(positioning/mount.py), on simulated figure-eight drives with known mounts, wheels 1.5 %
long and 1 % over-turning, a heading drift of 0.2 deg/s and a slip, and camera poses with
1 mm and 0.05 deg of noise."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cubeloc.daemon.cli import main
from cubeloc.daemon.config import FramesConfig, tomllib
from cubeloc.daemon.messages import encode, pose_payload
from cubeloc.fakes.odometry import camera_on_base, figure_eight, wheel_odometry, write_odometry
from cubeloc.fakes.trajectories import EPOCH_NS
from cubeloc.positioning.estimator import PoseEstimate, PoseSource, PoseState
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.mount import MountError, make_pairs, solve_mount
from cubeloc.positioning.target import default_cube_yaml, make_cube
from cubeloc.positioning.tracking.odometry import OdometryBuffer

OPTICAL = Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix()  # z ahead, x right, on a base x ahead
FLOOR_Z = -make_cube().cube.side_m / 2  # the cube's bottom face: the floor of its frame
POSE_SIGMA_M, POSE_SIGMA_RAD = 0.001, math.radians(0.05)


def mount(x, y, z, yaw_deg, pitch_deg) -> Transform:
    rotation = Rotation.from_euler("zy", [yaw_deg, pitch_deg], degrees=True).as_matrix() @ OPTICAL
    return Transform(rotation, np.array([x, y, z]))


def drive(X: Transform, seconds=60.0, fps=10.0, seed=0, base=None, slip=(23.0, 0.03), **wheel_errors):
    """Camera poses (stamp, noisy T_world_camera, covariance) at ``fps`` and odometry rows at
    50 Hz of a base driving figure-eights (``base``: another planar path maker)."""
    base = base or (lambda t: figure_eight(t, centre=(1.5, 0.0), size_m=1.2, period_s=20.0))
    rng = np.random.default_rng(seed)
    odometry_times = 0.007 + np.arange(int(seconds * 50)) / 50
    rows = wheel_odometry(odometry_times, base(odometry_times), slip=slip, seed=seed, **wheel_errors)
    camera_times = np.arange(int(seconds * fps)) / fps
    camera = []
    for t, T in zip(camera_times, camera_on_base(base(camera_times), X, FLOOR_Z), strict=True):
        noisy = Transform(Rotation.from_rotvec(rng.normal(0, POSE_SIGMA_RAD, 3)).as_matrix() @ T.rotation,
                          T.translation + rng.normal(0, POSE_SIGMA_M, 3))
        camera.append((EPOCH_NS + int(round(t * 1e9)), noisy, True))
    return camera, rows


def buffer_of(rows) -> OdometryBuffer:
    buffer = OdometryBuffer(capacity=len(rows))
    for row in rows:
        buffer.add(row["stamp_ns"], row["position"], row["orientation"])
    return buffer


MOUNTS = [(0.0, 0.0, 1.0, 0.0, -20.0), (0.2, 0.0, 0.5, 0.0, 0.0), (-0.3, 0.15, 0.8, 180.0, 10.0),
          (0.4, -0.2, 0.3, 90.0, -30.0), (0.1, 0.3, 0.6, -135.0, 0.0)]


@pytest.mark.parametrize("seed, placement", list(enumerate(MOUNTS)))
def test_the_mount_comes_within_5_mm_and_0_2_deg_and_says_so(seed, placement):
    X = mount(*placement)
    camera, rows = drive(X, seed=seed)
    result = solve_mount(make_pairs(camera, buffer_of(rows).pose_at), height_m=placement[2])
    found = result.T_base_camera
    error_m = found.translation - X.translation
    error_rad = Rotation.from_matrix(found.rotation @ X.rotation.T).as_rotvec()
    assert np.linalg.norm(error_m) < 0.005 and np.degrees(np.linalg.norm(error_rad)) < 0.2, (error_m, error_rad)
    sigma = np.sqrt(np.diag(result.covariance))
    # honest: each observed component within 4 of its standard deviations
    assert np.all(np.abs(error_m[:2]) < 4 * sigma[:2]) and np.all(np.abs(error_rad) < 4 * sigma[3:]), (error_m,
                                                                                                          error_rad, sigma)
    # the wheels' own errors are solved, not taken into the mount
    assert abs(result.distance_scale - 1.015) < 0.003 and abs(result.turn_scale - 1.01) < 0.003
    assert all(result.observed.values())


def test_without_a_height_the_lever_z_is_reported_unobserved():
    camera, rows = drive(mount(0.2, 0.1, 0.7, 30.0, -10.0), seed=7)
    result = solve_mount(make_pairs(camera, buffer_of(rows).pose_at))
    assert not result.observed["z"] and result.T_base_camera.translation[2] == 0.0
    assert math.sqrt(result.covariance[2, 2]) >= 1.0
    assert abs(result.T_base_camera.translation[0] - 0.2) < 0.005


def test_a_drive_without_turns_is_refused_with_what_to_drive():
    line = lambda t: [(0.5 + 0.3 * float(s), 0.0, 0.0) for s in t]  # noqa: E731
    camera, rows = drive(mount(0.2, 0.0, 0.5, 0.0, 0.0), base=line, slip=None)
    with pytest.raises(MountError, match="too little rotation.*figure-eights"):
        solve_mount(make_pairs(camera, buffer_of(rows).pose_at))


def test_odometry_that_does_not_move_is_refused():
    camera, rows = drive(mount(0.2, 0.0, 0.5, 0.0, 0.0))
    for row in rows:
        row["position"], row["orientation"] = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]
    with pytest.raises(MountError, match="odometry does not move"):
        solve_mount(make_pairs(camera, buffer_of(rows).pose_at))


def test_odometry_in_the_wrong_units_is_refused():
    camera, rows = drive(mount(0.2, 0.0, 0.5, 0.0, 0.0))
    for row in rows:  # millimetres
        row["position"] = [1000 * v for v in row["position"]]
    with pytest.raises(MountError, match="disagree in scale"):
        solve_mount(make_pairs(camera, buffer_of(rows).pose_at))


def test_odometry_of_another_drive_is_refused():
    camera, _ = drive(mount(0.2, 0.0, 0.5, 0.0, 0.0))
    other = lambda t: figure_eight(t + 7.0, centre=(1.5, 0.0), size_m=0.8, period_s=13.0)  # noqa: E731
    _, rows = drive(mount(0.2, 0.0, 0.5, 0.0, 0.0), base=other)
    with pytest.raises(MountError, match="disagree"):
        solve_mount(make_pairs(camera, buffer_of(rows).pose_at))


def write_drive(tmp_path, X):
    camera, rows = drive(X, seed=3)
    poses = tmp_path / "drive.jsonl"
    covariance = np.diag([POSE_SIGMA_M**2] * 3 + [POSE_SIGMA_RAD**2] * 3)
    lines = [encode(pose_payload(i, stamp, PoseEstimate(T, PoseState.TRACKING, 0, (), 0.0, covariance,
                                                        PoseSource.MAP)))
             for i, (stamp, T, _) in enumerate(camera)]
    # held and odometry-bridged poses are not the camera's measurement: a wild one is left out
    wild = Transform(np.eye(3), np.array([9.0, 9.0, 9.0]))
    lines.append(encode(pose_payload(len(lines), camera[-1][0] + 1, PoseEstimate(
        wild, PoseState.TRACKING, 0, (), 0.0, np.eye(6), PoseSource.HELD))))
    poses.write_bytes(b"\n".join(lines) + b"\n")
    odometry = tmp_path / "odom.jsonl"
    write_odometry(odometry, rows)
    return poses, odometry


def test_the_command_prints_and_writes_the_frames_table_with_the_height_from_the_cube(tmp_path, capsys):
    X = mount(-0.25, 0.1, 0.62, 180.0, -15.0)
    poses, odometry = write_drive(tmp_path, X)
    target = tmp_path / "cube.yaml"
    target.write_text(default_cube_yaml())
    out = tmp_path / "mount.toml"
    assert main(["calibrate-mount", "--poses", str(poses), "--odometry", str(odometry), "--target", str(target),
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "[frames.base_from_camera]" in printed and "above the cube's floor" in printed
    assert main(["calibrate-mount", "--poses", str(poses), "--odometry", str(odometry), "--out", str(out)]) == 2
    assert "already exists; use --force" in capsys.readouterr().err  # and the file is the first run's
    placement = FramesConfig(**tomllib.loads(out.read_text())["frames"]).base_from_camera
    found = placement.transform()
    assert np.linalg.norm(found.translation - X.translation) < 0.005
    assert np.degrees(found.rotation_angle_to(X)) < 0.2


def test_the_command_without_a_height_says_z_is_not_observed(tmp_path, capsys):
    poses, odometry = write_drive(tmp_path, mount(0.1, 0.0, 0.5, 0.0, 0.0))
    assert main(["calibrate-mount", "--poses", str(poses), "--odometry", str(odometry)]) == 0
    captured = capsys.readouterr()
    assert "NOT OBSERVED" in captured.out and "not observed" in captured.err


@pytest.mark.parametrize("change, message", [
    (lambda p, o: p.write_text("{}\n"), "drive.jsonl:1: not a cubeloc.pose/3"),
    (lambda p, o: o.write_text("nonsense\n"), "odom.jsonl:1: not a cubeloc.odometry/1"),
    (lambda p, o: o.write_text(o.read_text().replace("1700000", "1600000")), "do not cover any pose"),
])
def test_bad_input_gets_one_line_and_exit_2(tmp_path, capsys, change, message):
    poses, odometry = write_drive(tmp_path, mount(0.1, 0.0, 0.5, 0.0, 0.0))
    change(poses, odometry)
    assert main(["calibrate-mount", "--poses", str(poses), "--odometry", str(odometry)]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_the_maps_scale_is_solved_where_the_target_measured_part_of_the_drive():
    """Away from the cube the camera's metric is the map's, here 2 % large; where the cube
    measured enough of the drive (its first 20 s) to pin the wheels' scale, the map's is
    solved and the lever is not stretched by it (0.4 m lever: 8 mm if it were)."""
    X = mount(0.35, -0.2, 0.6, 90.0, -10.0)
    camera, rows = drive(X, seed=11)
    start = next(k for k, (stamp, _, _) in enumerate(camera) if stamp - camera[0][0] >= 20e9)
    origin = camera[start][1].translation
    camera = camera[:start] + [(stamp, Transform(T.rotation, origin + 1.02 * (T.translation - origin)), False)
                               for stamp, T, _ in camera[start:]]
    result = solve_mount(make_pairs(camera, buffer_of(rows).pose_at), height_m=0.6)
    assert result.map_scale is not None and abs(result.map_scale - 1.02) < 0.003, result.map_scale
    assert np.linalg.norm(result.T_base_camera.translation - X.translation) < 0.003
    assert abs(result.distance_scale - 1.015) < 0.003
