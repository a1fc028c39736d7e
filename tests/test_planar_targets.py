"""Planar targets: a board of tags (an AprilGrid such as Kalibr's) gives a pose from one
image, its two plane solutions told apart by their residuals; rendered, seeded."""

from __future__ import annotations

import numpy as np
import pytest

from calib.camera_info import paper_camera
from fakes import Room, render_view
from positioning.geometry import look_at
from positioning.single_frame import TargetPoseProcessor
from positioning.target import make_board

BOARD = make_board()  # 6x6 tags of 8.8 cm, 2.6 cm apart
CENTRE = np.array([0.5 * (6 * 0.114 - 0.026), -0.5 * (6 * 0.114 - 0.026), 0.0])
ROOM = Room(x_range=(-7.0, 7.0), y_range=(-7.0, 7.0), z_range=(-0.09, 5.0))


def board_view(distance_m: float, angle_deg: float, azimuth_deg: float):
    """The camera ``angle_deg`` off the board's normal, aimed at its centre."""
    a, phi = np.radians(angle_deg), np.radians(azimuth_deg)
    direction = np.array([np.sin(a) * np.cos(phi), np.sin(a) * np.sin(phi), np.cos(a)])
    return look_at(CENTRE + distance_m * direction, CENTRE, up=(0.0, 1.0, 0.0))


@pytest.mark.parametrize("distance_m", [0.5, 1.5, 3.0])
def test_a_board_gives_a_pose_from_one_image_face_on_and_60_degrees_off(distance_m):
    processor = TargetPoseProcessor(BOARD, paper_camera())
    for k, (angle, azimuth) in enumerate([(0.0, 0.0), (35.0, 120.0), (60.0, 250.0)]):
        truth = board_view(distance_m, angle, azimuth)
        processor.reset()
        result = processor.process(render_view(truth, target=BOARD, room=ROOM, seed=k + int(10 * distance_m)), 0, 0)
        assert result.estimate is not None, (distance_m, angle, result.status, result.detail)
        assert result.estimate.planes == 1
        error = np.linalg.norm(result.estimate.T_world_camera.translation - truth.translation)
        assert error < 0.003, (distance_m, angle, error)  # measured at most 0.7 mm over 84 views
