"""positioning/camera_model.py against fakes' independent optics (the ground truth)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cubeloc.calib.camera_info import paper_camera, read_camera_info, write_camera_info
from cubeloc.errors import InputFileError
from cubeloc.fakes.optics import project as true_project
from cubeloc.positioning.camera_model import distort, project, project_with_jacobian, undistort

CAMERA = paper_camera()


def test_undistort_inverts_the_camera_model():
    rng = np.random.default_rng(0)
    xn = rng.uniform(-0.35, 0.35, (50, 2))
    pixels = true_project(np.column_stack([xn, np.ones(50)]), CAMERA)
    assert np.abs(undistort(pixels, CAMERA) - xn).max() < 1e-9


def test_undistort_inverts_the_projection_over_the_whole_image_on_a_strong_lens():
    strong = dataclasses.replace(CAMERA, distortion=np.array([-0.3, 0.12, 0.001, -0.001, -0.02]))
    u, v = np.meshgrid(np.linspace(0, 1279, 17), np.linspace(0, 1023, 13))
    pixels = np.column_stack([u.ravel(), v.ravel()])
    assert np.abs(distort(undistort(pixels, strong), strong) - pixels).max() < 1e-6
    points = np.column_stack([undistort(pixels, strong), np.ones(len(pixels))]) * 2.0
    fast, _ = project_with_jacobian(points, strong)
    assert np.abs(fast - project(points, strong)).max() < 1e-6


FISHEYE = dataclasses.replace(CAMERA, distortion=np.array([0.0035, 0.0007, -0.002, 0.0002]),
                              distortion_model="equidistant", camera_matrix=np.array(
                                  [[560.0, 0.3, 641.5], [0.0, 559.0, 510.0], [0.0, 0.0, 1.0]]))


def test_the_fisheye_model_agrees_with_fakes_optics_to_84_degrees_off_axis():
    """cv2.fisheye under positioning/ (with a skew, which cv2.fisheye takes apart from K),
    fakes' own equidistant model: pixels, rays back, the compiled Jacobian against finite
    differences, and the pixels a pinhole PnP solver is given."""
    from cubeloc.positioning.camera_model import project_pose, solver_pixels

    rng = np.random.default_rng(4)
    theta, azimuth = np.radians(rng.uniform(0.0, 84.0, 300)), rng.uniform(0.0, 2 * np.pi, 300)
    rays = np.column_stack([np.tan(theta) * np.cos(azimuth), np.tan(theta) * np.sin(azimuth), np.ones(300)])
    points = rays * rng.uniform(0.3, 5.0, (300, 1))
    pixels = project(points, FISHEYE)
    assert np.abs(pixels - true_project(points, FISHEYE)).max() < 1e-9
    assert np.abs(undistort(pixels, FISHEYE) - rays[:, :2]).max() < 1e-9 * np.abs(rays).max()
    fast, jacobian = project_with_jacobian(points, FISHEYE)
    assert np.abs(fast - pixels).max() < 1e-9
    step = 1e-6
    numeric = np.stack([(project(points + step * e, FISHEYE) - project(points - step * e, FISHEYE)) / (2 * step)
                        for e in np.eye(3)], axis=2)
    assert np.abs(jacobian - numeric).max() < 1e-4 * np.abs(numeric).max()
    rvec, tvec = np.array([0.1, -0.2, 0.05]), np.array([0.02, -0.01, 0.1])
    posed, pose_jacobian = project_pose(points, rvec, tvec, FISHEYE, jacobian=True)
    numeric = np.column_stack([(project_pose(points, rvec + step * e[:3], tvec + step * e[3:], FISHEYE)
                                - project_pose(points, rvec - step * e[:3], tvec - step * e[3:], FISHEYE)).ravel()
                               / (2 * step) for e in np.eye(6)])
    assert np.abs(pose_jacobian - numeric).max() < 1e-4 * np.abs(numeric).max()
    solver, k, d = solver_pixels(pixels, FISHEYE)
    assert d is None and np.abs(solver - (rays @ k.T)[:, :2]).max() < 1e-6


def test_a_fisheye_camera_info_round_trips(tmp_path):
    write_camera_info(tmp_path / "fisheye.yaml", FISHEYE)
    again = read_camera_info(tmp_path / "fisheye.yaml")
    assert again.distortion_model == "equidistant" and again.is_fisheye
    assert np.array_equal(again.distortion, FISHEYE.distortion)
    text = (tmp_path / "fisheye.yaml").read_text().replace("data: [0.0035, 0.0007, -0.002, 0.0002]", "data: [0.0035]")
    (tmp_path / "short.yaml").write_text(text)
    with pytest.raises(InputFileError, match="equidistant needs 4 distortion coefficients, the file has 1"):
        read_camera_info(tmp_path / "short.yaml")
