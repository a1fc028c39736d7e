"""Camera trajectories around the cube, with exact ground truth ``T_world_camera``.

The cube stands at the world origin on the floor (z = -0.09). Every trajectory starts
with the camera about 2 m from the cube, above its top face and looking down a little at
the corner between the +x and -y faces, so three faces are in view.

==============  ===========================================================================
``static``      the start pose, held still (stability tests, like the paper's 100 s runs)
``orbit``       once round the cube every 40 s at 1.8 m, the height rising and falling 15 cm
``paper``       the paper's experiment: a trolley at constant height (1 m above the floor)
                pushed along a 5 m path at ~0.3 m/s; the cube is in view for the first ~5 s,
                then the camera turns away along the path; after 30 s the trolley stands
``room_walk``   a walk round the room at ~0.6 m/s looking ahead, the cube out of view for
                most of it (>= 20 s), back in view at the end; the walk is spread over the
                whole ``seconds`` (at least 30)
``spin``        4 s sliding 0.4 m sideways while looking at the cube (parallax to initialise),
                then a full turn on the spot (pure rotation, no parallax at all) over
                ``seconds`` - 6 s (at least 8), then 2 s held, looking at the cube again
==============  ===========================================================================

The robot-motion scenarios (``turn_after_init``, ``spin_in_place``, ``spin_in_place_fast``,
``spin_brisk``, ``spin_on_axis``, ``agile``, ``passers_by``, ``blank_wall``, ``long_lap``) live in
``fakes.scenarios``, with their own default rates and the effects that go with them.

Poses are smooth: positions and angles are clamped cubic splines through keyframes (zero
velocity at the ends), or closed-form curves. Stamps start at ``EPOCH_NS``.
"""

from __future__ import annotations

import numpy as np

from cubeloc.errors import CubelocError
from cubeloc.fakes import scenarios
from cubeloc.fakes.scenarios import clamped_spline
from cubeloc.positioning.geometry import Transform, look_at
from cubeloc.positioning.trajectory_io import StampedPose

EPOCH_NS = 1_700_000_000 * 1_000_000_000
DEFAULT_FPS = 10.0
DEFAULT_SECONDS = {"static": 10.0, "orbit": 40.0, "paper": 30.0, "room_walk": 40.0, "spin": 20.0,
                   **{name: timing[0] for name, timing in scenarios.TIMING.items()}}
DEFAULT_FPS_OF = {name: timing[1] for name, timing in scenarios.TIMING.items()}
TRAJECTORIES = tuple(DEFAULT_SECONDS)
ROOM_WALK_MIN_SECONDS = 30.0
START_POSITION = np.array([1.5, -1.5, 0.91])  # ~2.3 m from the cube centre, 1 m above the floor


class TrajectoryError(CubelocError):
    """An unknown trajectory or impossible timing (the message says what is allowed)."""


def camera_from_yaw_pitch(position: np.ndarray, yaw: float, pitch: float) -> Transform:
    """T_world_camera at ``position`` looking along heading ``yaw`` (radians from +x,
    counter-clockwise) tilted down by ``pitch`` (radians), with no roll."""
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), -np.sin(pitch)])
    return look_at(position, np.asarray(position, dtype=np.float64) + forward)


def _heading_to(position: np.ndarray, point: np.ndarray) -> tuple[float, float]:
    """Yaw and pitch that look from ``position`` at ``point``."""
    d = np.asarray(point, dtype=np.float64) - position
    return float(np.arctan2(d[1], d[0])), float(np.arctan2(-d[2], np.hypot(d[0], d[1])))


def _static(times: np.ndarray, seconds: float) -> list[Transform]:
    yaw, pitch = _heading_to(START_POSITION, np.zeros(3))
    pose = camera_from_yaw_pitch(START_POSITION, yaw, pitch)
    return [pose for _ in times]


def _orbit(times: np.ndarray, seconds: float) -> list[Transform]:
    start_azimuth = np.arctan2(START_POSITION[1], START_POSITION[0])
    radius = 1.8
    poses = []
    for t in times:
        azimuth = start_azimuth + 2 * np.pi * t / 40.0
        height = START_POSITION[2] + 0.15 * np.sin(2 * np.pi * t / 20.0)
        position = np.array([radius * np.cos(azimuth), radius * np.sin(azimuth), height])
        poses.append(look_at(position, np.zeros(3)))
    return poses


def _paper(times: np.ndarray, seconds: float) -> list[Transform]:
    # the trolley's camera is rigid: constant height and tilt; only the heading turns
    yaw0, pitch = _heading_to(START_POSITION, np.zeros(3))
    deg = np.pi / 180.0
    keyframes = np.array([
        # t [s], x, y, yaw
        [0.0, START_POSITION[0], START_POSITION[1], yaw0],
        [4.0, 1.9, -0.8, yaw0 + 25 * deg],
        [8.0, 2.3, 0.3, 90 * deg],
        [14.0, 2.5, 1.7, 115 * deg],
        [20.0, 1.7, 2.7, 160 * deg],
        [26.0, 0.6, 3.1, 180 * deg],
        [30.0, -0.5, 3.0, 190 * deg],
    ])
    values = clamped_spline(keyframes, times)
    return [
        camera_from_yaw_pitch(np.array([x, y, START_POSITION[2]]), yaw, pitch) for x, y, yaw in values
    ]


def _room_walk(times: np.ndarray, seconds: float) -> list[Transform]:
    if seconds < ROOM_WALK_MIN_SECONDS:
        raise TrajectoryError(
            f"room_walk needs --seconds of at least {ROOM_WALK_MIN_SECONDS:g} (got {seconds:g}): "
            "the cube must stay out of view for 20 s at a walking pace"
        )
    deg = np.pi / 180.0
    start_azimuth = float(np.arctan2(START_POSITION[1], START_POSITION[0]))
    start_radius = float(np.hypot(START_POSITION[0], START_POSITION[1]))
    yaw0, pitch0 = _heading_to(START_POSITION, np.zeros(3))
    rows = [[0.0, start_azimuth, start_radius, yaw0, pitch0]]
    # counter-clockwise round the cube looking ahead and a little outwards (the cube is
    # 110 degrees off the optical axis), tilted down 15 degrees
    for fraction in np.linspace(0.12, 0.86, 12):
        azimuth = start_azimuth + 25 * deg + (fraction - 0.12) / 0.74 * 320 * deg
        rows.append([fraction, azimuth, 2.8 - 0.3 * np.cos(2 * azimuth) ** 2, azimuth + 70 * deg, 15 * deg])
    end_azimuth = start_azimuth + 2 * np.pi
    rows.append([1.0, end_azimuth, start_radius, yaw0 + 2 * np.pi, pitch0])
    keyframes = np.array(rows)
    keyframes[:, 0] *= seconds
    values = clamped_spline(keyframes, times)
    poses = []
    for azimuth, radius, yaw, pitch in values:
        position = np.array([radius * np.cos(azimuth), radius * np.sin(azimuth), START_POSITION[2]])
        poses.append(camera_from_yaw_pitch(position, yaw, pitch))
    return poses


def _spin(times: np.ndarray, seconds: float) -> list[Transform]:
    if seconds < 14.0:
        raise TrajectoryError(f"spin needs --seconds of at least 14 (got {seconds:g}): 4 s to initialise, "
                              "a turn of at least 8 s, 2 s held")
    yaw0, pitch = _heading_to(START_POSITION, np.zeros(3))
    side = np.array([-np.sin(yaw0), np.cos(yaw0), 0.0])  # horizontal, across the line of sight
    stop = START_POSITION + 0.4 * side
    yaw1, pitch1 = _heading_to(stop, np.zeros(3))
    slide = clamped_spline(np.array([[0.0, *START_POSITION, yaw0, pitch], [4.0, *stop, yaw1, pitch1]]), times)
    turn = clamped_spline(np.array([[4.0, 0.0], [seconds - 2.0, 2 * np.pi]]), times)[:, 0]
    poses = []
    for t, row, extra in zip(times, slide, turn, strict=True):
        position, yaw, tilt = (row[:3], row[3], row[4]) if t < 4.0 else (stop, yaw1 + extra, pitch1)
        poses.append(camera_from_yaw_pitch(position, yaw, tilt))
    return poses


_MAKERS = {"static": _static, "orbit": _orbit, "paper": _paper, "room_walk": _room_walk, "spin": _spin,
           **scenarios.MAKERS}


def make_trajectory(name: str, seconds: float | None = None, fps: float | None = None) -> list[StampedPose]:
    """The named trajectory sampled at ``fps`` for ``seconds`` (defaults per trajectory:
    10 fps, 30 for ``agile`` and ``spin_in_place_fast``)."""
    if name not in _MAKERS:
        raise TrajectoryError(f"unknown trajectory {name!r}; known: {', '.join(TRAJECTORIES)}")
    seconds = DEFAULT_SECONDS[name] if seconds is None else float(seconds)
    fps = DEFAULT_FPS_OF.get(name, DEFAULT_FPS) if fps is None else float(fps)
    _check_seconds(seconds)
    if name in scenarios.TIMING and seconds < scenarios.TIMING[name][2]:
        raise TrajectoryError(f"{name} needs --seconds of at least {scenarios.TIMING[name][2]:g} (got {seconds:g})")
    return _sampled(_MAKERS[name], seconds, fps)


def spin_trajectory(rate_deg_s: float, seconds: float = 14.0, fps: float = 10.0,
                    lever_m: float = 0.2) -> list[StampedPose]:
    """``spin_in_place`` at any turn rate and frame rate: the camera ``lever_m`` ahead of
    the robot's axis, two turns at ``rate_deg_s`` right after initialisation (bench turns)."""
    if not (np.isfinite(rate_deg_s) and rate_deg_s > 0):
        raise TrajectoryError(f"the turn rate must be a positive number of deg/s, got {rate_deg_s:g}")
    _check_seconds(float(seconds))
    return _sampled(lambda times, s: scenarios.spin(times, s, lever_m, rate_deg_s), float(seconds), float(fps))


def _check_seconds(seconds: float) -> None:
    if not (np.isfinite(seconds) and seconds > 0):
        raise TrajectoryError(f"--seconds must be a positive number, got {seconds:g}")


def _sampled(maker, seconds: float, fps: float) -> list[StampedPose]:
    """``maker``'s poses at ``fps`` for ``seconds`` (checked positive), stamped from EPOCH_NS."""
    if not (np.isfinite(fps) and 0 < fps <= 1000):
        raise TrajectoryError(f"--fps must be in (0, 1000], got {fps:g}")
    count = max(1, int(np.floor(seconds * fps + 1e-9)))
    frame_ns = np.rint(np.arange(count) * 1e9 / fps).astype(np.int64)
    poses = maker(frame_ns / 1e9, seconds)
    return [StampedPose(EPOCH_NS + int(ns), pose) for ns, pose in zip(frame_ns, poses, strict=True)]


def trajectory_at(name: str, times_s: np.ndarray, seconds: float) -> list[Transform]:
    """T_world_camera of the named trajectory (of ``seconds``) at any times (seconds from
    its start, stamp ``EPOCH_NS``): a wheel odometry's own clock (fakes/odometry.py)."""
    return _MAKERS[name](np.asarray(times_s, np.float64), seconds)
