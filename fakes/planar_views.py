"""Seeded views of a planar target (a board of tags) for pose tests and ``bench planar``: the
camera 0.5-3 m from the board's centre, 0-60 deg off its normal, rolled at random, the
whole board in view, rendered blurred in a textured room; a calibration off as a real one
is; and a board stood up in a room (``standing_board``), for the tracker's scenarios."""

from __future__ import annotations

import dataclasses

import numpy as np

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.fakes.optics import project
from cubeloc.fakes.render import render_view
from cubeloc.fakes.room import Room
from cubeloc.positioning.geometry import Transform, look_at
from cubeloc.positioning.target import Tag, Target

BORDER_PX = 10.0  # every corner of the board at least this far inside the image
ROOM = Room(x_range=(-7.0, 7.0), y_range=(-7.0, 7.0), z_range=(-0.09, 5.0))  # the board at z = 0 faces up


def rendered_board_view(board: Target, calibration: CameraCalibration, seed: int
                        ) -> tuple[Transform, np.ndarray, np.random.Generator] | None:
    """View ``seed`` of ``board``: (T_world_camera, image, the generator for what else the
    case draws), blurred 0.3-1 px, smeared 0-2 px, read noise 2 DN; None when the board
    does not fit the lens."""
    rng = np.random.default_rng(1000 * seed + 7)
    truth = view_of_board(board, calibration, rng)
    if truth is None:
        return None
    image = render_view(truth, calibration=calibration, target=board, room=ROOM, seed=seed,
                        blur_sigma_px=rng.uniform(0.3, 1.0), motion_blur_px=rng.uniform(0.0, 2.0),
                        motion_blur_angle_deg=rng.uniform(0.0, 180.0))
    return truth, image, rng


def view_of_board(board: Target, calibration: CameraCalibration, rng: np.random.Generator,
                  distance_m: tuple[float, float] = (0.5, 3.0), max_angle_deg: float = 60.0) -> Transform | None:
    """A T_world_camera looking at ``board`` (a target whose tags face +z) from a random
    distance and angle off its normal, aimed within 5 cm of its centre, with the whole
    board in view; None when 200 draws found none (a board too large for the lens)."""
    points = board.corners_of(board.ids)
    centre = points.mean(axis=0)
    for _ in range(200):
        distance = rng.uniform(*distance_m)
        angle, azimuth = np.radians(rng.uniform(0.0, max_angle_deg)), rng.uniform(0.0, 2 * np.pi)
        direction = np.array([np.sin(angle) * np.cos(azimuth), np.sin(angle) * np.sin(azimuth), np.cos(angle)])
        roll = rng.uniform(0.0, 2 * np.pi)
        aim = centre + rng.normal(0.0, 0.05, 3) * np.array([1.0, 1.0, 0.0])
        pose = look_at(centre + distance * direction, aim, up=np.array([np.cos(roll), np.sin(roll), 0.0]))
        in_camera = pose.inverse().apply(points)
        if np.any(in_camera[:, 2] < 0.1):
            continue
        pixels = project(in_camera, calibration)
        if (pixels.min() > BORDER_PX and pixels[:, 0].max() < calibration.width - BORDER_PX
                and pixels[:, 1].max() < calibration.height - BORDER_PX):
            return pose
    return None


def miscalibrated(calibration: CameraCalibration, rng: np.random.Generator) -> CameraCalibration:
    """``calibration`` off as a real calibration is: f by 0.2 %, the principal point by 0.5
    px, k1 by 0.005 (one sigma each): a systematic corner error of a few tenths of a pixel."""
    k, d = calibration.camera_matrix.copy(), calibration.distortion.copy()
    f = 1.0 + rng.normal(0.0, 0.002)
    k[0, 0] *= f
    k[1, 1] *= f
    k[:2, 2] += rng.normal(0.0, 0.5, 2)
    d[0] += rng.normal(0.0, 0.005)
    return dataclasses.replace(calibration, camera_matrix=k, distortion=d)


def standing_board(board: Target, centre: np.ndarray, facing: np.ndarray) -> Target:
    """``board`` (``make_board``'s: tags in z = 0 facing +z, its rows going down -y) stood
    upright with its centre at ``centre``, facing the horizontal direction ``facing``, its
    rows level."""
    facing = np.array([facing[0], facing[1], 0.0], np.float64)
    facing /= np.linalg.norm(facing)
    up = np.array([0.0, 0.0, 1.0])
    rotation = np.column_stack([np.cross(up, facing), up, facing])  # board x, y (up it), normal
    shift = np.asarray(centre, np.float64) - rotation @ board.corners_of(board.ids).mean(axis=0)
    return Target(board.family, tuple(Tag(t.tag_id, t.corners @ rotation.T + shift) for t in board.tags),
                  border_bits=board.border_bits)
