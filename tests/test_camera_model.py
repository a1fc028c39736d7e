"""positioning/camera_model.py against fakes' independent optics (the ground truth)."""

from __future__ import annotations

import dataclasses

import numpy as np

from calib.camera_info import paper_camera
from fakes.optics import project as true_project
from positioning.camera_model import distort, project, project_with_jacobian, undistort

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
