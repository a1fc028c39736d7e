"""The robot of the randomized family (``fakes.family``) on its floor: where it may be
(``FreeFloor``: inside the walls, off the boxes and the cube) and how it drives there
(``Drive``: differential drive integrated at ``DT`` with bounded accelerations; ``wander``,
the family's motion from the start in front of the cube to the return to it)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from cubeloc.fakes.room import Room

DEG = np.pi / 180.0
CUBE_HALF = 0.09  # the standard cube: 18 cm, centre at the origin, standing on z = -0.09
DT = 0.01  # s, the motion's integration step
BASE_RADIUS = 0.3  # m, the robot's footprint: nothing comes closer to a wall, box or the cube
CAMERA_CLEARANCE = 0.15  # m, the camera from any wall or box face


class FreeFloor:
    """Where the robot's axis and its camera may be: inside the walls, off the boxes and the cube."""

    def __init__(self, room: Room, lever: float) -> None:
        self.room, self.lever = room, lever
        self.boxes = [(np.array(b.center[:2]), np.array(b.size[:2]) / 2) for b in room.boxes]
        self.boxes.append((np.zeros(2), np.array([CUBE_HALF, CUBE_HALF])))

    def clearance(self, xy: np.ndarray) -> float:
        """Distance from ``xy`` to the nearest wall or box footprint (negative inside one)."""
        r = self.room
        walls = min(xy[0] - r.x_range[0], r.x_range[1] - xy[0], xy[1] - r.y_range[0], r.y_range[1] - xy[1])
        nearest = walls
        for centre, half in self.boxes:
            d = np.abs(xy - centre) - half
            outside = np.linalg.norm(np.maximum(d, 0.0))
            nearest = min(nearest, outside if outside > 0 else float(np.max(d)))
        return float(nearest)

    def ok(self, x: float, y: float, heading: float) -> bool:
        base = np.array([x, y])
        camera = base + self.lever * np.array([np.cos(heading), np.sin(heading)])
        return self.clearance(base) >= BASE_RADIUS and self.clearance(camera) >= CAMERA_CLEARANCE

    def random_point(self, rng: np.random.Generator, margin: float = 0.6) -> np.ndarray:
        r = self.room
        for _ in range(500):
            p = np.array([rng.uniform(*r.x_range), rng.uniform(*r.y_range)])
            if self.clearance(p) >= margin + BASE_RADIUS:
                return p
        raise RuntimeError("no free floor")

    def segment_clear(self, a: np.ndarray, b: np.ndarray, margin: float) -> bool:
        """The straight way from ``a`` to ``b`` keeps ``margin`` from everything, but for its
        first half metre (a robot that stopped close to a wall may leave it)."""
        length = float(np.linalg.norm(b - a))
        steps = max(2, int(length / 0.1))
        return all(self.clearance(a + s * (b - a)) >= margin for s in np.linspace(0.0, 1.0, steps)
                   if s * length >= 0.5)


# --------------------------------------------------------------------------- the robot


class Drive:
    """A differential-drive robot's motion, integrated at ``DT`` with bounded accelerations."""

    def __init__(self, robot, free: FreeFloor, x: float, y: float, heading: float) -> None:
        self.robot, self.free = robot, free
        self.state = np.array([x, y, heading])
        self.v = self.w = 0.0
        self.rows: list[tuple[float, float, float, float]] = [(0.0, x, y, heading)]

    @property
    def t(self) -> float:
        return self.rows[-1][0]

    def _try(self, control, timeout_s: float) -> list | None:
        """Rows of one segment under ``control(state, v, w, t) -> (v*, w*, done)``, ending at
        rest; None if it would leave the free floor."""
        r = self.robot
        state, v, w, t = self.state.copy(), self.v, self.w, self.t
        rows, elapsed, done = [], 0.0, False
        w_max = r.turn_deg_s * DEG
        while elapsed < timeout_s + 5.0:
            if not done and elapsed < timeout_s:
                v_goal, w_goal, done = control(state, v, w, elapsed)
            else:
                v_goal = w_goal = 0.0
            v += float(np.clip(v_goal - v, -r.accel_m_s2 * DT, r.accel_m_s2 * DT))
            w += float(np.clip(np.clip(w_goal, -w_max, w_max) - w, -r.angular_accel_rad_s2 * DT,
                               r.angular_accel_rad_s2 * DT))
            state = state + DT * np.array([v * np.cos(state[2]), v * np.sin(state[2]), w])
            t += DT
            elapsed += DT
            if not self.free.ok(state[0], state[1], state[2]):
                return None
            rows.append((t, *state))
            if (done or elapsed >= timeout_s) and abs(v) < 1e-3 and abs(w) < 1e-3:
                return rows
        return rows

    def run(self, control, timeout_s: float) -> bool:
        rows = self._try(control, timeout_s)
        if not rows:
            return False
        self.rows += rows
        self.state = np.array(rows[-1][1:])
        self.v = self.w = 0.0
        return True

    def stop(self, seconds: float) -> None:
        x, y, h = self.state
        start = self.t
        self.rows += [(start + k * DT, x, y, h) for k in range(1, int(seconds / DT) + 1)]

    # primitives ------------------------------------------------------------------------
    def turn_to(self, heading: float) -> bool:
        a = self.robot.angular_accel_rad_s2

        def control(state, v, w, _t):
            error = wrap(heading - state[2])
            rate = np.sign(error) * min(self.robot.turn_deg_s * DEG, np.sqrt(2 * a * abs(error)))
            return 0.0, rate, abs(error) < 0.005

        return self.run(control, 20.0)

    def drive_to(self, goal: np.ndarray, weave: float = 0.0, reverse: bool = False) -> bool:
        a = self.robot.accel_m_s2
        period = 4.0

        def control(state, v, w, t):
            delta = goal - state[:2]
            distance = float(np.linalg.norm(delta))
            bearing = np.arctan2(delta[1], delta[0]) + (np.pi if reverse else 0.0)
            error = wrap(bearing - state[2])
            speed = min(self.robot.speed_m_s, np.sqrt(2 * a * distance)) * max(0.0, np.cos(error)) ** 2
            turn = 2.5 * error + weave * np.sin(2 * np.pi * t / period) * min(1.0, distance)
            return (-speed if reverse else speed), turn, distance < 0.05

        limit = 3.0 * np.linalg.norm(goal - self.state[:2]) / max(self.robot.speed_m_s, 0.1) + 10.0
        return self.run(control, limit)


def wrap(angle: float) -> float:
    return float((angle + np.pi) % (2 * np.pi) - np.pi)




def wander(rng, free: FreeFloor, robot, start, wander_s: float, want: set[str]):
    """The differential-drive rows (t, x, y, heading) and the blank-wall stop, if any."""
    base, heading, _ = start
    drive = Drive(robot, free, base[0], base[1], heading)
    # initialisation, slowly, the cube in view: a side-step (turn a little, drive 0.3-0.45 m,
    # face the cube again: a sideways baseline) or backing off with a slight sway (parallax
    # only off the line of sight: a weak start in a large hall), one or the other by the seed
    slow = replace(robot, speed_m_s=0.12)
    first = Drive(slow, free, base[0], base[1], heading)
    if rng.random() < 0.5:
        offset = float(rng.choice([-1.0, 1.0])) * min(25.0, 0.3 * robot.hfov_deg) * DEG
        ahead = base + rng.uniform(0.3, 0.45) * np.array([np.cos(heading + offset), np.sin(heading + offset)])
        started = first.turn_to(heading + offset) and first.drive_to(ahead) and \
            first.turn_to(float(np.arctan2(-first.state[1], -first.state[0])))
    else:
        backwards = base - 0.35 * np.array([np.cos(heading), np.sin(heading)])
        started = first.drive_to(backwards, weave=0.15, reverse=True)
    if started:
        drive.rows, drive.state = first.rows, first.state
    else:
        drive.stop(3.0)
    visited = [drive.state[:2].copy()]
    wall_stop = None
    wall_at = rng.uniform(0.2, 0.8) * wander_s if "blank_wall" in want else None
    turns_on_spot = []
    start_wander = drive.t
    attempts = 0
    while drive.t - start_wander < wander_s and attempts < 400:
        attempts += 1
        if wall_at is not None and wall_stop is None and drive.t - start_wander > wall_at:
            wall_stop = face_a_wall(rng, free, drive, turns_on_spot)
            if wall_stop is None:
                wall_at += 5.0
            continue
        revisit = len(visited) > 3 and rng.random() < 0.35
        goal = visited[int(rng.integers(0, len(visited) - 1))] if revisit else free.random_point(rng)
        if np.linalg.norm(goal - drive.state[:2]) < 1.0 or not free.segment_clear(drive.state[:2], goal, 0.45):
            continue
        bearing = float(np.arctan2(*(goal - drive.state[:2])[::-1]))
        if rng.random() < 0.6:
            before = drive.state[2]
            if not drive.turn_to(bearing):
                continue
            turns_on_spot.append(abs(wrap(bearing - before)))
        weave = float(rng.uniform(0.2, 0.8)) if rng.random() < 0.4 else 0.0
        if not (drive.drive_to(goal, weave) or drive.drive_to(goal)):
            continue
        visited.append(goal.copy())
        if rng.random() < 0.25:
            drive.stop(float(rng.uniform(0.5, 2.0)))
        if rng.random() < 0.15:
            back = drive.state[:2] - rng.uniform(0.3, 1.0) * np.array([np.cos(drive.state[2]), np.sin(drive.state[2])])
            drive.drive_to(back, reverse=True)
    # back to the cube: to where the robot started, facing it, and 2 s still
    for _ in range(4):
        target = start[0]
        if free.segment_clear(drive.state[:2], target, 0.4):
            bearing = float(np.arctan2(*(target - drive.state[:2])[::-1]))
            before = drive.state[2]
            drive.turn_to(bearing)
            turns_on_spot.append(abs(wrap(bearing - before)))
            if drive.drive_to(target):
                break
        hop = free.random_point(rng)  # round an obstacle: via a free point first
        if free.segment_clear(drive.state[:2], hop, 0.45) and free.segment_clear(hop, target, 0.45):
            drive.turn_to(float(np.arctan2(*(hop - drive.state[:2])[::-1])))
            drive.drive_to(hop)
    facing = float(np.arctan2(-drive.state[1], -drive.state[0]))
    before = drive.state[2]
    drive.turn_to(facing)
    turns_on_spot.append(abs(wrap(facing - before)))
    drive.stop(2.0)
    return np.array(drive.rows), wall_stop, turns_on_spot


def face_a_wall(rng, free: FreeFloor, drive: Drive, turns_on_spot: list) -> tuple | None:
    """Drive to 0.6-1.0 m from a wall, turn to face it, stay 1-3 s, turn back: the stop's
    (wall axis, wall coordinate, camera xy, seconds, start time)."""
    r = free.room
    walls = [(0, r.x_range[0], -1), (0, r.x_range[1], 1), (1, r.y_range[0], -1), (1, r.y_range[1], 1)]
    axis, at, sign = walls[int(rng.integers(0, 4))]
    away = rng.uniform(0.6, 1.0) + free.lever
    span = r.y_range if axis == 0 else r.x_range
    along = rng.uniform(span[0] + 1.0, span[1] - 1.0)
    goal = np.array([at - sign * away, along]) if axis == 0 else np.array([along, at - sign * away])
    if free.clearance(goal) < BASE_RADIUS + 0.2 or not free.segment_clear(drive.state[:2], goal, 0.45):
        return None
    before = drive.state[2]
    bearing = float(np.arctan2(*(goal - drive.state[:2])[::-1]))
    if not (drive.turn_to(bearing) and drive.drive_to(goal)):
        return None
    turns_on_spot.append(abs(wrap(bearing - before)))
    facing = 0.0 if (axis, sign) == (0, 1) else np.pi if axis == 0 else (np.pi / 2 if sign == 1 else -np.pi / 2)
    before = drive.state[2]
    drive.turn_to(facing)
    turns_on_spot.append(abs(wrap(facing - before)))
    started = drive.t
    seconds = float(rng.uniform(1.0, 3.0))
    drive.stop(seconds)
    drive.turn_to(before)
    turns_on_spot.append(abs(wrap(before - facing)))
    return axis, at, sign, drive.state[:2].copy(), seconds, started
