"""Trajectory metrics against ground truth, in the target (world) frame, with no alignment.

Monocular SLAM papers align the estimate to the ground truth (Umeyama, often with scale)
before computing the absolute trajectory error; that hides exactly what cubeloc exists
to get right, the metric position in the target's frame. So the absolute error here is
computed on the poses as published. Poses are paired by timestamp (nearest ground truth
within ``max_dt_ns``), as ``evo``'s ``associate`` does.

All functions are pure: lists of ``StampedPose`` (``T_world_camera``) in, frozen results out.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.trajectory_io import StampedPose

DEFAULT_MAX_DT_NS = 1_000_000  # 1 ms: both files come from the same frame stamps


@dataclass(frozen=True)
class AbsoluteError:
    """Position error of the camera centre, metres, over the associated poses."""

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    rotation_rmse_deg: float
    count: int  # associated pose pairs
    errors_m: np.ndarray  # (count,) per pose, in time order
    stamps_ns: np.ndarray  # (count,) the estimate's stamps


@dataclass(frozen=True)
class RelativeError:
    """Relative pose error per metre travelled (pairs of poses ``delta_m`` of path apart)."""

    delta_m: float
    translation_rmse_percent: float  # RMS of |translation error| / path length, in %
    rotation_rmse_deg_per_m: float
    count: int


@dataclass(frozen=True)
class ScaleDrift:
    """How the estimate's scale and position drift over a stretch of path."""

    distance_m: float  # ground-truth path length over the segment
    scale_error_percent: float  # estimated / true path length - 1, in %
    drift_percent_per_m: float  # slope of the local scale error against distance, %/m
    end_error_m: float  # position error at the end of the segment
    translation_drift_percent: float  # growth of the position error / distance, in %


def associate(
    reference: list[StampedPose], estimate: list[StampedPose], max_dt_ns: int = DEFAULT_MAX_DT_NS
) -> list[tuple[StampedPose, StampedPose]]:
    """(reference, estimate) pairs: each estimate with its nearest reference in time.

    Estimates with no reference within ``max_dt_ns`` are left out (never interpolated:
    the ground truth of a synthetic or motion-capture sequence is sampled per frame).
    """
    ref = sorted(reference, key=lambda p: p.stamp_ns)
    stamps = [p.stamp_ns for p in ref]
    pairs = []
    for est in sorted(estimate, key=lambda p: p.stamp_ns):
        i = bisect.bisect_left(stamps, est.stamp_ns)
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(ref):
                dt = abs(stamps[j] - est.stamp_ns)
                if dt <= max_dt_ns and (best is None or dt < abs(stamps[best] - est.stamp_ns)):
                    best = j
        if best is not None:
            pairs.append((ref[best], est))
    return pairs


def absolute_trajectory_error(
    reference: list[StampedPose],
    estimate: list[StampedPose],
    max_dt_ns: int = DEFAULT_MAX_DT_NS,
    start_ns: int | None = None,
    end_ns: int | None = None,
) -> AbsoluteError:
    """Position error with no alignment, optionally only over ``[start_ns, end_ns]``.

    Raises ValueError when no pose associates (an empty estimate has no error to report,
    and reporting 0 would be a lie).
    """
    pairs = [
        (r, e)
        for r, e in associate(reference, estimate, max_dt_ns)
        if (start_ns is None or e.stamp_ns >= start_ns) and (end_ns is None or e.stamp_ns <= end_ns)
    ]
    if not pairs:
        raise ValueError("no estimated pose has a ground-truth pose at the same time")
    errors = np.array(
        [np.linalg.norm(e.T_world_camera.translation - r.T_world_camera.translation) for r, e in pairs]
    )
    angles = np.degrees([r.T_world_camera.rotation_angle_to(e.T_world_camera) for r, e in pairs])
    return AbsoluteError(
        rmse_m=float(np.sqrt(np.mean(errors**2))),
        mean_m=float(errors.mean()),
        median_m=float(np.median(errors)),
        max_m=float(errors.max()),
        rotation_rmse_deg=float(np.sqrt(np.mean(np.square(angles)))),
        count=len(pairs),
        errors_m=errors,
        stamps_ns=np.array([e.stamp_ns for _, e in pairs], dtype=np.int64),
    )


def _path_lengths(poses: list[StampedPose]) -> np.ndarray:
    """Cumulative path length (N,) of the camera centre, metres."""
    centres = np.array([p.T_world_camera.translation for p in poses])
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1) if len(poses) > 1 else np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(steps)])


def relative_pose_error(
    reference: list[StampedPose],
    estimate: list[StampedPose],
    delta_m: float = 1.0,
    max_dt_ns: int = DEFAULT_MAX_DT_NS,
) -> RelativeError:
    """For every pose i, the pose j where the true path has grown by ``delta_m``; the
    error of the estimated motion i->j against the true one, per metre of true path.

    Raises ValueError when the associated path is shorter than ``delta_m``.
    """
    if delta_m <= 0:
        raise ValueError(f"delta_m must be positive, got {delta_m}")
    pairs = associate(reference, estimate, max_dt_ns)
    ref = [r for r, _ in pairs]
    est = [e for _, e in pairs]
    lengths = _path_lengths(ref)
    translation, rotation = [], []
    for i in range(len(pairs)):
        j = int(np.searchsorted(lengths, lengths[i] + delta_m))
        if j >= len(pairs):
            break
        travelled = lengths[j] - lengths[i]
        true_motion = ref[i].T_world_camera.inverse() @ ref[j].T_world_camera
        est_motion = est[i].T_world_camera.inverse() @ est[j].T_world_camera
        error = true_motion.inverse() @ est_motion
        translation.append(np.linalg.norm(error.translation) / travelled)
        rotation.append(np.degrees(_angle(error.rotation)) / travelled)
    if not translation:
        raise ValueError(f"the trajectory is shorter than {delta_m} m: no relative error to report")
    return RelativeError(
        delta_m=delta_m,
        translation_rmse_percent=float(100.0 * np.sqrt(np.mean(np.square(translation)))),
        rotation_rmse_deg_per_m=float(np.sqrt(np.mean(np.square(rotation)))),
        count=len(translation),
    )


def _angle(rotation: np.ndarray) -> float:
    """Angle (radians) of a rotation matrix."""
    return float(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)))


def scale_drift(
    reference: list[StampedPose],
    estimate: list[StampedPose],
    start_ns: int,
    end_ns: int,
    window_m: float = 0.25,
    max_dt_ns: int = DEFAULT_MAX_DT_NS,
) -> ScaleDrift:
    """Scale error and drift of the estimate over ``[start_ns, end_ns]`` (say, while the
    target was out of view).

    The local scale is the ratio of estimated to true displacement over consecutive
    stretches of ``window_m`` of true path; its slope against distance (least squares) is
    the scale drift in %/m. Raises ValueError when the segment is shorter than two windows.
    """
    pairs = [(r, e) for r, e in associate(reference, estimate, max_dt_ns) if start_ns <= e.stamp_ns <= end_ns]
    if len(pairs) < 3:
        raise ValueError("the segment has fewer than 3 associated poses")
    ref = [r for r, _ in pairs]
    est = [e for _, e in pairs]
    lengths = _path_lengths(ref)
    distance = float(lengths[-1])
    est_lengths = _path_lengths(est)
    ratios, at = [], []
    i = 0
    while True:
        j = int(np.searchsorted(lengths, lengths[i] + window_m))
        if j >= len(pairs):
            break
        true_step = np.linalg.norm(ref[j].T_world_camera.translation - ref[i].T_world_camera.translation)
        est_step = np.linalg.norm(est[j].T_world_camera.translation - est[i].T_world_camera.translation)
        if true_step > 1e-6:
            ratios.append(est_step / true_step - 1.0)
            at.append(0.5 * (lengths[i] + lengths[j]))
        i = j
    if len(ratios) < 2:
        raise ValueError(f"the segment ({distance:.2f} m) is shorter than two windows of {window_m} m")
    slope = float(np.polyfit(np.array(at), np.array(ratios), 1)[0])
    start_error = np.linalg.norm(est[0].T_world_camera.translation - ref[0].T_world_camera.translation)
    end_error = np.linalg.norm(est[-1].T_world_camera.translation - ref[-1].T_world_camera.translation)
    return ScaleDrift(
        distance_m=distance,
        scale_error_percent=float(100.0 * (est_lengths[-1] / distance - 1.0)) if distance > 0 else 0.0,
        drift_percent_per_m=100.0 * slope,
        end_error_m=float(end_error),
        translation_drift_percent=float(100.0 * (end_error - start_error) / distance) if distance > 0 else 0.0,
    )


@dataclass(frozen=True)
class ScaleWalk:
    """How the scale walks while the target is away, told apart by what the robot did
    between two stretches of path: turned, or drove on (``scale_walk``). Each entry is one
    pair of stretches."""

    stretch_m: float
    turned_deg: np.ndarray  # (T,) the turning between the two stretches' middles, pairs that turned
    turn_steps: np.ndarray  # (T,) |log| of their scales' ratio: the scale's step across each turn
    drive_steps: np.ndarray  # (D,) the same, pairs that turned less (straight drives, arcs)
    under_turn_percent: np.ndarray  # (T,) how much less than the camera the estimate turned, %

    @property
    def turn_step_percent(self) -> float:
        """The RMS step across a turn, %."""
        return float(100.0 * np.sqrt(np.mean(self.turn_steps**2))) if len(self.turn_steps) else float("nan")

    @property
    def drive_walk_percent(self) -> float:
        """How fast the scale walks while driving on, % per square root of metre: the RMS
        change from one stretch to the next over the root of the stretch's length (a random
        walk's rate, the same whatever the stretch)."""
        return float(100.0 * np.sqrt(np.mean(self.drive_steps**2) / self.stretch_m)) if len(self.drive_steps) \
            else float("nan")

    @property
    def under_turn_median_percent(self) -> float:
        """The median under-turn over the turns, %."""
        return float(np.median(self.under_turn_percent)) if len(self.under_turn_percent) else float("nan")

    @property
    def largest_step_percent(self) -> float:
        """The largest change from one stretch to the next, turn or drive, %."""
        steps = np.concatenate([self.turn_steps, self.drive_steps])
        return float(100.0 * steps.max()) if len(steps) else float("nan")


def _heading(rotation: np.ndarray, up: np.ndarray) -> float:
    """The optical axis' direction about ``up``, radians (world x towards y for up = z)."""
    axis = rotation[:, 2] - (rotation[:, 2] @ up) * up
    east = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    east = east - (east @ up) * up
    north = np.cross(up, east)
    return float(np.arctan2(axis @ north, axis @ east))


def scale_walk(truth: list[StampedPose], estimates: list[StampedPose | None], away: np.ndarray | None = None,
               stretch_m: float = 1.0, turn_deg: float = 30.0, up: np.ndarray | None = None) -> ScaleWalk:
    """Where the estimate's scale changes: across turns, or along straight drives.

    ``truth`` and ``estimates`` are one per frame (None: no pose); ``away`` (per frame,
    default all) marks the frames whose pose is not the target's. The true path is cut into
    stretches of ``stretch_m``; a stretch's scale is the estimated over the true
    displacement between its ends (a stretch that bends to less than half its length end
    to end has none). Two stretches with a scale make a pair when every frame from the
    first to the second is posed, the target does not come back there, no stretch between
    them has a scale, and the second is away all through. The turning between their
    middles (the sum of the camera's heading changes about ``up``, default world z) sorts
    the pair as a turn (``turn_deg`` or more) or a drive (less: straight on, or an arc).
    For a turn whose net heading change is ``turn_deg`` or more, the estimate's heading
    change is also compared with the true one.

    >>> from cubeloc.positioning.geometry import Transform
    >>> def drive(n=200):  # 2 m along x, a 90 deg turn on the spot, 2 m along y
    ...     poses, yaw, x = [], 0.0, np.zeros(3)
    ...     for i in range(3 * n):
    ...         if i < n or i >= 2 * n:
    ...             x = x + 0.01 * np.array([np.cos(yaw), np.sin(yaw), 0.0])
    ...         else:
    ...             yaw += np.pi / 2 / n
    ...         c, s = np.cos(yaw), np.sin(yaw)  # optical axis along the heading, image y down
    ...         poses.append(StampedPose(i, Transform(np.array([[s, 0, c], [-c, 0, s], [0, -1, 0.0]]), x)))
    ...     return poses
    >>> truth = drive()
    >>> origin = truth[300].T_world_camera.translation  # 5 % shorter after the turn
    >>> shrunk = [p if i < 300 else StampedPose(p.stamp_ns, Transform(p.T_world_camera.rotation,
    ...           origin + 0.95 * (p.T_world_camera.translation - origin))) for i, p in enumerate(truth)]
    >>> walk = scale_walk(truth, shrunk, stretch_m=0.5)
    >>> round(walk.turn_step_percent, 1), round(walk.drive_walk_percent, 2), walk.turned_deg.round().tolist()
    (5.1, 0.0, [90.0])
    """
    if len(truth) != len(estimates):
        raise ValueError(f"{len(truth)} ground-truth poses for {len(estimates)} frames")
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, np.float64) / np.linalg.norm(up)
    n = len(truth)
    away = np.ones(n, bool) if away is None else np.asarray(away, bool)
    # a pose missing, or the target coming back into view (its pose corrects the map's):
    # nothing measured across such a frame is the map's own scale
    breaks = ~np.array([e is not None for e in estimates]) | (~away & np.r_[False, away[:-1]])
    true_xyz = np.array([t.T_world_camera.translation for t in truth]).reshape(-1, 3)
    path = _path_lengths(truth)
    heading = np.array([_heading(t.T_world_camera.rotation, up) for t in truth])
    turning = np.r_[0.0, np.cumsum(np.abs(np.angle(np.exp(1j * np.diff(heading)))))]
    broken = np.r_[0, np.cumsum(breaks)]  # breaks before frame i: broken[b + 1] - broken[a] in a..b
    inside = np.r_[0, np.cumsum(~away)]  # frames with the target in view before frame i
    ends = np.searchsorted(path, np.arange(0.0, path[-1], stretch_m))
    turned, turn_steps, drive_steps, under = [], [], [], []
    previous = None  # the last stretch with a scale: (middle frame, log scale)
    for a, b in zip(ends[:-1], ends[1:], strict=True):
        if broken[b + 1] - broken[a]:
            previous = None
            continue
        true_step = np.linalg.norm(true_xyz[b] - true_xyz[a])
        if true_step < 0.5 * stretch_m:  # bent double (a turn in it): no scale, but no break either
            continue
        est_step = np.linalg.norm(estimates[b].T_world_camera.translation - estimates[a].T_world_camera.translation)
        current = (int(np.searchsorted(path, 0.5 * (path[a] + path[b]))), np.log(max(est_step, 1e-12) / true_step))
        if previous is not None and inside[b + 1] == inside[a]:  # the scale after is the map's alone
            (m0, s0), (m1, s1) = previous, current
            total = np.degrees(turning[m1] - turning[m0])
            if total < turn_deg:
                drive_steps.append(abs(s1 - s0))
            else:
                turned.append(total)
                turn_steps.append(abs(s1 - s0))
                net = np.angle(np.exp(1j * (heading[m1] - heading[m0])))
                if abs(np.degrees(net)) >= turn_deg:
                    estimated = np.angle(np.exp(1j * (_heading(estimates[m1].T_world_camera.rotation, up)
                                                      - _heading(estimates[m0].T_world_camera.rotation, up))))
                    under.append(100.0 * (1.0 - estimated / net))
        previous = current
    return ScaleWalk(stretch_m, np.array(turned), np.array(turn_steps), np.array(drive_steps), np.array(under))


# NEES bounds for the position (3 dof): the chi-square 99.7 % bound, and a Mahalanobis
# distance of 5 (an error 5 standard deviations out along its own worst direction)
CHI2_3DOF_997 = 14.16
NEES_5_SIGMA = 25.0


@dataclass(frozen=True)
class RunScore:
    """How a run over a sequence went, frame by frame, against the ground truth."""

    frames: int
    with_pose: int
    coverage: float  # frames with a pose / frames
    longest_gap_frames: int  # the longest run of frames without a pose
    rmse_m: float  # absolute position error, no alignment (nan without a pose)
    max_m: float
    consistent: float  # share of poses with a covariance whose error is inside its 3-sigma ellipsoid
    beyond_5_sigma: int  # poses whose error is beyond 5 sigma of their own covariance (NEES > 25)
    without_covariance: int


def score_run(truth: list[StampedPose], poses: list[tuple[StampedPose, np.ndarray | None] | None]) -> RunScore:
    """Score one estimate per frame (``None`` for a frame without a pose, else the pose
    and its 6x6 covariance, ROS order, or None) against ``truth`` (one per frame, same
    order). Consistency is the NEES of the position: e^T S^-1 e with S the covariance's
    position block, against the chi-square bound for 3 dof (14.16 for 99.7 %) and 25 (a
    Mahalanobis distance of 5).

    >>> from cubeloc.positioning.geometry import Transform
    >>> t = [StampedPose(i, Transform.identity()) for i in range(4)]
    >>> off = Transform(np.eye(3), np.array([0.003, 0.0, 0.0]))
    >>> s = score_run(t, [None, (StampedPose(1, off), np.eye(6) * 1e-6), (StampedPose(2, off), None), None])
    >>> s.coverage, s.longest_gap_frames, round(s.rmse_m, 4), s.consistent, s.beyond_5_sigma
    (0.5, 1, 0.003, 1.0, 0)
    """
    if len(truth) != len(poses):
        raise ValueError(f"{len(truth)} ground-truth poses for {len(poses)} frames")
    errors, nees, gap, longest, without = [], [], 0, 0, 0
    for reference, entry in zip(truth, poses, strict=True):
        if entry is None:
            gap += 1
            longest = max(longest, gap)
            continue
        gap = 0
        estimate, covariance = entry
        error = estimate.T_world_camera.translation - reference.T_world_camera.translation
        errors.append(float(np.linalg.norm(error)))
        if covariance is None:
            without += 1
        else:
            nees.append(float(error @ np.linalg.solve(np.asarray(covariance)[:3, :3], error)))
    errors_a, nees_a = np.array(errors), np.array(nees)
    return RunScore(
        frames=len(truth),
        with_pose=len(errors),
        coverage=len(errors) / max(len(truth), 1),
        longest_gap_frames=longest,
        rmse_m=float(np.sqrt(np.mean(errors_a**2))) if len(errors) else float("nan"),
        max_m=float(errors_a.max()) if len(errors) else float("nan"),
        consistent=float(np.mean(nees_a <= CHI2_3DOF_997)) if len(nees) else float("nan"),
        beyond_5_sigma=int(np.sum(nees_a > NEES_5_SIGMA)),
        without_covariance=without,
    )


# a place "seen before": within this distance and view angle of an earlier posed frame,
# about how far ORB's matches against a keyframe reach (docs/notes/2026-12-05-far-halls-and-held-frames.md)
SEEN_BEFORE_RADIUS_M = 0.7
SEEN_BEFORE_ANGLE_DEG = 25.0


def lost_where_seen_before(truth: list[StampedPose], posed: list[bool], radius_m: float = SEEN_BEFORE_RADIUS_M,
                           angle_deg: float = SEEN_BEFORE_ANGLE_DEG) -> np.ndarray:
    """For each frame (``truth`` and ``posed`` one per frame, in time order): whether it has
    no pose although an earlier frame with a pose was taken within ``radius_m`` of it,
    looking within ``angle_deg`` of its direction (both on the truth): the frames a
    relocalisation against the map could at best give back. A frame lost elsewhere needs
    the map to grow first.

    >>> from cubeloc.positioning.geometry import Transform
    >>> at = lambda x, turned=False: StampedPose(0, Transform(np.diag([-1.0, 1.0, -1.0]) if turned else np.eye(3),
    ...                                                       np.array([x, 0.0, 0.0])))
    >>> truth = [at(0.0), at(5.0), at(0.2), at(9.0), at(0.1, turned=True)]
    >>> lost_where_seen_before(truth, [True, True, False, False, False]).tolist()
    [False, False, True, False, False]
    """
    if len(truth) != len(posed):
        raise ValueError(f"{len(truth)} ground-truth poses for {len(posed)} frames")
    centres = np.array([t.T_world_camera.translation for t in truth]).reshape(-1, 3)
    axes = np.array([t.T_world_camera.rotation[:, 2] for t in truth]).reshape(-1, 3)
    cos_limit = np.cos(np.radians(angle_deg))
    out = np.zeros(len(truth), bool)
    seen: list[int] = []
    for i, has_pose in enumerate(posed):
        if has_pose:
            seen.append(i)
        elif seen:
            near = np.linalg.norm(centres[seen] - centres[i], axis=1) < radius_m
            out[i] = bool(np.any(near & (axes[seen] @ axes[i] > cos_limit)))
    return out


def score_estimates(truth: list[StampedPose], estimates: list) -> RunScore:
    """``score_run`` for one pose estimate per frame (anything with ``T_world_camera`` and
    ``covariance``, such as the tracker's ``PoseEstimate``; None for a frame without a
    pose), each stamped as its frame's ground truth."""
    return score_run(truth, [None if e is None else (StampedPose(t.stamp_ns, e.T_world_camera), e.covariance)
                             for e, t in zip(estimates, truth, strict=True)])


def corners_sqpnp_pose(points_world: np.ndarray, pixels: np.ndarray, calibration) -> Transform | None:
    """The corners-only baseline a pose is measured against: SQPnP, then OpenCV's
    Levenberg-Marquardt, on all given corners (T_world_camera, or None)."""
    import cv2

    if len(points_world) < 4:
        return None
    from cubeloc.positioning.camera_model import solver_pixels
    from cubeloc.positioning.corner_pose import refine_lm

    solver = solver_pixels(pixels, calibration)
    ok, rvec, tvec = cv2.solvePnP(points_world, *solver, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return None
    if calibration.is_fisheye:  # LM on the fisheye's own pixels
        rvec, tvec = refine_lm(points_world, pixels, rvec.ravel(), tvec.ravel(), calibration)
    else:  # OpenCV's LM as it comes
        rvec, tvec = cv2.solvePnPRefineLM(points_world, *solver, rvec, tvec)
    return Transform.from_rvec_tvec(rvec.ravel(), tvec.ravel()).inverse()


def decoded_corners_pose(image: np.ndarray, target, calibration, detector) -> Transform | None:
    """The corners-only baseline on an image: ``target``'s tags decoded by ``detector``
    without decimation, then ``corners_sqpnp_pose`` on all their corners."""
    from cubeloc.positioning.target_pose import unique_target_detections

    found = unique_target_detections(detector.detect(image, None, 1.0), target)
    if not found:
        return None
    return corners_sqpnp_pose(target.corners_of(tuple(d.tag_id for d in found)),
                              np.concatenate([d.corners for d in found]), calibration)
