"""Trajectories, the SyntheticCamera (camera protocol, registry source) and `cubeloc simulate`."""

from __future__ import annotations

import time

import numpy as np
import pytest

from cubeloc.calib.camera_info import paper_camera, read_camera_info
from cubeloc.daemon.cameras import make_camera
from cubeloc.drivers.base import (
    Camera,
    CameraNotFound,
    CameraSettings,
    EndOfStream,
    FeatureNotSupported,
)
from cubeloc.drivers.sequence import read_image, read_sequence_index
from cubeloc.fakes import TRAJECTORIES, SyntheticCamera, default_room, make_trajectory
from cubeloc.fakes.scenarios import TIMING as SCENARIO_TIMING
from cubeloc.fakes.trajectories import DEFAULT_FPS_OF, EPOCH_NS, TrajectoryError
from cubeloc.positioning.geometry import look_at
from cubeloc.positioning.target import load_target, make_cube
from cubeloc.positioning.trajectory_io import StampedPose, read_tum, write_tum

CUBE = make_cube()
PAPER = paper_camera()
HALF_FOV = np.array([PAPER.cx / PAPER.fx, PAPER.cy / PAPER.fy])  # normalised image half-size


def cube_in_view(pose) -> bool:
    centre = pose.inverse().apply(np.zeros((1, 3)))[0]
    return bool(centre[2] > 0 and np.all(np.abs(centre[:2] / centre[2]) < 0.9 * HALF_FOV))


def faces_towards(pose) -> set[int]:
    """Tags whose face the camera sees at under 75 degrees from its normal."""
    seen = set()
    for tag in CUBE.tags:
        to_camera = pose.translation - tag.center
        if tag.normal @ to_camera / np.linalg.norm(to_camera) > np.cos(np.radians(75)):
            seen.add(tag.tag_id)
    return seen


@pytest.mark.parametrize("name", TRAJECTORIES)
def test_every_trajectory_starts_on_three_faces_and_moves_smoothly(name):
    poses = make_trajectory(name)
    first = poses[0].T_world_camera
    assert cube_in_view(first) and faces_towards(first) == {0, 3, 4}
    assert 1.5 <= np.linalg.norm(first.translation) <= 2.5
    assert poses[0].stamp_ns == EPOCH_NS
    fps = DEFAULT_FPS_OF.get(name, 10.0)  # 10 fps default, 30 for the fast scenarios
    assert np.all(np.abs(np.diff([p.stamp_ns for p in poses]) - 1e9 / fps) <= 1)
    # the robot-motion scenarios turn briskly on purpose (fakes.scenarios)
    max_turn = (130 if name == "spin_brisk" else 100) if name in SCENARIO_TIMING else 45
    room = default_room()
    for a, b in zip(poses, poses[1:], strict=False):
        assert room.contains(b.T_world_camera.translation, margin=0.3)
        step = np.linalg.norm(b.T_world_camera.translation - a.T_world_camera.translation)
        turn = np.degrees(a.T_world_camera.rotation_angle_to(b.T_world_camera))
        assert step * fps < 1.0 and turn * fps < max_turn  # walking pace, turning at < 45 (100, 130) deg/s


def test_paper_and_room_walk_lose_the_cube_and_room_walk_finds_it_again():
    paper = [cube_in_view(p.T_world_camera) for p in make_trajectory("paper")]
    assert all(paper[:30]) and not any(paper[100:])  # in view for 3 s, gone after 10 s
    walk = [cube_in_view(p.T_world_camera) for p in make_trajectory("room_walk", seconds=40, fps=10)]
    out = np.flatnonzero(~np.array(walk))
    assert walk[0] and walk[-1]
    assert len(out) >= 200 and np.all(np.diff(out) == 1)  # one stretch of >= 20 s out of view
    poses = make_trajectory("orbit", seconds=40)
    azimuths = np.unwrap([np.arctan2(p.T_world_camera.translation[1], p.T_world_camera.translation[0]) for p in poses])
    assert np.ptp(azimuths) > np.radians(340)  # round the cube
    assert all(cube_in_view(p.T_world_camera) for p in poses)


def test_trajectory_errors_say_what_is_allowed():
    with pytest.raises(TrajectoryError, match="known: static, orbit, paper, room_walk"):
        make_trajectory("zigzag")
    with pytest.raises(TrajectoryError, match="at least 30"):
        make_trajectory("room_walk", seconds=10)
    with pytest.raises(TrajectoryError, match="fps"):
        make_trajectory("paper", seconds=3, fps=0)
    assert len(make_trajectory("static", seconds=2, fps=25)) == 50


def test_synthetic_camera_follows_the_protocol_and_reports_ground_truth():
    camera = make_camera("synthetic:orbit?seconds=0.4&fps=10&seed=3&noise=1.5")
    assert isinstance(camera, SyntheticCamera) and isinstance(camera, Camera)
    assert camera.info.transport == "synthetic" and camera.settings.frame_rate_hz == pytest.approx(10)
    truth = make_trajectory("orbit", 0.4, 10)
    with camera:
        camera.start()
        frames = [camera.next_frame(timeout_s=1.0) for _ in range(4)]
        with pytest.raises(EndOfStream):
            camera.next_frame(timeout_s=1.0)
    assert [f.frame_id for f in frames] == [0, 1, 2, 3]
    assert [f.stamp_ns for f in frames] == [p.stamp_ns for p in truth]
    assert all(f.image.shape == (1024, 1280) and f.image.dtype == np.uint8 for f in frames)
    assert camera.stats.delivered == 4 and camera.stats.dropped == 0
    for frame, pose in zip(frames, truth, strict=True):
        found = camera.ground_truth_at(frame.stamp_ns)
        assert np.allclose(found.matrix(), pose.T_world_camera.matrix())
    assert camera.ground_truth_at(frames[0].stamp_ns + 10**9) is None
    # frames are rendered from the poses with noise seeded per frame: reproducible
    again = SyntheticCamera(truth, seed=3, options=camera.options)
    with again:
        again.start()
        assert np.array_equal(again.next_frame(1.0).image, frames[0].image)
        assert not np.array_equal(again.next_frame(1.0).image, frames[0].image)


def test_synthetic_camera_loops_and_paces_in_real_time():
    camera = make_camera("synthetic:static?seconds=0.3&fps=10&loop=1&realtime=1")
    with camera:
        camera.start()
        started = time.monotonic()
        frames = [camera.next_frame(timeout_s=2.0) for _ in range(5)]
        elapsed = time.monotonic() - started
    ids = [f.frame_id for f in frames]
    assert ids == sorted(set(ids)) and ids[-1] >= 4  # increasing; a slow machine may skip some
    assert camera.stats.frame_id_gaps == ids[-1] - 4
    # paced by the clock: frame k is not delivered before k / fps after the start
    assert elapsed >= 0.1 * ids[-1] - 0.05
    stamps = np.array([f.stamp_ns for f in frames])
    assert np.all(np.diff(stamps) == 100_000_000 * np.diff(ids))  # on the frame grid, over loops
    assert abs(stamps[0] - time.time_ns()) < 60e9  # host clock in real time
    assert camera.ground_truth_at(int(stamps[-1])) is not None  # loops map back onto the trajectory


@pytest.mark.parametrize(
    ("source", "error", "match"),
    [
        ("synthetic:zigzag", CameraNotFound, "known: static, orbit"),
        ("synthetic:paper?speed=3", FeatureNotSupported, "unknown option.*speed.*known: seconds"),
        ("synthetic:paper?fps=fast", FeatureNotSupported, "fps='fast'"),
        ("synthetic:paper?fps=0", FeatureNotSupported, r"fps='0' must be in \(0, 1000\]"),  # before: accepted
        ("synthetic:paper?fps=-5", FeatureNotSupported, "fps='-5' must be"),
        ("synthetic:paper?hide=top", FeatureNotSupported, "hide='top'"),
    ],
)
def test_bad_synthetic_sources_name_the_problem(source, error, match):
    with pytest.raises(error, match=match):
        make_camera(source)


def test_synthetic_camera_refuses_settings_it_cannot_honour():
    camera = make_camera("synthetic:static", CameraSettings(width=640, height=480))
    with pytest.raises(FeatureNotSupported, match="renders 1280x1024"):
        camera.open()


def test_simulate_writes_a_complete_sequence(tmp_path, cli):
    out = tmp_path / "seq"
    result = cli("simulate", "--trajectory", "paper", "--seconds", "0.5", "--fps", "6", "--out", str(out), "--seed", "2")
    assert result.returncode == 0, result.stderr
    assert "wrote 3 frames" in result.stdout
    entries = read_sequence_index(out)
    truth = read_tum(out / "groundtruth.tum")
    assert [e.stamp_ns for e in entries] == [p.stamp_ns for p in truth] == [
        p.stamp_ns for p in make_trajectory("paper", 0.5, 6)
    ]
    assert read_image(entries[0].path).shape == (1024, 1280)
    assert np.allclose(read_camera_info(out / "camera.yaml").camera_matrix, PAPER.camera_matrix)
    assert load_target(out / "target.yaml").ids == (0, 1, 2, 3, 4, 5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]  # no staging left behind

    again = cli("simulate", "--trajectory", "paper", "--seconds", "0.5", "--out", str(out))
    assert again.returncode == 2
    assert again.stderr.count("\n") == 1 and "Traceback" not in again.stderr
    assert str(out) in again.stderr and "choose another --out" in again.stderr

    short = cli("simulate", "--trajectory", "room_walk", "--seconds", "5", "--out", str(tmp_path / "walk"))
    assert short.returncode == 2 and "at least 30" in short.stderr
    assert not (tmp_path / "walk").exists()


def test_a_tum_file_plays_as_a_trajectory_and_poses_outside_the_room_are_refused(tmp_path):
    poses = make_trajectory("orbit", seconds=0.2, fps=10)
    path = tmp_path / "mine.tum"
    write_tum(path, poses)
    with make_camera(f"synthetic:{path}") as camera:
        camera.start()
        frame = camera.next_frame(1.0)
    assert frame.stamp_ns == poses[0].stamp_ns
    assert np.allclose(camera.ground_truth_at(frame.stamp_ns).matrix(), poses[0].T_world_camera.matrix(), atol=1e-8)
    outside = [StampedPose(EPOCH_NS, look_at(np.array([9.0, 0.0, 1.0]), np.zeros(3)))]
    write_tum(path, outside)
    with pytest.raises(CameraNotFound, match="pose 0 at .* outside the synthetic room"):
        make_camera(f"synthetic:{path}")


def test_simulate_offers_every_trajectory():
    from cubeloc.daemon.commands.simulate import TRAJECTORY_NAMES
    from cubeloc.fakes.trajectories import TRAJECTORIES

    assert TRAJECTORY_NAMES == TRAJECTORIES


def test_simulate_sigterm_leaves_nothing_and_folders_take_the_usual_mode(tmp_path):
    """SIGTERM mid-render removes the staging folder as Ctrl-C does (before: tens of MB of
    ``.partial`` left); a finished sequence's folders have the mode a plain mkdir gives
    (before: 0700 from the staging folder; ``record`` wrote 0755)."""
    import os
    import signal
    import stat
    import subprocess
    import sys
    import time

    out = tmp_path / "long"
    process = subprocess.Popen([sys.executable, "-m", "cubeloc.daemon.cli", "simulate", "--trajectory", "paper", "--out", str(out)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not any(tmp_path.glob(".long.*.partial/mav0/cam0/data/*.png")):
        time.sleep(0.1)
    assert any(tmp_path.glob(".long.*.partial/mav0/cam0/data/*.png")), "no frame rendered within 60 s"
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=60)
    assert process.returncode != 0 and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == [], list(tmp_path.iterdir())

    umask = os.umask(0o022)
    os.umask(umask)
    done = subprocess.run([sys.executable, "-m", "cubeloc.daemon.cli", "simulate", "--trajectory", "paper", "--seconds", "0.2",
                           "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    for folder in (out, out / "mav0", out / "mav0" / "cam0", out / "mav0" / "cam0" / "data"):
        assert stat.S_IMODE(folder.stat().st_mode) == 0o777 & ~umask, folder


def test_simulate_help_gives_every_trajectorys_default_length():
    """Before: four default lengths for five trajectories (and none of the scenarios')."""
    import subprocess
    import sys

    from cubeloc.fakes.trajectories import DEFAULT_SECONDS

    done = subprocess.run([sys.executable, "-m", "cubeloc.daemon.cli", "simulate", "--help"], capture_output=True, text=True,
                          timeout=60, env={"COLUMNS": "1000", **__import__("os").environ})
    text = " ".join(done.stdout.split())
    for name, seconds in DEFAULT_SECONDS.items():
        assert f"{name} {seconds:g}" in text, name
