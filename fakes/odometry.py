"""Simulated wheel odometry along a synthetic trajectory, with the errors wheels have.

The robot's base is on the floor under the camera, the mount's horizontal lever behind it
(``T_base_camera``), heading as the mount says (x, y, heading: wheels measure nothing
else; the camera may tilt on its mount). Its motion between two samples is corrupted as
wheel odometry is: every distance scaled by ``1 + scale_error`` (1.5 %: a worn or
mis-measured wheel), every turn by ``1 + turn_error``, a heading drift of
``heading_drift_deg_s`` (a slow gyro or wheel-base error), white noise of 0.1 mm and 0.1
mrad a sample (encoder steps: 3 mm over 20 s at 50 Hz); integrated from the identity in
the robot's own ``odom`` frame, at ``rate_hz`` (50) on its own clock phase, each sample
arriving ``latency_s`` after its stamp.

Rows are the ``cubeloc.odometry/1`` JSON of docs/robot.md, plus ``arrival_ns`` (when the
sample reached the daemon), one per line: what ``cubeloc track --odometry`` replays.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from cubeloc.positioning.geometry import Transform

ODOMETRY_SCHEMA = "cubeloc.odometry/1"
LEVER_M = 0.2  # the camera ahead of the base's axis, unless a scenario puts it elsewhere


def mount_of(T_world_camera: Transform, lever_m: float = LEVER_M) -> tuple[list[float], list[float]]:
    """T_base_camera (xyz, quaternion [x, y, z, w]) for a base on the floor, ``lever_m``
    behind the camera, heading where it looks: exact for the pose ``T_world_camera`` (a
    trajectory's first), tilt included; as ``[frames] base_from_camera`` takes it."""
    forward = T_world_camera.rotation[:, 2]
    heading = math.atan2(forward[1], forward[0])
    position = T_world_camera.translation - lever_m * np.array([math.cos(heading), math.sin(heading), 0.0])
    position[2] = 0.0
    base = Transform(Rotation.from_euler("z", heading).as_matrix(), position)
    mount = base.inverse() @ T_world_camera
    return [float(v) for v in mount.translation], [float(v) for v in mount.quaternion()]


def drawn_errors(draw: int) -> dict:
    """The wheels' errors of one robot of a family (``wheel_odometry``'s keywords): draw 0
    has the documented ones (distances 1.5 % long, turns 1 % long, 0.2 deg/s); every other
    draw its own, uniform within distances +-2 %, turns +-1.5 %, heading drift +-0.3 deg/s
    (past the error model's 0.2 deg/s: a robot whose gyro is worse than its config says),
    and its own noise."""
    if draw == 0:
        return {}
    rng = np.random.default_rng(1000 + draw)
    return {"scale_error": float(rng.uniform(-0.02, 0.02)), "turn_error": float(rng.uniform(-0.015, 0.015)),
            "heading_drift_deg_s": float(rng.uniform(-0.3, 0.3)), "seed": draw}


def _planar(T_world_camera: Transform, T_base_camera: Transform) -> tuple[float, float, float]:
    """The base under a camera (x, y, heading): the base's x is the mount's, seen from the
    camera and laid flat; its axis the mount's horizontal lever behind the camera. A
    camera that tilts on its mount (the scenarios look down at the cube, level along the
    room) tilts over the same base."""
    ahead = T_world_camera.rotation @ (T_base_camera.rotation.T @ np.array([1.0, 0.0, 0.0]))
    heading = math.atan2(ahead[1], ahead[0])
    lx, ly = T_base_camera.translation[:2]
    c, s = math.cos(heading), math.sin(heading)
    x, y = T_world_camera.translation[:2]
    return float(x - lx * c + ly * s), float(y - lx * s - ly * c), heading


def simulate_odometry(trajectory: str, seconds: float, T_base_camera: Transform, rate_hz: float = 50.0,
                      phase_s: float = 0.007, **errors) -> list[dict]:
    """The wheels' odometry along the named camera trajectory, the base under the camera as
    ``T_base_camera`` says (``wheel_odometry`` has the errors)."""
    from cubeloc.fakes.trajectories import make_trajectory, trajectory_at

    make_trajectory(trajectory, seconds, rate_hz)  # checks the name and the timing
    count = int(np.floor((seconds - phase_s) * rate_hz + 1e-9))
    times = phase_s + np.arange(count) / rate_hz  # the robot's own clock phase, not the camera's
    truth = trajectory_at(trajectory, times, seconds)
    return wheel_odometry(times, [_planar(T, T_base_camera) for T in truth], **errors)


def wheel_odometry(times: np.ndarray, planar: list[tuple[float, float, float]], scale_error: float = 0.015,
                   turn_error: float = 0.01, heading_drift_deg_s: float = 0.2, noise_m: float = 0.0001,
                   noise_rad: float = 0.0001, latency_s: float = 0.03, slip: tuple[float, float] | None = None,
                   seed: int = 0) -> list[dict]:
    """Odometry rows for the base's true ``planar`` poses (x, y, heading) at ``times``
    (seconds from the epoch), as wheels measure them; ``slip`` = (time s, metres): the
    wheels turn that much further than the base moves in the 0.2 s from that time (a
    wheel spinning on a slippery patch)."""
    from cubeloc.fakes.trajectories import EPOCH_NS

    rate_hz = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 else 50.0
    rng = np.random.default_rng(seed)
    x, y, heading = 0.0, 0.0, 0.0
    rows = []
    for k, t in enumerate(times):
        if k:
            (x0, y0, h0), (x1, y1, h1) = planar[k - 1], planar[k]
            # the true step in the base frame at the start, then as the wheels measure it
            dx, dy = x1 - x0, y1 - y0
            ahead, left = math.cos(h0) * dx + math.sin(h0) * dy, -math.sin(h0) * dx + math.cos(h0) * dy
            turn = math.remainder(h1 - h0, 2 * math.pi)
            ahead, left = (v * (1 + scale_error) + rng.normal(0, noise_m) for v in (ahead, left))
            if slip is not None and slip[0] <= t < slip[0] + 0.2:
                ahead += slip[1] * (t - times[k - 1]) / 0.2
            turn = turn * (1 + turn_error) + math.radians(heading_drift_deg_s) / rate_hz + rng.normal(0, noise_rad)
            x += math.cos(heading) * ahead - math.sin(heading) * left
            y += math.sin(heading) * ahead + math.cos(heading) * left
            heading += turn
        stamp_ns = EPOCH_NS + int(round(t * 1e9))
        rows.append({"schema": ODOMETRY_SCHEMA, "stamp_ns": stamp_ns, "frame_id": "odom", "child_frame_id": "base_link",
                     "position": [x, y, 0.0],
                     "orientation": [float(v) for v in Rotation.from_euler("z", heading).as_quat()],
                     "arrival_ns": stamp_ns + int(latency_s * 1e9)})
    return rows


def write_odometry(path: Path, rows: list[dict]) -> None:
    from cubeloc.jsonlines import write_json_lines

    write_json_lines(path, rows)


def figure_eight(times_s: np.ndarray, centre=(0.0, 0.0), size_m: float = 1.0, period_s: float = 20.0
                 ) -> list[tuple[float, float, float]]:
    """A base driving figure-eights (x, y, heading) at ``times_s``: the lemniscate of Gerono
    ``size_m`` from its centre to either end, once round per ``period_s``. Each lobe turns
    the base ~270 deg, one each way, at up to ~50 deg/s for the defaults."""
    w = 2 * math.pi / period_s
    t = np.asarray(times_s, np.float64)
    x = centre[0] + size_m * np.sin(w * t)
    y = centre[1] + 0.5 * size_m * np.sin(2 * w * t)
    heading = np.unwrap(np.arctan2(size_m * w * np.cos(2 * w * t), size_m * w * np.cos(w * t)))
    return [(float(a), float(b), float(h)) for a, b, h in zip(x, y, heading, strict=True)]


def camera_on_base(planar: list[tuple[float, float, float]], T_base_camera: Transform, floor_z: float = 0.0
                   ) -> list[Transform]:
    """T_world_camera of a camera mounted at ``T_base_camera`` on a base at the ``planar``
    poses, its origin on the floor (world z = ``floor_z``, world z up)."""
    return [Transform(Rotation.from_euler("z", h).as_matrix(), np.array([x, y, floor_z])) @ T_base_camera
            for x, y, h in planar]
