"""The camera's mount on the robot (``T_base_camera``) from a drive: hand-eye calibration.

Over a drive, the camera's poses (``T_world_camera``, from the target or the map) and the
wheel odometry's (``T_odom_base``) give, between two times, the camera's motion ``A`` (in
the camera frame where it started) and the base's ``B`` (in the base frame). The mount
``X = T_base_camera`` is what makes them one motion:

    B = X A X^-1        (hand-eye, AX = XB)

A ground robot moves on the floor, every ``B`` is a turn about the base's z with a shift
in its x-y plane, and that decides what the drive can observe:

- the rotation of the mount: its roll and pitch from the axis the camera turns about
  (the floor's normal), its yaw from how the camera's displacements line up with the
  base's;
- the lever's x and y, from the turns (a turn by ``theta`` moves a camera ``d`` off the
  axis by ``2 d sin(theta / 2)``): a drive in straight lines observes neither;
- **not** the lever's z: ``(I - R_B) t`` has no z for a turn about z. It comes from the
  camera's height above the floor (a cube standing on the floor gives it) less the base
  origin's own height, or from the user.

The wheels measure distances and turns with a scale error of their own (1-2 %), which is
not the mount's: the drive's distance and turn scales are solved with the mount (the
camera is metric) and reported, so that a wheel calibrated wrong does not bend the lever.

Away from the target the camera's metric is the tracker's map, whose scale may be off by
about a percent; a camera that sees every motion 1 % large sees the lever 1 % long. The
map's scale is one more unknown, with a 1 % prior, pinned against the wheels' by the
stretches the target measured (their scale is exact).

Solved in two steps: a closed form (the turn axis, then the yaw by a search over the
circle with the lever and the distance scale linear at each yaw), then a joint robust
least squares over the rotation, the lever's x and y, the wheels' two scales and heading
drift, and the map's scale. The covariance is the fit's (Gauss-Newton, the prior in it)
scaled by its residuals where they exceed the noise assumed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from cubeloc.errors import CubelocError
from cubeloc.positioning.geometry import Transform, robust_sigma

MIN_TURN_DEG = 20.0  # the largest turn between two poses of a pair must reach this
MIN_PAIRS = 8
MAX_SCALE_ERROR = 0.15  # a wheel scale more than 15 % off is a wrong file or wrong units, not wear


class MountError(CubelocError):
    """The drive cannot give the mount (the message says why and what to drive)."""


@dataclass(frozen=True)
class MountNoise:
    """What a stretch's two motions are weighed by: the camera's relative pose over it
    (``camera_m``, ``camera_rad``: a pose's own covariance is of where it is, drift since
    the target included, not of how it moved over a second, so it is not used) and the
    wheels' once their scales and heading drift are solved (``wheel_m`` plus
    ``wheel_per_m`` of the distance, ``wheel_rad``). Only their ratio shapes the fit: the
    covariance is scaled by the residuals where they are larger."""

    camera_m: float = 0.001
    camera_rad: float = math.radians(0.05)
    # the prior of the map's scale away from the target (tracker drift: docs/tracker.md;
    # exact on it): a camera that saw every motion 1 % large sees the lever 1 % long, and
    # only the stretches the target measured tell the two apart
    map_scale: float = 0.01
    wheel_m: float = 0.001
    wheel_per_m: float = 0.005
    wheel_rad: float = math.radians(0.05)


@dataclass(frozen=True)
class MountPair:
    """One stretch of the drive: the camera's motion ``A`` and the base's ``B`` over it."""

    seconds: float
    camera: Transform  # A = T_world_camera(t0)^-1 T_world_camera(t1)
    base: Transform  # B = T_odom_base(t0)^-1 T_odom_base(t1)
    on_target: bool = False  # both camera poses measured by the target (its scale exact)


@dataclass(frozen=True)
class MountResult:
    T_base_camera: Transform
    covariance: np.ndarray  # 6x6 over (x, y, z, rotation about the base's x, y, z), ROS order
    observed: dict[str, bool]  # x, y, z, roll, pitch, yaw: measured by the drive (z: by the height given)
    height_source: str  # where z came from: "target", "given" or "unobserved (0)"
    distance_scale: float  # odometry distance / true distance
    turn_scale: float  # odometry turn / true turn
    heading_drift_deg_s: float  # the odometry's heading drift
    map_scale: float | None  # the map's scale against the target's (None: every stretch measured by the target)
    map_scale_sigma: float | None  # its standard deviation (the prior's where the target measured too little)
    target_pairs: int  # stretches the target measured at both ends
    pairs: int
    used_pairs: int  # inside the robust fit's limits
    residual_m: float  # RMS of the translation residuals (metres)
    residual_deg: float  # RMS of the rotation residuals
    largest_turn_deg: float
    warnings: list[str] = field(default_factory=list)

    def sigma(self) -> tuple[np.ndarray, np.ndarray]:
        """Standard deviations of (x, y, z) in metres and of the rotation in degrees."""
        d = np.sqrt(np.maximum(np.diag(self.covariance), 0.0))
        return d[:3], np.degrees(d[3:])


def make_pairs(camera: list[tuple[int, Transform, bool]], odometry_at, pair_s: float = 1.0) -> list[MountPair]:
    """Consecutive stretches of ``pair_s`` seconds (at least) between the camera's poses
    ``(stamp_ns, T_world_camera, measured by the target)``, in time order, with the base's motion over each from
    ``odometry_at(stamp_ns)`` (``T_odom_base`` or None where the odometry does not cover
    the time). A gap of more than twice ``pair_s`` between two poses (the camera lost)
    starts a new stretch."""
    pairs: list[MountPair] = []
    start = None
    for stamp, pose, on_target in camera:
        odom = odometry_at(stamp)
        if odom is None:
            start = None
            continue
        if start is not None and (stamp - start[0]) / 1e9 > 2 * pair_s:
            start = None
        if start is None:
            start = (stamp, pose, odom, on_target)
            continue
        if (stamp - start[0]) / 1e9 < pair_s:
            continue
        pairs.append(MountPair((stamp - start[0]) / 1e9, start[1].inverse() @ pose, start[2].inverse() @ odom,
                               start[3] and on_target))
        start = (stamp, pose, odom, on_target)
    return pairs


def _yaw_of(rotation: np.ndarray) -> float:
    return float(Rotation.from_matrix(rotation).as_rotvec()[2])


def _align(axis: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit ``axis`` to +z."""
    z = np.array([0.0, 0.0, 1.0])
    cross = np.cross(axis, z)
    s, c = np.linalg.norm(cross), float(axis @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return Rotation.from_rotvec(cross / s * math.atan2(s, c)).as_matrix()


def _closed_form(pairs: list[MountPair]) -> tuple[np.ndarray, np.ndarray, float]:
    """A first mount: (R_base_camera, lever x-y, distance scale). The camera's turn axis
    (its rotation vectors, signed by the base's turns) is the base's z; the yaw about it
    is the one whose lever and scale, solved linearly, fit the displacements best."""
    turns = np.array([_yaw_of(p.base.rotation) for p in pairs])
    vectors = np.array([Rotation.from_matrix(p.camera.rotation).as_rotvec() for p in pairs])
    axis = (np.sign(turns)[:, None] * vectors).sum(axis=0)
    axis /= max(np.linalg.norm(axis), 1e-12)
    aligned = _align(axis)
    best = None
    for yaw in np.radians(np.arange(0.0, 360.0, 1.0)):
        rotation = Rotation.from_rotvec([0.0, 0.0, yaw]).as_matrix() @ aligned
        rows, rhs = [], []
        for p in pairs:
            # R_X t_A + (I - R_B) t_X = c t_B, with c = 1 / distance scale (x and y rows)
            m = np.eye(3) - p.base.rotation
            rows.append(np.column_stack([m[:2, :2], -p.base.translation[:2]]))
            rhs.append(-(rotation @ p.camera.translation)[:2])
        a, b = np.vstack(rows), np.concatenate(rhs)
        solution, *_ = np.linalg.lstsq(a, b, rcond=None)
        cost = float(np.sum((a @ solution - b) ** 2))
        if solution[2] > 0 and (best is None or cost < best[0]):
            best = (cost, rotation, solution)
    if best is None:
        raise MountError("the odometry moves against the camera at every heading of the mount: is it this drive's?")
    _, rotation, solution = best
    return rotation, solution[:2], 1.0 / float(solution[2])


def solve_mount(pairs: list[MountPair], height_m: float | None = None, height_source: str = "given",
                noise: MountNoise | None = None, height_sigma_m: float = 0.0) -> MountResult:
    """The mount from a drive's ``pairs``; ``height_m`` is the lever's z (the camera's
    height above the base's origin, with standard deviation ``height_sigma_m``), which a
    drive on the floor does not observe."""
    noise = noise or MountNoise()
    if len(pairs) < MIN_PAIRS:
        raise MountError(f"{len(pairs)} stretches of the drive have both a camera pose and odometry, "
                         f"{MIN_PAIRS} needed: drive longer in view of the target or the map")
    turns = np.degrees(np.abs([_yaw_of(p.base.rotation) for p in pairs]))
    camera_turns = np.degrees([np.linalg.norm(Rotation.from_matrix(p.camera.rotation).as_rotvec()) for p in pairs])
    odometry_path = sum(float(np.linalg.norm(p.base.translation)) for p in pairs)
    camera_path = sum(float(np.linalg.norm(p.camera.translation)) for p in pairs)
    if odometry_path < 0.05 * max(camera_path, 1e-9) and turns.max() < 1.0:
        raise MountError(f"the odometry does not move ({odometry_path:.2f} m, {turns.max():.1f} deg) while the "
                         f"camera moved {camera_path:.2f} m and turned up to {camera_turns.max():.0f} deg: "
                         "is it this drive's odometry, and is the robot's odometry running?")
    if turns.max() < MIN_TURN_DEG:
        raise MountError(f"too little rotation: the largest turn over a stretch is {turns.max():.1f} deg, "
                         f"{MIN_TURN_DEG:g} needed; drive figure-eights (turns both ways) in view of the target")
    rotation0, lever0, scale0 = _closed_form(pairs)
    z = 0.0 if height_m is None else float(height_m)
    seconds = np.array([p.seconds for p in pairs])
    sigma_t = np.hypot(noise.camera_m, [noise.wheel_m + noise.wheel_per_m * np.linalg.norm(p.base.translation)
                                        for p in pairs])
    sigma_r = np.hypot(noise.camera_rad, noise.wheel_rad)

    on_target = np.array([p.on_target for p in pairs])
    # the map's scale against the target's: an unknown with the prior ``noise.map_scale``,
    # which the stretches the target measured (their scale exact) pin against the wheels'
    mapped = not on_target.all()

    def unpack(x: np.ndarray) -> tuple[Transform, float, float, float, float]:
        mount = Transform(Rotation.from_rotvec(x[:3]).as_matrix() @ rotation0, np.array([x[3], x[4], z]))
        return mount, 1.0 + x[5], 1.0 + x[6], x[7], (1.0 + x[8]) if mapped else 1.0

    def residuals(x: np.ndarray) -> np.ndarray:
        prior = [x[8:9] / noise.map_scale] if mapped else []
        return np.concatenate([pair_residuals(x), *prior])

    def pair_residuals(x: np.ndarray) -> np.ndarray:
        mount, distance_scale, turn_scale, drift, map_scale = unpack(x)
        inverse = mount.inverse()
        out = []
        for p, st, dt in zip(pairs, sigma_t, seconds, strict=True):
            camera = p.camera if p.on_target else Transform(p.camera.rotation, p.camera.translation / map_scale)
            predicted = mount @ camera @ inverse
            rv = Rotation.from_matrix(predicted.rotation).as_rotvec()
            extra = rv[2] * (turn_scale - 1.0) + drift * dt  # the wheels' turn: scaled, and drifting
            rv[2] += extra
            # the wheels integrate their displacement along their own heading: over an arc,
            # a turn ``extra`` too far turns the chord by half of it
            c, s = math.cos(extra / 2), math.sin(extra / 2)
            t = predicted.translation * distance_scale
            t = np.array([c * t[0] - s * t[1], s * t[0] + c * t[1], t[2]])
            out.append((t - p.base.translation) / st)
            out.append((rv - Rotation.from_matrix(p.base.rotation).as_rotvec()) / sigma_r)
        return np.concatenate(out)

    x0 = np.array([0.0, 0.0, 0.0, lever0[0], lever0[1], scale0 - 1.0, 0.0, 0.0] + ([0.0] if mapped else []))
    fit = least_squares(residuals, x0, loss="huber", f_scale=3.0, x_scale="jac")
    mount, distance_scale, turn_scale, drift, map_scale = unpack(fit.x)
    raw = pair_residuals(fit.x).reshape(len(pairs), 2, 3)
    per_pair = np.sqrt((raw**2).sum(axis=(1, 2)) / 6.0)
    used = per_pair < 3.0
    # Gauss-Newton covariance of the parameters, scaled up by the residuals where they are
    # larger than the noise assumed (never down: a lucky drive does not make the mount surer)
    jac = fit.jac
    try:
        cov_x = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        raise MountError("the drive does not determine the mount (its turns all look alike): drive "
                         "figure-eights, turning both ways") from None
    chi2 = float(np.sum(raw[used] ** 2)) / max(6 * int(used.sum()) + int(mapped) - len(fit.x), 1)
    cov_x *= max(chi2, 1.0)
    covariance = np.zeros((6, 6))
    covariance[:2, :2] = cov_x[3:5, 3:5]
    covariance[:2, 3:] = cov_x[3:5, :3]
    covariance[3:, :2] = cov_x[:3, 3:5]
    covariance[3:, 3:] = cov_x[:3, :3]
    trans = raw[:, 0, :] * sigma_t[:, None]
    rots = raw[:, 1, :] * sigma_r
    warnings = []
    if abs(distance_scale - 1.0) > MAX_SCALE_ERROR or abs(turn_scale - 1.0) > MAX_SCALE_ERROR:
        raise MountError(f"the odometry and the camera disagree in scale: the wheels measure {distance_scale:.3f} "
                         f"times the distance and {turn_scale:.3f} times the turn the camera saw; wrong units, "
                         "the wrong odometry file, or a target of the wrong size")
    if used.mean() < 0.7:
        raise MountError(f"the odometry and the camera disagree beyond their noise on {int((~used).sum())} of "
                         f"{len(pairs)} stretches (translation residual RMS "
                         f"{1000 * float(np.sqrt(np.mean(trans**2))):.1f} mm): wheels slipping, the target "
                         "moved, or the clocks of the camera and the odometry apart")
    if not used.all():
        warnings.append(f"{int((~used).sum())} of {len(pairs)} stretches disagree beyond 3 sigma (slip?) and "
                        "were down-weighted")
    observed = {"x": True, "y": True, "z": height_m is not None, "roll": True, "pitch": True, "yaw": True}
    covariance[2, 2] = height_sigma_m**2
    if height_m is None:
        covariance[2, 2] = 1.0  # unknown: a metre's standard deviation stands for "not measured"
        height_source = "unobserved (0)"
    return MountResult(mount, covariance, observed, height_source, distance_scale, turn_scale,
                       math.degrees(drift), map_scale if mapped else None,
                       float(math.sqrt(cov_x[8, 8])) if mapped else None, int(on_target.sum()), len(pairs),
                       int(used.sum()), float(np.sqrt(np.mean(trans[used] ** 2))),
                       float(np.degrees(np.sqrt(np.mean(rots[used] ** 2)))), float(turns.max()), warnings)


def camera_height(camera_positions: np.ndarray, up: np.ndarray, floor_point: np.ndarray) -> tuple[float, float]:
    """The camera's height above the floor (median over the drive) and its spread (the
    median absolute deviation, scaled to a standard deviation): ``up`` is the floor's
    normal and ``floor_point`` a point on the floor, both in the target's frame."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    heights = (np.asarray(camera_positions) - np.asarray(floor_point)) @ up
    median = float(np.median(heights))
    return median, robust_sigma(heights, median)
