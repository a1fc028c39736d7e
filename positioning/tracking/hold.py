"""When the map runs short: hold the pose on the tracks' rays, coast, and the drift.

``RayHold`` keeps, for every live track, the ray it was last seen along from a measured
pose (its camera centre and world direction). When PnP has too few map points (a turn on
the spot, a passer-by in front of the map) ``hold`` fits the orientation to those rays and
the position to the map points still in view and the motion model (``pose_fit``), whose
standard deviation grows with the time held; with too few rays as well it coasts on the
motion model alone for at most ``motion.max_coast_s`` (``motion.MotionModel.coast``).

``Drift`` adds to a tracking pose's covariance what its own measurements cannot know: how
far the map may have drifted since the target was last trusted, growing with the path at
the relative scale error bundle adjustment measures (a random walk as the map's points are
replaced) and with the rotation since.
"""

from __future__ import annotations

import collections

import numpy as np

from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking.map import Map
from cubeloc.positioning.tracking.motion import Held, MotionModel
from cubeloc.positioning.tracking.options import TrackerOptions
from cubeloc.positioning.tracking.pose_fit import Rays, fit_pose
from cubeloc.positioning.tracking.types import Tracks


def position_sigma(covariance: np.ndarray | None) -> float:
    """The position's standard deviation (root of the covariance's trace), 0 without one."""
    return 0.0 if covariance is None else float(np.sqrt(max(np.trace(np.asarray(covariance)[:3, :3]), 0.0)))


class RayHold:
    def __init__(self, options: TrackerOptions, fx: float) -> None:
        self.options = options
        self.fx = fx
        # track id -> (world camera centre, world unit ray) of its last measured sighting
        self.rays: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.since: int | None = None  # stamp of the last measured pose before the hold
        self.speed_m_s = 0.0  # the camera's speed by the motion model when the hold began
        # the 6x6 covariance of the measured pose the rays last started from (None: unknown)
        self.base_covariance: np.ndarray | None = None

    @property
    def holding(self) -> bool:
        return self.since is not None

    def end(self) -> None:
        self.since = None

    def rebase(self, pose: Transform | None, ids: np.ndarray, xn: np.ndarray,
               covariance: np.ndarray | None = None) -> None:
        """Keep the rays of the live tracks ``ids``. On a frame with a measured pose
        (``pose``, its own ``covariance``) every ray starts again there: a ray is only as
        good as the pose it starts from, and the newest measured one is the best (a
        correction of the map moves the old ones)."""
        if pose is None:
            self.rays = {int(t): self.rays[int(t)] for t in ids if int(t) in self.rays}
            return
        self.rays = self._from(pose, ids, xn)
        self.base_covariance = None if covariance is None else np.asarray(covariance, np.float64)

    def add(self, pose: Transform, ids: np.ndarray, xn: np.ndarray) -> None:
        """Rays for new tracks, born in a frame of pose ``pose``."""
        self.rays.update(self._from(pose, ids, xn))

    @staticmethod
    def _from(pose: Transform, ids: np.ndarray, xn: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        directions = np.column_stack([xn, np.ones(len(xn))]) @ pose.rotation.T
        directions /= np.linalg.norm(directions, axis=1)[:, None]
        return {int(t): (pose.translation, d) for t, d in zip(ids, directions, strict=True)}

    def hold(self, stamp_ns: int, motion: MotionModel, prediction: Transform, tracks: Tracks,
             xn: np.ndarray, world_map: Map, odometry: np.ndarray | None = None) -> Held | None:
        """The held pose of the frame at ``stamp_ns`` (``motion`` has the last frame's pose,
        ``prediction`` is its prediction, or the wheel odometry's when ``odometry``, its
        covariance since the hold began, is given), or None when rays and time do not allow it."""
        o = self.options
        if self.since is None:
            self.since = motion.stamp
            self.speed_m_s = motion.speed(prediction, stamp_ns)
        held_s = (stamp_ns - self.since) / 1e9
        if held_s > o.hold.max_s:
            return None
        has = world_map.mapped(tracks.ids)
        born = np.array([not h and int(t) in self.rays for t, h in zip(tracks.ids, has, strict=True)], bool)
        if born.sum() < o.hold.min_rays:
            coasted = motion.coast(prediction, held_s)
            return None if coasted is None else (coasted[0], self._from_base(coasted[1]))
        points = np.array([world_map.points[int(t)] for t in tracks.ids[has]]).reshape(-1, 3)
        depths = prediction.inverse().apply(points)[:, 2] if has.any() else np.zeros(0)
        depths = depths[depths > 0]
        depth = float(np.median(depths)) if len(depths) else o.hold.default_depth_m
        centres = np.array([self.rays[int(t)][0] for t in tracks.ids[born]])
        directions = np.array([self.rays[int(t)][1] for t in tracks.ids[born]])
        rays = Rays(centres, directions, xn[born], 1.0 / depth)
        if odometry is not None:  # the wheels measured the translation: the odometry's, with its sigma
            prior = (prediction.translation, float(np.sqrt(o.hold.sigma_m**2 + odometry[0, 0])))
        else:  # no measured translation: the motion model's dies away (it moved the prediction)
            prior = (motion.faded(prediction, stamp_ns), o.hold.sigma_m + o.hold.sigma_m_per_s * held_s)
        fit = fit_pose(prediction, points, xn[has], rays, fx=self.fx, sigma_px=o.track_sigma_px,
                       prior_position=prior)
        if fit is not None and 0 < fit.point_inliers.sum() < o.hold.min_points:
            # a handful of points pull the position wherever their few rays allow (measured:
            # 2 points moved a held pose 40 mm): the rays and the motion model alone
            fit = fit_pose(prediction, np.zeros((0, 3)), np.zeros((0, 2)), rays, fx=self.fx,
                           sigma_px=o.track_sigma_px, prior_position=prior)
        if fit is None or fit.ray_inliers.sum() < max(o.hold.min_rays, o.hold.min_ray_fraction * born.sum()):
            return None
        rotation_sigma = np.sqrt(np.max(np.linalg.eigvalsh(fit.covariance[3:, 3:])))
        if np.degrees(rotation_sigma) > o.hold.max_rotation_sigma_deg:
            return None
        covariance = fit.covariance
        if fit.point_inliers.sum() >= o.hold.min_points:
            return fit.T_world_camera, covariance  # map points place it: in the map, not from the base
        if odometry is None:
            # nothing measured the position (rays of unknown depth, each fresh one born on a
            # held pose, agree with a position left behind): it is as unsure as the robot's
            # motion allows (a hold before the map drifted 4.3 m claiming 0.1-0.3 m:
            # docs/notes/2026-12-03-family-traces.md)
            covariance = covariance.copy()
            floor = motion.unmeasured_sigma(self.speed_m_s, held_s) ** 2
            smallest = float(np.min(np.linalg.eigvalsh(covariance[:3, :3])))
            covariance[:3, :3] += np.eye(3) * max(0.0, floor - smallest)
        return fit.T_world_camera, self._from_base(covariance)

    def _from_base(self, covariance: np.ndarray) -> np.ndarray:
        """``covariance``, of the pose held since the base (the rays' directions, the motion
        from it), plus the base pose's own: a hold carries on from where the base was, so it
        is off by at least as much (docs/tracker.md, "Held on rays")."""
        return covariance if self.base_covariance is None else covariance + self.base_covariance


class Drift:
    """Path and rotation since the target was last trusted, and what they may have cost."""

    def __init__(self, options: TrackerOptions) -> None:
        self.options = options
        self.path_m = 0.0
        self.turned_rad = 0.0
        self.floor_m = options.drift.floor_m
        self.scale_var = 0.0  # variance of the map's relative scale error where the camera is
        self.scaled_m = 0.0  # the position's standard deviation grown with the path at that scale
        self._agreement: collections.deque[float] = collections.deque(maxlen=30)  # metres

    def agreement(self, distance_m: float) -> None:
        """The map's pose and the target's, in one frame, ``distance_m`` apart. Their
        RMS over the last 30 such frames is the floor of every tracking pose's standard
        deviation once the target has gone: the map is no better than it agrees with the
        target (agile at half resolution: 5 mm off at once, where a 1 mm floor was
        claimed). Conservative: the target's own noise is in it, on each axis."""
        self._agreement.append(distance_m)

    def begun_on(self, *covariances: np.ndarray | None) -> None:
        """The map begins on target poses of these position covariances (3, 3): until the
        next trusted target pose (``reset``, where the map's agreement with it takes over),
        a pose on the map is no surer than they are (the largest standard deviation among
        them, on each axis)."""
        known = [np.asarray(c) for c in covariances if c is not None]
        if known:
            sigma = max(float(np.sqrt(max(np.max(np.linalg.eigvalsh(c)), 0.0))) for c in known)
            self.floor_m = max(self.floor_m, sigma)

    def reset(self) -> None:
        """The target is trusted again: nothing has drifted since."""
        self.path_m = self.turned_rad = self.scaled_m = self.scale_var = 0.0
        agreement = float(np.sqrt(np.mean(np.square(self._agreement)))) if self._agreement else 0.0
        self.floor_m = max(self.options.drift.floor_m, agreement)

    @property
    def grown_m(self) -> float:
        """How much the position's standard deviation has grown since the target: the
        measure of drift ``Map.correct`` spreads a correction by."""
        return self.options.drift.per_m * self.path_m + self.options.drift.m_per_rad * self.turned_rad

    def scale_measured(self, window_var: float, renewed: float, held_by_target: bool, anchored_var: float = 0.0
                       ) -> None:
        """A bundle adjustment's relative scale variance across its window
        (``bundle._scale_var``). Held by the target, the window's scale is the map's, and no
        surer than the anchored keyframes fix it (``anchored_var``,
        ``Map.anchored_scale_var``: a map begun on a 3 cm baseline between two target poses
        6-8 mm unsure has its scale to ~20 %, whatever the window's points say). Held
        by keyframes, the scale walks on as the points that carry it are replaced: by the
        window's variance for a window of points all new, by the ``renewed`` share of it
        for one whose points are partly new since the last (a turn on the spot, a keyframe
        every frame, renews few and walks little)."""
        if held_by_target:
            self.scale_var = max(window_var, anchored_var)
        else:
            self.scale_var += window_var * min(max(renewed, 0.0), 1.0)

    def rewind(self, grown_m: float) -> None:
        """A loop closed onto a keyframe made when the drift had grown by ``grown_m``: the
        pose is as sure as that keyframe's now, so path, turn and scale walk shrink alike
        until ``grown_m`` is what has grown."""
        if self.grown_m <= grown_m or self.grown_m <= 0.0:
            return
        fraction = max(grown_m, 0.0) / self.grown_m
        self.path_m *= fraction
        self.turned_rad *= fraction
        self.scaled_m *= fraction

    def relocalised(self, covariance: np.ndarray | None) -> None:
        """A relocalisation against keyframes: the map is built on from its pose, so its
        uncertainty stays in every pose after it until the target returns."""
        if covariance is not None:
            sigma = float(np.sqrt(np.max(np.linalg.eigvalsh(np.asarray(covariance)[:3, :3]))))
            self.floor_m = max(self.floor_m, sigma)

    def covariance(self, previous: Transform | None, pose: Transform, measured: np.ndarray | None
                   ) -> np.ndarray | None:
        """``measured`` (this frame's own covariance) plus the drift since the target, a
        standard deviation growing with the path and rotation (``drift.per_m`` ...);
        ``previous`` is the last frame's pose, from which the path goes on. Each metre of it
        adds the map's relative scale error (``scale_measured``), at least ``drift.per_m``."""
        if previous is not None:
            step_m = float(np.linalg.norm(pose.translation - previous.translation))
            self.path_m += step_m
            # a map whose scale is off by s puts every metre travelled on it s off
            self.scaled_m += max(self.options.drift.per_m, float(np.sqrt(self.scale_var))) * step_m
            self.turned_rad += float(previous.rotation_angle_to(pose))
        if measured is None:
            return None
        o = self.options
        position_sigma = self.floor_m + self.scaled_m + self.options.drift.m_per_rad * self.turned_rad
        rotation_sigma = o.drift.rad_per_m * self.path_m + o.drift.rad_per_rad * self.turned_rad
        total = np.array(measured, dtype=np.float64, copy=True)
        total[:3, :3] += np.eye(3) * position_sigma**2
        total[3:, 3:] += np.eye(3) * rotation_sigma**2
        return total
