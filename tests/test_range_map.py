"""The effective-range bookkeeping (the sweep itself runs in bench/pose.py)."""

from __future__ import annotations

import numpy as np

from cubeloc.calib.camera_info import paper_camera
from cubeloc.positioning.range_map import (
    FaceAngleSample,
    RangeCell,
    camera_on_sphere,
    critical_angle,
    range_sweep,
    summary_rows,
)
from cubeloc.positioning.target import make_cube


def test_camera_on_sphere_looks_at_the_origin_from_the_given_direction():
    T = camera_on_sphere(90.0, 30.0, 2.0)
    assert np.allclose(T.translation, [0.0, 2 * np.cos(np.radians(30)), 1.0])
    assert np.allclose(T.rotation[:, 2], -T.translation / 2.0)  # optical axis towards the cube


def test_critical_angle_is_the_last_decoded_angle_before_the_first_failure():
    samples = [FaceAngleSample(a, 2.0, a <= 77 or a == 80) for a in range(70, 85)]
    samples += [FaceAngleSample(a, 1.0, True) for a in range(70, 85)]
    assert critical_angle(samples, 2.0) == 77
    assert critical_angle(samples, 1.0) == 84
    assert critical_angle(samples, 3.0) is None


def test_summary_counts_faces_and_medians_per_distance():
    cells = [RangeCell(0, 1.0, 3, 3, 0.2, "ok"), RangeCell(10, 1.0, 3, 3, 0.4, "ok"),
             RangeCell(20, 1.0, 2, 2, 1.0, "ok"), RangeCell(30, 1.0, 0, 1, None, "one_face")]
    (row,) = summary_rows(cells)
    assert (row["three"], row["two"], row["none"], row["one_face_only"]) == (2, 1, 1, 1)
    assert abs(row["median_3_mm"] - 0.3) < 1e-12
    assert row["max_mm"] == 1.0


def test_sweep_records_no_pose_for_images_without_the_target():
    camera = paper_camera()
    blank = np.full((camera.height, camera.width), 128, np.uint8)
    cells = range_sweep(make_cube(), camera, lambda T, seed: blank, [0.0, 45.0], [1.0], 30.0)
    assert [(c.azimuth_deg, c.planes, c.status) for c in cells] == [(0.0, 0, "no_target"), (45.0, 0, "no_target")]
