"""The randomized family of scenes, robots and motions (fakes/family.py): each seed is one
case, drawn within the bounds the family promises, the same every time, and its flags say
where a camera alone cannot know the position."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from cubeloc.drivers.sequence import read_image, read_sequence_index
from cubeloc.fakes.family import (
    BLANK_VIEW_SHARE,
    CUBE_HALF,
    RESOLUTIONS,
    _textured_share,
    base_from_camera,
    make_case,
    render_case,
    wheel_odometry,
)
from cubeloc.fakes.room import Room
from cubeloc.fakes.trajectories import camera_from_yaw_pitch

SEEDS = (0, 3, 6, 13)  # a hall, two corridors, a room (the draws of the family as it is)


@pytest.fixture(scope="module")
def cases():
    return {seed: make_case(seed) for seed in SEEDS}


def _camera_motion(case):
    times = (np.array([p.stamp_ns for p in case.poses]) - case.poses[0].stamp_ns) / 1e9
    poses = [p.T_world_camera for p in case.poses]
    dt = np.diff(times)
    rate = np.array([np.degrees(a.rotation_angle_to(b)) for a, b in zip(poses, poses[1:], strict=False)]) / dt
    positions = np.array([p.translation for p in poses])
    return times, positions, rate


def test_a_seed_is_one_case_and_another_seed_another(cases):
    again = make_case(SEEDS[0])
    assert again.render_key() == cases[SEEDS[0]].render_key()
    assert again.describe_json() == cases[SEEDS[0]].describe_json()
    assert len({c.render_key() for c in cases.values()}) == len(cases)
    # the two resolutions: the same scene and motion, the lens scaled
    full = make_case(SEEDS[0], "full")
    assert (full.calibration.width, full.calibration.height) == RESOLUTIONS["full"]
    assert full.calibration.fx == pytest.approx(2 * cases[SEEDS[0]].calibration.fx)
    assert full.room == cases[SEEDS[0]].room
    assert [p.stamp_ns for p in full.poses] == [p.stamp_ns for p in cases[SEEDS[0]].poses]


def test_every_case_keeps_within_the_bounds_of_the_family(cases):
    for seed, case in cases.items():
        r = case.robot
        assert 30.0 <= r.hfov_deg <= 100.0 and r.fps in (10.0, 20.0, 30.0, 60.0), seed
        assert 0.2 <= r.height_m <= 1.5 and -30.0 <= r.pitch_deg <= 10.0 and 0.0 <= r.lever_m <= 0.4, seed
        assert 0.001 <= r.exposure_s <= 0.008 and case.effects.exposure_s == r.exposure_s, seed
        times, positions, rate = _camera_motion(case)
        assert 30.0 <= case.seconds <= 200.0, seed
        # the camera's speed: the robot's (<= 1.2 m/s) plus its turn on the lever
        speed = np.linalg.norm(np.diff(positions, axis=0), axis=1) / np.diff(times)
        assert speed.max() <= r.speed_m_s + np.radians(r.turn_deg_s) * r.lever_m + 0.02, seed
        assert rate.max() <= r.turn_deg_s + 1.0 and r.turn_deg_s <= 120.0, seed
        # inside the room, at the camera's height, never inside a box
        room = case.room
        assert all(room.contains(p, margin=0.1) for p in positions), seed
        assert np.allclose(positions[:, 2], room.z_range[0] + r.height_m), seed
        for box in room.boxes:
            low = np.array(box.center) - np.array(box.size) / 2
            high = np.array(box.center) + np.array(box.size) / 2
            inside = np.all((positions > low) & (positions < high), axis=1)
            assert not inside.any(), seed
        # it starts and ends in front of the cube, and loses it in between
        assert case.target_visible[0] and case.target_visible[-1], seed
        assert case.longest_target_absence_s() >= 10.0, seed
        assert case.path_since_target().max() > 3.0, seed


def test_the_cube_stands_on_the_floor_or_on_a_table_and_the_floor_is_below_it():
    tables = [make_case(seed) for seed in (4, 11)]  # cases with the cube on a table
    for case in tables:
        assert 0.7 <= case.table_m <= 0.8
        assert case.room.z_range[0] == pytest.approx(-CUBE_HALF - case.table_m)
        # the camera looks over the table top at the start, not into the table's side
        assert case.poses[0].T_world_camera.translation[2] > -CUBE_HALF


def test_a_view_of_plain_paint_is_blank_and_a_textured_wall_is_not():
    room = Room(plain=(0.0, 0.0, 0.0, 0.0, 1.0, 0.0))  # a plain floor, textured walls
    calibration = make_case(SEEDS[0]).calibration
    down = camera_from_yaw_pitch(np.array([0.0, -1.5, 1.0]), 0.0, np.radians(80.0))  # at the floor
    ahead = camera_from_yaw_pitch(np.array([0.0, -1.5, 1.0]), 0.0, 0.0)  # at the +x wall
    floor, wall = _textured_share([down, ahead], calibration, room, ())
    assert floor < BLANK_VIEW_SHARE
    assert wall == pytest.approx(0.75)  # the wall 5 m ahead; the lower quarter of the view is the floor


def test_long_blank_views_and_turns_on_the_axis_are_flagged_unobservable():
    flagged = {seed: make_case(seed) for seed in (1, 2, 3)}
    assert "blank_view" in flagged[1].unobservable  # a painted panel faced for seconds
    assert "blank_view" in flagged[3].unobservable  # a narrow lens pitched down at a plain floor
    assert "rotation_on_axis" in flagged[2].unobservable and flagged[2].robot.lever_m < 0.05
    assert min(flagged[3].textured) < BLANK_VIEW_SHARE


def test_a_rendered_case_is_a_sequence_with_its_description(tmp_path, cases):
    case = cases[SEEDS[1]]
    short = replace(case, poses=case.poses[:4], target_visible=case.target_visible[:4],
                    textured=case.textured[:4])
    render_case(short, tmp_path / "seq")
    entries = read_sequence_index(tmp_path / "seq")
    assert len(entries) == 4
    image = read_image(entries[0].path)
    assert image.shape == (case.calibration.height, case.calibration.width)
    described = json.loads((tmp_path / "seq" / "family.json").read_text())
    assert described["seed"] == case.seed and described["camera"]["fps"] == case.robot.fps
    assert (tmp_path / "seq" / "render.key").read_text().strip() == short.render_key()
    assert short.render_key() != case.render_key()


def test_the_robots_wheel_odometry_follows_its_base_with_the_wheels_errors(cases):
    from cubeloc.positioning.geometry import Transform

    case = cases[6]
    rows = wheel_odometry(case)
    stamps = np.array([r["stamp_ns"] for r in rows])
    assert np.all(np.diff(stamps) == 20_000_000)  # 50 Hz
    assert case.poses[0].stamp_ns < stamps[0] < case.poses[1].stamp_ns  # on its own clock phase
    assert stamps[-1] <= case.poses[-1].stamp_ns
    # the base under the camera, as the mount says: the camera carried on by the odometry
    # from its first pose lands where the truth has it, within the wheels' errors
    xyz, quaternion = base_from_camera(case)
    mount = Transform.from_quaternion(np.array(xyz), np.array(quaternion))
    start = case.poses[0].T_world_camera @ mount.inverse()  # the base in the world at the start
    first = Transform.from_quaternion(np.array(rows[0]["position"]), np.array(rows[0]["orientation"]))
    k = len(rows) // 4  # a quarter of the run in
    at = Transform.from_quaternion(np.array(rows[k]["position"]), np.array(rows[k]["orientation"]))
    camera = start @ first.inverse() @ at @ mount
    truth = min(case.poses, key=lambda p: abs(p.stamp_ns - rows[k]["stamp_ns"])).T_world_camera
    positions = np.array([r["position"] for r in rows])
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    driven = steps[:k].sum()
    assert driven > 2.0
    assert np.linalg.norm(camera.translation - truth.translation) < 0.05 * driven
    # the wheels measure the base's path (the axis, the lever behind the camera), 1.5 % long
    centres = np.array([p.T_world_camera.translation[:2] for p in case.poses])
    forward = np.array([p.T_world_camera.rotation[:2, 2] for p in case.poses])
    axis = centres - case.robot.lever_m * forward / np.linalg.norm(forward, axis=1, keepdims=True)
    true_path = np.linalg.norm(np.diff(axis, axis=0), axis=1).sum()
    assert steps.sum() / true_path == pytest.approx(1.015, abs=0.005)
