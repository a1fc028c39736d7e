"""A randomized family of scenes, robots and motions: a case never seen before is one seed away.

``make_case(seed)`` draws, from that seed alone:

- **a scene**: a room (5 x 5 m to 12 x 10 m), a hall (up to 40 x 20 m) or a corridor (2-3 m
  wide, 12-30 m long); a ceiling of 2.5-8 m; shelves along the walls and boxes near them;
  walls from richly textured to 70 % plain paint; a textured or a plain floor; the 18 cm
  cube on the floor or on a table (0.7-0.8 m);
- **a robot**: the camera 0.2-1.5 m above the floor, pitched -30 to +10 deg (up is
  positive), 0-0.4 m ahead of the axis the robot turns about; a lens of 30-100 deg HFOV
  with barrel distortion that grows with the field; 10, 20, 30 or 60 fps; an exposure of
  1-8 ms whose motion blur is integrated over it;
- **a motion** of a differential-drive robot (speed up to 1.2 m/s, turn rate up to 120
  deg/s, accelerations bounded): it starts in front of the cube (backing off slowly, the
  parallax initialisation needs), then a random mix of turns on the spot, straight drives,
  S-curves, reversing and stops between goals in the free floor, some of them places it
  has been before; 20-150 s of wandering, then back to the cube;
- **disturbances**: passers-by, auto-exposure steps, the light falling to 30 % over 25 s
  and coming back, 1-3 s facing a freshly painted (blank) wall.

A case is *unobservable by construction* over a stretch when no camera-only tracker can
know its position there: a blank wall filling the view (``blank_wall``), or turns on the
spot with the camera on the axis (``rotation_on_axis``: no parallax). ``unobservable``
names them; a tracker keeps the orientation there and holds the position with a growing
covariance.

Resolutions: ``full`` is 1280x1024; ``half`` is the same lens at 640x512 (every other
draw the same), for day-to-day work.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace

import numpy as np

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.fakes.camera import RenderOptions
from cubeloc.fakes.drive import CUBE_HALF, DEG, FreeFloor, wander
from cubeloc.fakes.room import WALL_AXES, Box, Room, plain_paint, plain_span
from cubeloc.fakes.scenarios import Effects, walkers_across
from cubeloc.fakes.surfaces import Quad, TextureShader
from cubeloc.fakes.trajectories import EPOCH_NS, camera_from_yaw_pitch
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.target import make_cube
from cubeloc.positioning.trajectory_io import StampedPose

RENDER_VERSION = 1  # bumped when the renderer or the textures change what a case's frames show
RESOLUTIONS = {"full": (1280, 1024), "half": (640, 512)}
MAX_ATLAS_TEXELS = 5000  # the longest wall at most this many texels (4 mm, coarser in halls)
# A view is blank when fewer than this share of its rays meet texture (not plain paint), and
# a case is unobservable by construction when its view stays blank this long
BLANK_VIEW_SHARE = 0.15
BLANK_VIEW_S = 1.0


@dataclass(frozen=True)
class Robot:
    height_m: float  # camera above the floor
    pitch_deg: float  # up positive
    lever_m: float  # camera ahead of the turning axis
    hfov_deg: float
    k1: float
    k2: float
    fps: float
    exposure_s: float
    speed_m_s: float  # cruise speed
    turn_deg_s: float  # turn-rate limit
    accel_m_s2: float
    angular_accel_rad_s2: float


@dataclass(frozen=True)
class FamilyCase:
    """One member of the family: everything to render it and score a tracker on it."""

    seed: int
    resolution: str
    kind: str  # room, hall, corridor
    room: Room
    table_m: float  # the cube's table height (0: on the floor)
    robot: Robot
    calibration: CameraCalibration
    poses: tuple[StampedPose, ...]
    effects: Effects
    disturbances: tuple[str, ...]
    unobservable: tuple[str, ...]
    target_visible: tuple[bool, ...]  # per frame: the cube's centre in the image, in front
    textured: tuple[float, ...]  # per frame: the share of the view on texture (walls' plain paint, panels not)
    noise_sigma: float = 2.0
    extras: dict = field(default_factory=dict)

    @property
    def seconds(self) -> float:
        return (self.poses[-1].stamp_ns - self.poses[0].stamp_ns) / 1e9

    @property
    def render_options(self) -> RenderOptions:
        return RenderOptions(noise_sigma=self.noise_sigma)

    def path_since_target(self) -> np.ndarray:
        """Per frame, metres the camera travelled since the cube was last in view."""
        positions = np.array([p.T_world_camera.translation for p in self.poses])
        steps = np.r_[0.0, np.linalg.norm(np.diff(positions, axis=0), axis=1)]
        out, since = np.zeros(len(steps)), 0.0
        for i, (step, seen) in enumerate(zip(steps, self.target_visible, strict=True)):
            since = 0.0 if seen else since + step
            out[i] = since
        return out

    def longest_target_absence_s(self) -> float:
        longest = run = 0
        for seen in self.target_visible:
            run = 0 if seen else run + 1
            longest = max(longest, run)
        return longest / self.robot.fps

    def describe(self) -> dict:
        """The draws, as JSON-able numbers (``family.json`` beside a rendered case)."""
        r = self.robot
        positions = np.array([p.T_world_camera.translation for p in self.poses])
        return {
            "seed": self.seed, "resolution": self.resolution, "kind": self.kind,
            "room_m": [round(self.room.x_range[1] - self.room.x_range[0], 2),
                       round(self.room.y_range[1] - self.room.y_range[0], 2),
                       round(self.room.z_range[1] - self.room.z_range[0], 2)],
            "boxes": len(self.room.boxes), "plain_walls": [round(p, 2) for p in self.room.plain],
            "table_m": round(self.table_m, 3),
            "camera": {"height_m": round(r.height_m, 3), "pitch_deg": round(r.pitch_deg, 1),
                       "lever_m": round(r.lever_m, 3), "hfov_deg": round(r.hfov_deg, 1),
                       "k1": round(r.k1, 4), "k2": round(r.k2, 4), "fps": r.fps,
                       "exposure_ms": round(r.exposure_s * 1e3, 2)},
            "motion": {"speed_m_s": round(r.speed_m_s, 2), "turn_deg_s": round(r.turn_deg_s, 1),
                       "seconds": round(self.seconds, 1), "frames": len(self.poses),
                       "path_m": round(float(np.sum(np.linalg.norm(np.diff(positions, axis=0), axis=1))), 2),
                       "target_absent_s": round(self.longest_target_absence_s(), 1)},
            "disturbances": list(self.disturbances), "unobservable": list(self.unobservable),
            "least_textured_view": round(float(min(self.textured)), 3),
        }

    def render_key(self) -> str:
        """A digest of everything the frames depend on (poses, lens, room, effects, noise):
        a cached render with the same key has the same pixels."""
        import hashlib

        digest = hashlib.sha256()
        digest.update(np.array([[p.stamp_ns, *p.T_world_camera.matrix().ravel()] for p in self.poses]).tobytes())
        c = self.calibration
        digest.update(repr((c.width, c.height, c.camera_matrix.tolist(), c.distortion.tolist(), self.room,
                            self.noise_sigma, self.effects.exposure_s, self.effects.gain_steps,
                            self.effects.walkers, len(self.effects.static_quads), RENDER_VERSION)).encode())
        return digest.hexdigest()

    def describe_json(self) -> str:
        return json.dumps(self.describe(), indent=1) + "\n"


# --------------------------------------------------------------------------- the scene
def _scene(rng: np.random.Generator, seed: int) -> tuple[str, Room, float]:
    kind = str(rng.choice(["room", "room", "hall", "corridor"]))
    if kind == "room":
        size = (rng.uniform(5.0, 12.0), rng.uniform(5.0, 10.0))
        ceiling = rng.uniform(2.5, 4.0)
    elif kind == "hall":
        size = (rng.uniform(15.0, 40.0), rng.uniform(10.0, 20.0))
        ceiling = rng.uniform(4.0, 8.0)
    else:
        size = (rng.uniform(12.0, 30.0), rng.uniform(2.0, 3.0))
        ceiling = rng.uniform(2.5, 3.5)
    table = float(rng.uniform(0.7, 0.8)) if kind != "corridor" and rng.random() < 0.3 else 0.0
    floor = -CUBE_HALF - table
    # where the cube stands in the room: anywhere 1.5 m from the walls (a corridor's cube
    # near one side, so that the robot can start off its diagonal)
    if kind == "corridor":
        x0 = rng.uniform(2.5, size[0] - 2.5)
        y0 = 0.45
    else:
        x0 = rng.uniform(1.5, size[0] - 1.5)
        y0 = rng.uniform(1.5, size[1] - 1.5)
    x_range, y_range = (-x0, size[0] - x0), (-y0, size[1] - y0)
    texel = max(0.004, max(size) / MAX_ATLAS_TEXELS, ceiling / MAX_ATLAS_TEXELS)
    sparseness = 0.7 * rng.random() ** 2  # rooms from rich to sparse: up to 70 % of a wall plain paint
    plain = [float(np.clip(sparseness * rng.uniform(0.5, 1.0), 0.0, 0.7)) for _ in range(4)]
    plain += [1.0 if rng.random() < 0.2 else 0.0, 0.0]  # a plain or a textured floor; the ceiling as it is
    boxes = _furniture(rng, kind, x_range, y_range, floor, ceiling, table)
    room = Room(x_range, y_range, (floor, floor + ceiling), texel, seed, tuple(boxes), (), tuple(plain))
    return kind, room, table


def _furniture(rng, kind, x_range, y_range, floor, ceiling, table) -> list[Box]:
    """Shelves against the walls, boxes near them, a table under the cube: 2 m clear round it."""
    boxes = []
    if table > 0:
        boxes.append(Box((0.0, 0.0, floor + table / 2), (0.7, 0.7, table), seed=5000))
    walls = [(0, x_range[0]), (0, x_range[1]), (1, y_range[0]), (1, y_range[1])]
    for k in range(int(rng.integers(0, 5 if kind != "corridor" else 2))):
        axis, at = walls[int(rng.integers(0, 4))]
        other = y_range if axis == 0 else x_range
        length = min(rng.uniform(1.0, 4.0), other[1] - other[0] - 0.5)
        depth = rng.uniform(0.35, 0.6) if kind != "corridor" else 0.35
        height = min(rng.uniform(1.2, 2.5), ceiling - 0.2)
        along = rng.uniform(other[0] + length / 2, other[1] - length / 2)
        inward = 1.0 if at == (x_range[0] if axis == 0 else y_range[0]) else -1.0
        across = at + inward * depth / 2
        centre = (across, along) if axis == 0 else (along, across)
        size = (depth, length) if axis == 0 else (length, depth)
        boxes.append(Box((centre[0], centre[1], floor + height / 2), (size[0], size[1], height), seed=5001 + k))
    for k in range(int(rng.integers(0, 7 if kind != "corridor" else 2))):
        side = rng.uniform(0.3, 0.8)
        axis, at = walls[int(rng.integers(0, 4))]
        other = y_range if axis == 0 else x_range
        along = rng.uniform(other[0] + side, other[1] - side)
        inward = 1.0 if at == (x_range[0] if axis == 0 else y_range[0]) else -1.0
        across = at + inward * rng.uniform(side / 2 + 0.05, side / 2 + 1.0)
        centre = (across, along) if axis == 0 else (along, across)
        boxes.append(Box((centre[0], centre[1], floor + side / 2), (side, side, side), seed=5100 + k))
    # nothing within 2 m of the cube but its table: the start and the return need the room
    return [b for b in boxes if b.seed == 5000 or np.hypot(*b.center[:2]) - 0.5 * np.hypot(*b.size[:2]) > 2.0]


def _robot(rng: np.random.Generator, room: Room) -> Robot:
    fps = float(rng.choice([10.0, 20.0, 30.0, 60.0]))
    hfov = rng.uniform(30.0, 100.0)
    k1 = -rng.uniform(0.0, 0.3) * (hfov / 100.0) ** 2
    k2 = 0.5 * k1 * k1  # above 0.45 k1^2 the radial map never folds back: every pixel has a ray
    return Robot(
        height_m=float(rng.uniform(0.2, 1.5)), pitch_deg=0.0, lever_m=float(rng.uniform(0.0, 0.4)),
        hfov_deg=float(hfov), k1=float(k1), k2=float(k2), fps=fps,
        exposure_s=float(rng.uniform(0.001, 0.008)), speed_m_s=float(rng.uniform(0.15, 1.2)),
        turn_deg_s=float(rng.uniform(30.0, 120.0)), accel_m_s2=float(rng.uniform(0.3, 1.0)),
        angular_accel_rad_s2=float(rng.uniform(1.0, 4.0)),
    )


def lens(robot: Robot, resolution: str) -> CameraCalibration:
    width, height = RESOLUTIONS[resolution]
    f = width / 2.0 / np.tan(robot.hfov_deg * DEG / 2.0)
    k = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return CameraCalibration(width, height, k, np.array([robot.k1, robot.k2, 0.0, 0.0, 0.0]), "plumb_bob",
                             f"family-{resolution}")


# --------------------------------------------------------------------------- the motion
def _start(rng, free: FreeFloor, robot: Robot, calibration: CameraCalibration, table: float):
    """The first camera position (in front of the cube, two faces in view, the cube 75-130
    px across at half resolution) and the pitch that has the cube in view there."""
    width, height = RESOLUTIONS["full"]
    f = width / 2.0 / np.tan(robot.hfov_deg * DEG / 2.0)
    vfov = 2 * np.arctan(np.tan(robot.hfov_deg * DEG / 2.0) * height / width)
    floor = -CUBE_HALF - table
    for _ in range(400):
        span = rng.uniform(150.0, 260.0)  # px across at full resolution
        distance = float(np.clip(f * 2 * CUBE_HALF * 1.4 / span, 0.6, 3.5))
        azimuth = rng.integers(0, 4) * np.pi / 2 + np.pi / 4 + rng.uniform(-35, 35) * DEG
        camera = distance * np.array([np.cos(azimuth), np.sin(azimuth)])
        heading = azimuth + np.pi  # facing the cube
        base = camera - robot.lever_m * np.array([np.cos(heading), np.sin(heading)])
        if not free.ok(base[0], base[1], heading):
            continue
        z = floor + robot.height_m
        if table > 0 and z < -CUBE_HALF + 0.05:  # below the table top: the table hides the cube
            continue
        elevation = np.arctan2(-z, distance) / DEG  # up positive: the cube's centre is at z = 0
        low, high = max(-30.0, elevation - 0.25 * vfov / DEG), min(10.0, elevation + 0.25 * vfov / DEG)
        if low > high:
            continue
        return base, heading, float(rng.uniform(low, high))
    return None


def _panel(room: Room, stop, camera_z: float, seed: int) -> tuple[Quad, ...]:
    """A freshly painted panel, 3 m wide and up to 2.6 m high, 3 cm before the faced wall."""
    axis, at, sign, xy, _, _ = stop
    n = np.eye(3)[axis] * sign  # from the room to the wall
    down = np.array([0.0, 0.0, -1.0])
    right = np.cross(down, n)
    height = min(2.6, room.z_range[1] - room.z_range[0] - 0.1)
    top = min(room.z_range[1] - 0.05, camera_z + height / 2)
    centre = np.array([xy[0], xy[1], 0.0])
    centre[axis] = at - sign * 0.03
    origin = centre - right * 1.5
    origin[2] = top
    texel = 0.004
    texture = plain_paint(int(height / texel), int(3.0 / texel), np.random.default_rng([seed, 9]))
    return (Quad(origin, right, down, 3.0, height, TextureShader(texture, texel)),)


def _textured_share(poses: list[Transform], calibration: CameraCalibration, room: Room,
                    panel: tuple[Quad, ...], grid: int = 16) -> list[float]:
    """Per pose, the share of a ``grid`` x ``grid`` fan of view rays (pinhole) whose first hit
    is texture: a textured span of wall, floor or ceiling, a box, the cube; not plain paint
    nor the blank panel."""
    k = calibration.camera_matrix
    u, v = np.meshgrid(np.linspace(0.5, calibration.width - 0.5, grid), np.linspace(0.5, calibration.height - 0.5, grid))
    rays_c = np.column_stack([(u.ravel() - k[0, 2]) / k[0, 0], (v.ravel() - k[1, 2]) / k[1, 1], np.ones(grid * grid)])
    lower, upper = room.lower, room.upper
    spans = [plain_span(room, wall) for wall in range(6)]
    boxes = [(np.array(b.center) - np.array(b.size) / 2, np.array(b.center) + np.array(b.size) / 2)
             for b in room.boxes] + [(-np.full(3, CUBE_HALF), np.full(3, CUBE_HALF))]
    shares = []
    for pose in poses:
        d = rays_c @ pose.rotation.T
        c = pose.translation
        with np.errstate(divide="ignore", invalid="ignore"):
            t_walls = np.where(d > 0, (upper - c) / d, (lower - c) / d)
        t_walls = np.where(np.isfinite(t_walls) & (t_walls > 0), t_walls, np.inf)
        axis = np.argmin(t_walls, axis=1)
        t = t_walls[np.arange(len(d)), axis]
        hit = c + t[:, None] * d
        wall = 2 * axis + (d[np.arange(len(d)), axis] > 0)
        plain = np.zeros(len(d), bool)
        for w, span in enumerate(spans):
            if span is not None:
                on = wall == w
                coordinate = hit[on, WALL_AXES[w // 2][0]]
                plain[on] = (coordinate >= span[0]) & (coordinate <= span[1])
        for quad in panel:  # the blank panel: plain where it is hit before the wall
            normal = quad.normal
            denominator = d @ normal
            with np.errstate(divide="ignore", invalid="ignore"):
                tq = ((quad.origin - c) @ normal) / denominator
            on = np.isfinite(tq) & (tq > 0) & (tq < t)
            local = c + tq[:, None] * d - quad.origin
            a, b = local @ quad.axis_u, local @ quad.axis_v
            on &= (a >= 0) & (a <= quad.size_u) & (b >= 0) & (b <= quad.size_v)
            plain[on], t = True, np.where(on, tq, t)
        for low, high in boxes:  # boxes and the cube are textured, wherever they stand in front
            with np.errstate(divide="ignore", invalid="ignore"):
                t0, t1 = (low - c) / d, (high - c) / d
            near = np.nanmax(np.minimum(t0, t1), axis=1)
            far = np.nanmin(np.maximum(t0, t1), axis=1)
            plain &= ~((near <= far) & (far > 0) & (near < t))
        shares.append(float(1.0 - plain.mean()))
    return shares


def _longest_below(values, bound: float) -> int:
    longest = run = 0
    for value in values:
        run = run + 1 if value < bound else 0
        longest = max(longest, run)
    return longest


def _visible(poses: list[Transform], calibration: CameraCalibration) -> list[bool]:
    k = calibration.camera_matrix
    out = []
    for pose in poses:
        p = pose.inverse().apply(np.zeros((1, 3)))[0]
        if p[2] <= 0.1:
            out.append(False)
            continue
        u, v = k[0, 0] * p[0] / p[2] + k[0, 2], k[1, 1] * p[1] / p[2] + k[1, 2]
        out.append(bool(0 <= u < calibration.width and 0 <= v < calibration.height))
    return out


def _gains(rng, seconds: float, light: bool, steps: bool) -> tuple[tuple[float, float], ...]:
    """Exposure gain over time, every 0.25 s: auto-exposure steps of 0.7-1.35 every 2-4 s,
    times the light falling to 30 % over 25 s and coming back on at once."""
    grid = np.arange(0.0, seconds + 0.25, 0.25)
    gain = np.ones_like(grid)
    if steps:
        t = 2.0
        while t < seconds:
            gain[grid >= t] = rng.uniform(0.7, 1.35)
            t += rng.uniform(2.0, 4.0)
    if light:
        start = rng.uniform(5.0, max(6.0, seconds - 35.0))
        fall = np.clip((grid - start) / 25.0, 0.0, 1.0)
        on = (grid >= start) & (grid < start + 25.0 + rng.uniform(2.0, 6.0))
        gain = gain * np.where(on, 1.0 - 0.7 * fall, 1.0)
    if not (light or steps):
        return ()
    return tuple((float(t), float(g)) for t, g in zip(grid, gain, strict=True))


def make_case(seed: int, resolution: str = "half") -> FamilyCase:
    """Family member ``seed`` at ``resolution`` ("full" or "half": the same scene, robot
    and motion; the lens at 1280x1024 or 640x512)."""
    if resolution not in RESOLUTIONS:
        raise ValueError(f"resolution must be one of {', '.join(RESOLUTIONS)}, got {resolution!r}")
    rng = np.random.default_rng([int(seed), 35])
    kind, room, table = _scene(rng, int(seed))
    for _ in range(50):
        robot = _robot(rng, room)
        free = FreeFloor(room, robot.lever_m)
        start = _start(rng, free, robot, lens(robot, "full"), table)
        if start is not None:
            break
    else:
        raise RuntimeError(f"family seed {seed}: no start in front of the cube")
    robot = replace(robot, pitch_deg=start[2])
    want = {name for name, p in (("passers_by", 0.4), ("light_change", 0.3), ("blank_wall", 0.3),
                                 ("exposure_steps", 0.5)) if rng.random() < p}
    wander_s = float(rng.uniform(20.0, 150.0))
    rows, wall_stop, turns = wander(rng, free, robot, start, wander_s, want)
    calibration = lens(robot, resolution)
    # sampled at the frame rate: the camera rides on the robot, lever ahead of its axis
    times = np.arange(0.0, rows[-1, 0], 1.0 / robot.fps)
    x = np.interp(times, rows[:, 0], rows[:, 1])
    y = np.interp(times, rows[:, 0], rows[:, 2])
    heading = np.interp(times, rows[:, 0], np.unwrap(rows[:, 3]))
    z = room.z_range[0] + robot.height_m
    transforms = [camera_from_yaw_pitch(np.array([xi + robot.lever_m * np.cos(h), yi + robot.lever_m * np.sin(h), z]),
                                        float(h), -robot.pitch_deg * DEG) for xi, yi, h in zip(x, y, heading, strict=True)]
    poses = tuple(StampedPose(EPOCH_NS + int(round(t * 1e9)), p) for t, p in zip(times, transforms, strict=True))
    disturbances = sorted(want - ({"blank_wall"} if wall_stop is None else set()))
    walkers = ()
    if "passers_by" in want:
        crossings = [(float(rng.uniform(4.0, times[-1] - 3.0)), float(rng.uniform(0.6, 2.0)),
                      float(rng.uniform(0.8, 1.5))) for _ in range(int(rng.integers(1, 4)))]
        walkers = walkers_across(list(transforms), times, crossings, seed=int(seed) * 10)
    effects = Effects(exposure_s=robot.exposure_s,
                      gain_steps=_gains(rng, float(times[-1]), "light_change" in want, "exposure_steps" in want),
                      walkers=walkers,
                      static_quads=_panel(room, wall_stop, z, int(seed)) if wall_stop is not None else ())
    textured = _textured_share(transforms, calibration, room, effects.static_quads)
    unobservable = []
    if _longest_below(textured, BLANK_VIEW_SHARE) >= BLANK_VIEW_S * robot.fps:
        unobservable.append("blank_view")
    if robot.lever_m < 0.05 and any(t > np.pi / 2 for t in turns):
        unobservable.append("rotation_on_axis")
    return FamilyCase(int(seed), resolution, kind, room, table, robot, calibration, poses, effects,
                      tuple(disturbances), tuple(unobservable), tuple(_visible(transforms, calibration)),
                      tuple(textured))


def wheel_odometry(case: FamilyCase, rate_hz: float = 50.0, phase_s: float = 0.007) -> list[dict]:
    """The robot's wheel odometry along ``case`` (``fakes.odometry.wheel_odometry``: distances
    1.5 % long, turns 1 %, a heading drift, noise, 30 ms late), at ``rate_hz`` on its own
    clock phase: the base's axis ``lever_m`` behind the camera, heading where it looks."""
    from cubeloc.fakes.odometry import wheel_odometry as odometry_rows

    times = np.array([(p.stamp_ns - EPOCH_NS) / 1e9 for p in case.poses])
    centres = np.array([p.T_world_camera.translation for p in case.poses])
    forward = np.array([p.T_world_camera.rotation[:, 2] for p in case.poses])
    heading = np.unwrap(np.arctan2(forward[:, 1], forward[:, 0]))
    x = centres[:, 0] - case.robot.lever_m * np.cos(heading)
    y = centres[:, 1] - case.robot.lever_m * np.sin(heading)
    at = phase_s + np.arange(int(np.floor((times[-1] - phase_s) * rate_hz + 1e-9)) + 1) / rate_hz
    planar = [(float(a), float(b), float(c)) for a, b, c in
              zip(np.interp(at, times, x), np.interp(at, times, y), np.interp(at, times, heading), strict=True)]
    return odometry_rows(at, planar, seed=case.seed)


def base_from_camera(case: FamilyCase) -> tuple[list[float], list[float]]:
    """The camera's mount on the robot's base (xyz, quaternion [x, y, z, w]), exact, as
    ``[frames] base_from_camera`` takes it."""
    from cubeloc.fakes.odometry import mount_of

    return mount_of(case.poses[0].T_world_camera, case.robot.lever_m)


def render_case(case: FamilyCase, out_dir, progress=None):
    """Render ``case`` as a sequence directory (``fakes.sequence`` layout) with its
    ``family.json``; returns the ``SequenceSummary``."""
    from cubeloc.fakes.sequence import write_synthetic_sequence

    return write_synthetic_sequence(
        out_dir, f"family-{case.seed}", poses=list(case.poses), effects=case.effects, seed=case.seed,
        calibration=case.calibration, target=make_cube(), room=case.room, options=case.render_options,
        progress=progress, extra_files={"family.json": case.describe_json(), "render.key": case.render_key() + "\n"},
    )
