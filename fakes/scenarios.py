"""Robot-motion scenarios: trajectories a wheeled robot really drives, and what moves
or changes in the view while it does (passers-by, auto-exposure, motion blur).

Every scenario starts as the others do (``fakes.trajectories``): the camera ~2.1 m from
the cube, looking at it, and drifting a little sideways for the parallax that
initialisation needs. The camera is 1 m above the floor with no roll, as on a robot.

=====================  =================================================================
``turn_after_init``    3 s on the cube, then a 110 deg turn away (peak 44 deg/s) while
                       driving at 0.12-0.3 m/s, a lap of the room looking ahead (cube out of
                       view for ~70 s), and a turn back to face it; >= 75 s, 10 fps
``spin_in_place``      a robot turning on the spot with the camera 0.2 m ahead of the
                       axis: 2 turns at 45 deg/s right after initialisation; 10 fps
``spin_in_place_fast`` the same at 90 deg/s, 30 fps
``spin_brisk``         the same at 120 deg/s at 10 fps (12 deg a frame), 8 ms exposure (motion
                       blur ~1 deg, ~14 px at 640x512)
``spin_on_axis``       the camera on the axis (pure rotation, no parallax): 45 deg/s
``agile``              yaw swings of +-50 deg (63 deg/s, ~80 as they start) that take the cube in and
                       out of view while drifting along an arc; 4 ms exposure (motion
                       blur up to ~8 px, integrated over the exposure) and auto-exposure
                       steps of gain 0.7-1.35 every 2-4 s; 30 fps
``passers_by``         a slow drive past the cube and away while person-sized textured
                       slabs walk across the view 0.6-1.8 m from the camera, one over the
                       cube during initialisation; 10 fps
``blank_wall``         a drive along the room, a turn to face a freshly painted wall from
                       1.2 m (~3 s of view with a few scuffs for all texture), and back;
                       10 fps
``long_lap``           110 s: a lap of the room with the cube out of view >= 80 s, radius,
                       heading and tilt wandering, back to the cube at the end; 10 fps
``laps``               three laps of the room as ``long_lap`` drives it (~50 m), each lap's
                       radius, heading and tilt a little off the others', the cube out of
                       view for ~185 s, back to it at the end; 200 s, 10 fps (loop closure)
=====================  =================================================================

The effects (``Effects``) are seeded by the scenario alone, so a sequence is the same
every time: ``scenario_effects(name, trajectory)``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np
from scipy.interpolate import CubicSpline

from cubeloc.fakes.room import Box, box_quads, plain_paint
from cubeloc.fakes.surfaces import Quad, TextureShader
from cubeloc.positioning.geometry import Transform, look_at
from cubeloc.positioning.trajectory_io import StampedPose

DEG = np.pi / 180.0
HEIGHT = 0.91  # camera 1 m above the floor (z = -0.09)
START = np.array([1.5, -1.5])  # as fakes.trajectories.START_POSITION
# scenario -> (default seconds, default fps, minimum seconds)
TIMING = {
    "turn_after_init": (80.0, 10.0, 75.0),
    "spin_in_place": (22.0, 10.0, 14.0),
    "spin_in_place_fast": (14.0, 30.0, 10.0),
    "spin_brisk": (14.0, 10.0, 14.0),
    "spin_on_axis": (22.0, 10.0, 14.0),
    "agile": (24.0, 30.0, 12.0),
    "passers_by": (30.0, 10.0, 24.0),
    "blank_wall": (26.0, 10.0, 22.0),
    "long_lap": (110.0, 10.0, 100.0),
    "laps": (200.0, 10.0, 150.0),
}


def clamped_spline(rows, times: np.ndarray) -> np.ndarray:
    """Clamped cubic spline (zero velocity at both ends) through ``rows`` of (t, values...),
    evaluated at ``times`` (held past the ends): every scripted trajectory's poses."""
    keyframes = np.asarray(rows, dtype=np.float64)
    spline = CubicSpline(keyframes[:, 0], keyframes[:, 1:], axis=0, bc_type="clamped")
    return spline(np.clip(times, keyframes[0, 0], keyframes[-1, 0]))


def _stop_and_go(rows: list[list[float]], times: np.ndarray) -> np.ndarray:
    """Rows (t, values...) joined by smoothstep segments: at rest at every row (a robot
    that stops, turns, stops), no overshoot between rows."""
    keyframes = np.array(rows, dtype=np.float64)
    t = np.clip(times, keyframes[0, 0], keyframes[-1, 0])
    k = np.clip(np.searchsorted(keyframes[:, 0], t, side="right") - 1, 0, len(keyframes) - 2)
    a, b = keyframes[k], keyframes[k + 1]
    s = _smoothstep((t - a[:, 0]) / (b[:, 0] - a[:, 0]))[:, None]
    return a[:, 1:] + s * (b[:, 1:] - a[:, 1:])


def _camera(x: float, y: float, yaw: float, pitch: float, z: float = HEIGHT) -> Transform:
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), -np.sin(pitch)])
    position = np.array([x, y, z])
    return look_at(position, position + forward)


def _look_at_cube(x: float, y: float) -> tuple[float, float]:
    """Yaw and pitch from (x, y) at camera height to the cube's centre."""
    return float(np.arctan2(-y, -x)), float(np.arctan2(HEIGHT, np.hypot(x, y)))


def _smoothstep(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def _polar(azimuth: float, radius: float) -> tuple[float, float]:
    return radius * np.cos(azimuth), radius * np.sin(azimuth)


# --------------------------------------------------------------------------- trajectories
def _start_rows() -> tuple[float, float]:
    return float(np.arctan2(START[1], START[0])), float(np.hypot(*START))


def _on_the_cube(round_deg: float, until_s: float) -> list[list[float]]:
    """The opening rows (t, x, y, yaw, pitch): from the start, ``round_deg`` round the cube
    by ``until_s``, looking at it all the way (the parallax initialisation needs)."""
    a0, r0 = _start_rows()
    x1, y1 = _polar(a0 + round_deg * DEG, r0)
    return [[0.0, *START, *_look_at_cube(*START)], [until_s, x1, y1, *_look_at_cube(x1, y1)]]


def _back_on_the_cube(rows: list[list[float]], azimuth: float, radius: float, seconds: float) -> list[list[float]]:
    """The closing rows: at ``azimuth``/``radius`` facing the cube for the last 3 s, the
    yaw unwrapped to the nearest turn from the last row's."""
    xe, ye = _polar(azimuth, radius)
    yaw_e, pitch_e = _look_at_cube(xe, ye)
    yaw_e += 2 * np.pi * round((rows[-1][3] - yaw_e) / (2 * np.pi))
    return [[seconds - 3.0, xe, ye, yaw_e, pitch_e], [seconds, xe, ye, yaw_e, pitch_e]]


def _turn_after_init(times: np.ndarray, seconds: float) -> list[Transform]:
    a0, _ = _start_rows()
    rows = _on_the_cube(7, 3.0)
    yaw1 = rows[-1][3]
    # the turn: 110 deg to the right in 3 s, driving on round the cube
    x2, y2 = _polar(a0 + 16 * DEG, 2.3)
    rows.append([6.0, x2, y2, yaw1 - 110 * DEG, 10 * DEG])
    # the lap: counter-clockwise at 2.3-2.9 m, looking ahead and a little outwards
    lap_end = seconds - 8.0
    for fraction in np.linspace(0.0, 1.0, 9)[1:]:
        azimuth = a0 + 16 * DEG + fraction * 300 * DEG
        radius = 2.6 + 0.3 * np.sin(3 * azimuth)
        rows.append([6.0 + fraction * (lap_end - 6.0), *_polar(azimuth, radius), azimuth + 60 * DEG, 10 * DEG])
    rows += _back_on_the_cube(rows, a0 + 340 * DEG, 2.2, seconds)  # and back: face the cube again
    return [_camera(x, y, yaw, pitch) for x, y, yaw, pitch in clamped_spline(rows, times)]


def spin(times: np.ndarray, seconds: float, lever_m: float, rate_deg_s: float) -> list[Transform]:
    """Initialise for 2.5 s (a slow drive round the cube), then turn on the spot about a
    vertical axis ``lever_m`` behind the camera at ``rate_deg_s`` (0.5 s ramps), as many
    degrees as the time allows up to two turns, and come to rest facing the cube."""
    a0, r0 = _start_rows()
    x1, y1 = _polar(a0 + 6 * DEG, r0)
    yaw0, pitch0 = _look_at_cube(*START)
    yaw1, pitch1 = _look_at_cube(x1, y1)
    init = clamped_spline([[0.0, *START, yaw0, pitch0], [2.5, x1, y1, yaw1, pitch1]], times)
    turn_s = min(seconds - 4.0, 720.0 / rate_deg_s + 0.5)
    turns = max(1, int(np.floor(rate_deg_s * (turn_s - 0.5) / 360.0)))
    total = turns * 2 * np.pi
    ramp = 0.5
    cruise = total / (rate_deg_s * DEG) - ramp  # ramps of `ramp` s each add ramp/2 of angle-time
    poses = []
    # the axis stays where the camera's mount point was at the end of initialisation
    axis = np.array([x1, y1]) - lever_m * np.array([np.cos(yaw1), np.sin(yaw1)])
    for t, (x, y, yaw, pitch) in zip(times, init, strict=True):
        if t > 2.5:
            s = t - 2.5
            omega = rate_deg_s * DEG
            # trapezoid rate profile: up in `ramp` s, cruise, down in `ramp` s
            if s < ramp:
                angle = 0.5 * omega * s * s / ramp
            elif s < ramp + cruise:
                angle = 0.5 * omega * ramp + omega * (s - ramp)
            elif s < 2 * ramp + cruise:
                u = s - ramp - cruise
                angle = 0.5 * omega * ramp + omega * cruise + omega * u - 0.5 * omega * u * u / ramp
            else:
                angle = total
            yaw = yaw1 + angle
            x, y = axis + lever_m * np.array([np.cos(yaw), np.sin(yaw)])
            pitch = pitch1
        poses.append(_camera(x, y, yaw, pitch))
    return poses


def _agile(times: np.ndarray, seconds: float) -> list[Transform]:
    """Yaw swings of +-50 deg about the direction of the cube, period 5 s (63 deg/s at
    the peak), while drifting 0.1 m/s round it and the tilt nodding +-3 deg."""
    a0, r0 = _start_rows()
    poses = []
    for t in times:
        azimuth = a0 + 0.1 * t / r0 * np.clip(t / 2.0, 0.0, 1.0)
        x, y = _polar(azimuth, r0 + 0.2 * np.sin(2 * np.pi * t / 17.0))
        yaw_c, pitch_c = _look_at_cube(x, y)
        # start still for 1.5 s (initialisation), then swing
        swing = 50 * DEG * np.sin(2 * np.pi * (t - 1.5) / 5.0) * _smoothstep(np.array((t - 1.5) / 1.0))
        poses.append(_camera(x, y, yaw_c + float(swing), pitch_c + 3 * DEG * np.sin(2 * np.pi * t / 9.0)))
    return poses


def _passers_by(times: np.ndarray, seconds: float) -> list[Transform]:
    """A slow drive (0.15 m/s) round the cube looking at it for 10 s, a turn 80 deg away
    over 5 s driving on, then back to the cube for the last 3 s."""
    a0, r0 = _start_rows()
    azimuth = clamped_spline([[0.0, a0], [seconds - 3.0, a0 + 120 * DEG], [seconds, a0 + 120 * DEG]], times)[:, 0]
    away = 80 * DEG * (_smoothstep((times - 10.0) / 5.0) - _smoothstep((times - (seconds - 8.0)) / 5.0))
    poses = []
    for a, offset in zip(azimuth, away, strict=True):
        x, y = _polar(a, r0)
        yaw, pitch = _look_at_cube(x, y)
        poses.append(_camera(x, y, yaw + offset, pitch))
    return poses


BLANK_WALL_X = 5.0 - 0.05  # the painted panel stands 5 cm in front of the +x wall


def _blank_wall(times: np.ndarray, seconds: float) -> list[Transform]:
    """From the cube, drive along the room towards the +x wall looking along it (its
    textured neighbours in view), stop, turn 90 deg right (2.5 s) to face the painted panel
    from 1.2 m, hold 1 s, turn back left to the view it came with, and on round to drive
    back to the cube. The view is all panel for ~3 s (it is 2.4 m wide)."""
    yaw0, pitch0 = _look_at_cube(*START)
    near = BLANK_WALL_X - 1.2
    middle = seconds / 2
    along = 90 * DEG  # looking along the wall (+y)
    xe, ye = 1.8, -1.8
    yaw_e, pitch_e = _look_at_cube(xe, ye)
    rows = [[0.0, *START, yaw0, pitch0], [3.0, 1.7, -1.35, yaw0 - 8 * DEG, pitch0],
            [middle - 7.0, 2.6, -1.3, along + 15 * DEG, 5 * DEG],
            [middle - 3.75, near, -0.3, along, 0.0],
            [middle - 1.25, near, -0.3, 0.0, 0.0], [middle - 0.25, near, -0.3, 0.0, 0.0],
            [middle + 2.25, near, -0.3, along, 0.0],
            [seconds - 2.5, xe, ye, yaw_e, pitch_e], [seconds, xe, ye, yaw_e, pitch_e]]
    return [_camera(x, y, yaw, pitch) for x, y, yaw, pitch in _stop_and_go(rows, times)]


def _long_lap(times: np.ndarray, seconds: float) -> list[Transform]:
    a0, _ = _start_rows()
    rows = _on_the_cube(6, 3.0)
    lap_end = seconds - 8.0
    steps = 16
    for k in range(1, steps + 1):
        fraction = k / steps
        azimuth = a0 + 6 * DEG + fraction * 320 * DEG
        radius = 2.7 + 0.5 * np.sin(2 * azimuth + 1.0)
        heading = azimuth + (75 + 25 * np.sin(5 * fraction * np.pi)) * DEG
        tilt = (12 + 6 * np.sin(3 * fraction * np.pi)) * DEG
        rows.append([3.0 + fraction * (lap_end - 3.0), *_polar(azimuth, radius), heading, tilt])
    rows += _back_on_the_cube(rows, a0 + 345 * DEG, 2.2, seconds)
    return [_camera(x, y, yaw, pitch) for x, y, yaw, pitch in clamped_spline(rows, times)]


def _laps(times: np.ndarray, seconds: float, laps: int = 3) -> list[Transform]:
    """``laps`` turns round the cube on ``long_lap``'s route; each lap is offset in radius
    (0.15 m), heading (8 deg) and tilt (3 deg) from the one before, so a place is seen
    again from a slightly different pose, as a robot repeating a route sees it."""
    a0, _ = _start_rows()
    rows = _on_the_cube(6, 3.0)
    lap_end = seconds - 8.0
    steps = 16 * laps
    for k in range(1, steps + 1):
        fraction = k / steps
        lap = min(int(fraction * laps), laps - 1)
        within = fraction * laps - lap
        azimuth = a0 + 6 * DEG + fraction * (laps * 360 - 40) * DEG
        offset = (-1.0, 1.0, 0.0)[lap % 3]
        radius = 2.7 + 0.5 * np.sin(2 * azimuth + 1.0) + 0.15 * offset
        heading = azimuth + (75 + 25 * np.sin(5 * within * np.pi) + 8 * offset) * DEG
        tilt = (12 + 6 * np.sin(3 * within * np.pi) + 3 * offset) * DEG
        rows.append([3.0 + fraction * (lap_end - 3.0), *_polar(azimuth, radius), heading, tilt])
    rows += _back_on_the_cube(rows, a0 + (laps * 360 - 15) * DEG, 2.2, seconds)
    return [_camera(x, y, yaw, pitch) for x, y, yaw, pitch in clamped_spline(rows, times)]


MAKERS = {
    "turn_after_init": _turn_after_init,
    "spin_in_place": lambda t, s: spin(t, s, 0.2, 45.0),
    "spin_in_place_fast": lambda t, s: spin(t, s, 0.2, 90.0),
    "spin_brisk": lambda t, s: spin(t, s, 0.2, 120.0),
    "spin_on_axis": lambda t, s: spin(t, s, 0.0, 45.0),
    "agile": _agile,
    "passers_by": _passers_by,
    "blank_wall": _blank_wall,
    "long_lap": _long_lap,
    "laps": _laps,
}


# --------------------------------------------------------------------------- effects
@dataclass(frozen=True)
class Walker:
    """A passer-by: a person-sized textured slab (0.5 x 0.25 x 1.75 m) walking in a
    straight line on the floor, from ``start`` at ``t0`` with ``velocity`` (m/s)."""

    start: tuple[float, float]
    velocity: tuple[float, float]
    t0: float
    t1: float
    seed: int

    def quads_at(self, t: float) -> tuple[Quad, ...]:
        if not self.t0 <= t <= self.t1:
            return ()
        x = self.start[0] + self.velocity[0] * (t - self.t0)
        y = self.start[1] + self.velocity[1] * (t - self.t0)
        shift = np.array([x, y, 0.0])
        return tuple(replace(q, origin=np.asarray(q.origin) + shift) for q in _walker_quads(self.seed))


@functools.lru_cache(maxsize=16)
def _walker_quads(seed: int) -> tuple[Quad, ...]:
    """The slab at the origin (standing on the floor), its textures built once."""
    return box_quads(Box(center=(0.0, 0.0, -0.09 + 0.875), size=(0.5, 0.25, 1.75), seed=1000 + seed))


@dataclass(frozen=True)
class Effects:
    """What changes in the view besides the camera: per-frame extras for the renderer."""

    exposure_s: float = 0.0  # motion blur: the frame is the mean of renders over this time
    gain_steps: tuple[tuple[float, float], ...] = ()  # (from t [s], exposure gain) in order
    walkers: tuple[Walker, ...] = ()
    static_quads: tuple[Quad, ...] = ()  # fixed extra surfaces (the painted wall)

    def gain_at(self, t: float) -> float:
        gain = 1.0
        for start, value in self.gain_steps:
            if t >= start:
                gain = value
        return gain

    def objects_at(self, t: float) -> tuple[tuple[Quad, ...], ...]:
        """Extra objects in view at trajectory time ``t``: one group of quads each."""
        groups = [w.quads_at(t) for w in self.walkers]
        if self.static_quads:
            groups.append(self.static_quads)
        return tuple(g for g in groups if g)


def walkers_across(poses: list[Transform], times: np.ndarray, crossings: list[tuple[float, float, float]],
                   seed: int) -> tuple[Walker, ...]:
    """Walkers that cross the line of sight at (time, distance ahead m, speed m/s), from
    left to right and back alternately, walking 2.4 s each side of the crossing."""
    walkers = []
    for k, (t_cross, distance, speed) in enumerate(crossings):
        i = int(np.argmin(np.abs(times - t_cross)))
        pose = poses[i]
        forward = pose.rotation[:, 2].copy()
        forward[2] = 0.0
        forward /= np.linalg.norm(forward)
        side = np.array([-forward[1], forward[0], 0.0]) * (1 if k % 2 == 0 else -1)
        crossing = pose.translation + distance * forward
        start = crossing - side * speed * 2.4
        walkers.append(Walker((float(start[0]), float(start[1])), (float(side[0] * speed), float(side[1] * speed)),
                              t_cross - 2.4, t_cross + 2.4, seed + k))
    return tuple(walkers)


@functools.lru_cache(maxsize=2)
def painted_wall() -> tuple[Quad, ...]:
    """A freshly painted panel, 2.4 m x 2.8 m, before the +x wall: flat paint with faint
    roller marks and a handful of scuffs (a few corners, far fewer than the room's)."""
    texel = 0.004
    rng = np.random.default_rng(42)
    h, w = int(2.8 / texel), int(2.4 / texel)
    texture = plain_paint(h, w, rng)
    origin = np.array([BLANK_WALL_X, 0.9, 2.85])  # top-left seen from inside (looking +x)
    return (Quad(origin, np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, -1.0]), 2.4, 2.8,
                 TextureShader(texture, texel)),)


def scenario_effects(name: str, trajectory: list[StampedPose]) -> Effects:
    """The effects of scenario ``name`` along ``trajectory`` (none for other names)."""
    if name not in TIMING or not trajectory:
        return Effects()
    times = np.array([(p.stamp_ns - trajectory[0].stamp_ns) / 1e9 for p in trajectory])
    return make_effects(name, [p.T_world_camera for p in trajectory], times)


def make_effects(name: str, poses: list[Transform], times: np.ndarray) -> Effects:
    """The scenario's effects along its own poses (times in seconds from the start)."""
    seconds = float(times[-1]) if len(times) else 0.0
    if name == "agile":
        rng = np.random.default_rng(7)
        steps, t = [], 2.0
        while t < seconds:
            steps.append((t, float(rng.uniform(0.7, 1.35))))
            t += float(rng.uniform(2.0, 4.0))
        return Effects(exposure_s=0.004, gain_steps=tuple(steps))
    if name == "spin_brisk":
        return Effects(exposure_s=0.008)
    if name == "passers_by":
        # one over the cube during initialisation (0.5 s in), two later at other distances
        crossings = [(1.2, 1.0, 1.2), (8.0, 0.6, 1.0), (min(18.0, seconds - 6.0), 1.8, 1.4)]
        return Effects(walkers=walkers_across(poses, times, crossings, seed=5))
    if name == "blank_wall":
        return Effects(static_quads=painted_wall())
    return Effects()
