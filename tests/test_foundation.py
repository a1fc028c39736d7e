"""The shared core: configuration, calibration files, targets, atomic writes, the CLI."""

from __future__ import annotations

import numpy as np
import pytest

from cubeloc.atomic import atomic_open
from cubeloc.calib.camera_info import (
    CameraCalibration,
    paper_camera,
    read_camera_info,
    write_camera_info,
)
from cubeloc.daemon.config import load_config
from cubeloc.errors import ConfigError, InputFileError
from cubeloc.positioning.geometry import Transform, canonical_quaternion, look_at
from cubeloc.positioning.target import load_target, make_cube


def test_config_defaults_and_file(tmp_path):
    config = load_config(None, environ={})
    assert config.camera.width == 1280 and config.camera.height == 1024
    path = tmp_path / "c.toml"
    path.write_text('name = "bot1"\n[camera]\nexposure_us = 5000\n[zenoh]\nconnect = ["tcp/127.0.0.1:7447"]\n')
    config = load_config(path, environ={})
    assert config.name == "bot1" and config.camera.exposure_us == 5000
    assert config.zenoh.connect == ("tcp/127.0.0.1:7447",)


def test_config_environment_override(tmp_path):
    config = load_config(None, environ={"CUBELOC_CAMERA__GAIN_DB": "3.5", "CUBELOC_NAME": "r7"})
    assert config.camera.gain_db == 3.5 and config.name == "r7"
    with pytest.raises(ConfigError, match="CUBELOC_CAMERA__GAIN_DB"):
        load_config(None, environ={"CUBELOC_CAMERA__GAIN_DB": "loud"})


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("[camera]\nexposure_us = 'abc'\n", r"camera.exposure_us = 'abc'"),
        ("[camera]\nexposur_us = 3\n", r"unknown key 'camera.exposur_us'"),
        ("[zenoh]\nconnect = ['10.0.0.1:7447']\n", r"zenoh.connect"),
        ("name = 'a/b'\n", r"name = 'a/b'"),
        ("[camera\n", r"not valid TOML"),
    ],
)
def test_config_errors_name_field_value_and_file(tmp_path, text, match):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match) as info:
        load_config(path, environ={})
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_camera_info_round_trip(tmp_path):
    calibration = CameraCalibration(
        1280, 1024, paper_camera().camera_matrix, [-0.1, 0.02, 1e-4, -2e-4, 0.003],
        metadata={"rms_px": 0.12, "views": 25},
    )
    path = tmp_path / "cam.yaml"
    write_camera_info(path, calibration)
    loaded = read_camera_info(path)
    assert np.array_equal(loaded.camera_matrix, calibration.camera_matrix)
    assert np.array_equal(loaded.distortion, calibration.distortion)
    assert loaded.metadata == {"rms_px": 0.12, "views": 25}


def test_camera_info_written_by_ros_loads(tmp_path):
    # The layout ROS camera_calibration_parsers writes (its documented format).
    path = tmp_path / "ost.yaml"
    path.write_text(
        "image_width: 1280\nimage_height: 1024\ncamera_name: narrow_stereo\n"
        "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [1650.1, 0, 640.2, 0, 1651.3, 511.7, 0, 0, 1]\n"
        "distortion_model: plumb_bob\n"
        "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [-0.08, 0.05, 0, 0, 0]\n"
        "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
        "projection_matrix:\n  rows: 3\n  cols: 4\n  data: [1650.1, 0, 640.2, 0, 0, 1651.3, 511.7, 0, 0, 0, 1, 0]\n"
    )
    loaded = read_camera_info(path)
    assert loaded.fx == pytest.approx(1650.1) and loaded.cy == pytest.approx(511.7)


def test_camera_info_errors(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("image_width: 1280\nimage_height: 1024\ncamera_matrix: {rows: 3, cols: 3, data: [1, 2]}\n")
    with pytest.raises(InputFileError, match="camera_matrix"):
        read_camera_info(path)
    with pytest.raises(InputFileError, match="not found"):
        read_camera_info(tmp_path / "missing.yaml")


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    path = tmp_path / "f.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError), atomic_open(path) as handle:
        handle.write("new, half")
        raise RuntimeError("crash while writing")
    assert path.read_text() == "old"
    assert list(tmp_path.iterdir()) == [path]


def test_cube_layout_faces_outward_and_upright():
    cube = make_cube()
    for tag in cube.tags:
        center = tag.center
        assert np.dot(tag.normal, center) == pytest.approx(0.09)  # on the face, normal outward
        assert tag.size_m == pytest.approx(0.144)
    side = cube.tag(0)  # +x face: TL is at +z (upright) and -y (left, seen from outside)
    assert side.corners[0][2] > 0 and side.corners[0][1] < 0


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("family: tag99h1\ncube: {side: 0.18, tag_size: 0.144, ids: [0,1,2,3,4,5]}", "unrecognised tag family"),
        ("cube: {side: 0.18, tag_size: 0.2, ids: [0,1,2,3,4,5]}", "no larger than"),
        ("cube: {side: 0.18, tag_size: 0.144, ids: [0,1,2,3,4,4]}", "appears twice"),
        ("tags: [{id: 1, corners: [[0,0,0],[1,0,0],[1,1,0]]}]", "needs 4 corners"),
        ("tags: [{id: 1, corners: [[0,0,0],[0.1,0,0],[0.1,0.2,0],[0,0.2,0]]}]", "not a square"),
        ("tags: [{id: 1, corners: [[0,0,0],[0.1,0,0],[0.1,0.1,0.01],[0,0.1,0]]}]", "not planar"),
    ],
)
def test_target_validation(tmp_path, text, match):
    path = tmp_path / "t.yaml"
    path.write_text(text)
    with pytest.raises(InputFileError, match=match):
        load_target(path)


def test_explicit_target_round_trip(tmp_path):
    cube = make_cube()
    path = tmp_path / "t.yaml"
    path.write_text(cube.to_yaml())
    loaded = load_target(path)
    assert loaded.ids == cube.ids
    assert np.allclose(loaded.corners_of([3, 4]), cube.corners_of([3, 4]))


def test_transforms_and_quaternion_convention():
    T = look_at([2.0, 1.0, 0.5], [0.0, 0.0, 0.0])
    assert np.allclose((T @ T.inverse()).matrix(), np.eye(4))
    q = T.quaternion()
    assert q[3] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
    assert np.allclose(canonical_quaternion(-q), q)
    back = Transform.from_quaternion(T.translation, q)
    assert np.allclose(back.rotation, T.rotation)
    # the camera looks at the origin: it is on the optical axis, in front
    p = T.inverse().apply(np.zeros((1, 3)))[0]
    assert p[0] == pytest.approx(0, abs=1e-12) and p[1] == pytest.approx(0, abs=1e-12) and p[2] > 0


def test_cli_help_and_user_errors(cli):
    result = cli("--help")
    assert result.returncode == 0 and "demo" in result.stdout
    result = cli("no-such-verb")
    assert result.returncode == 2 and "Traceback" not in result.stderr


def test_ray_grid_inverts_opencv_projection_exactly():
    import cv2

    from cubeloc.fakes.optics import project, ray_grid

    calibration = CameraCalibration(
        320, 256, [[420.0, 0, 159.5], [0, 421.0, 127.5], [0, 0, 1]], [-0.3, 0.12, 1e-3, -2e-3, -0.02]
    )
    grid = ray_grid(calibration, supersample=2)
    assert grid.shape == (512, 640, 2)
    rays = np.concatenate([grid.reshape(-1, 2), np.ones((grid.shape[0] * grid.shape[1], 1))], axis=1)
    uv, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), calibration.camera_matrix, calibration.distortion)
    s = 2
    u = (np.arange(640) + 0.5) / s - 0.5
    v = (np.arange(512) + 0.5) / s - 0.5
    uu, vv = np.meshgrid(u, v)
    expected = np.column_stack([uu.ravel(), vv.ravel()])
    assert np.abs(uv.reshape(-1, 2) - expected).max() < 1e-6
    assert np.abs(project(rays, calibration) - expected).max() < 1e-6


def test_atomic_write_removes_what_a_killed_writer_left(tmp_path):
    import os
    import subprocess
    import sys

    from cubeloc.atomic import atomic_write_bytes

    target = tmp_path / "camera.yaml"
    target.write_bytes(b"old")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    orphan = tmp_path / f".camera.yaml.{dead_pid}.abc123.tmp"  # a writer killed mid-write
    orphan.write_bytes(b"half")
    alive = tmp_path / f".camera.yaml.{os.getpid()}.xyz789.tmp"  # a write in progress elsewhere
    alive.write_bytes(b"busy")
    atomic_write_bytes(target, b"new")
    assert target.read_bytes() == b"new"
    assert not orphan.exists() and alive.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([target.name, alive.name])
