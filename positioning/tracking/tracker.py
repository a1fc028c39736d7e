"""The tracker's back end: initialisation on the target, then frame-to-map tracking.

Per frame it takes feature tracks (ids and pixels, from ``features.KltFrontEnd`` or any
other source) and, when the target is in view, a trusted target pose with its corners.

- Before a map exists it runs the paper's Algorithms 1 and 2 (``beginning``,
  ``initialiser``); when the target has gone before Algorithm 2's median parallax (out of
  the view, the hold on rays ended, or the reference's tracks run out), the map begins on
  the longest baseline the target gave (``Initialiser.on_departure``).
- Afterwards the pose comes from PnP with RANSAC on the map points' tracks, refined with
  Levenberg-Marquardt on the inliers, refused 0.5 m or 5 deg from the motion model's.
- While the target is trusted, its pose is the published pose and keyframes made then
  are *anchored*: the target's corners enter bundle adjustment as fixed world points, so
  the map cannot drift while the target is visible. When the target comes back and
  disagrees with the tracker by more than ``relocalised_jump_*``, the drifted part of the
  map is moved by the difference and the frame is published as RELOCALISED.
- A target pose less sure than the map (a grazing face, the image edge) neither corrects
  nor anchors it: the map's pose goes out (a 24 mm-sigma target pose had moved the map by
  12 mm on ``agile``). Where nothing else gives a pose, such a target pose goes out but
  makes no keyframe and is not taken for motion. The target corrects the map only against
  the map's own pose (PnP, or the motion model on a map tracked until the last frame).
- Keyframes on baseline (parallax) and visibility criteria, on every frame while the map
  runs short (a turn carries its points out of view); tracks without a point are
  triangulated against the first keyframe that saw them, from 0.7 deg of parallax (0.3
  while the map runs short); a sliding-window bundle adjustment runs after each keyframe,
  in a worker thread when ``bundle.background``.
- Too few map points for PnP (a turn on the spot, a passer-by): the pose is *held*
  (``hold.RayHold``): orientation from every track's ray, position from the points left
  and the motion model; nothing at all in view: the motion model for at most 0.5 s. With
  wheel odometry (``odometry``, an ``odometry.OdometryPrior``) its motion is the
  prediction and the held position; lost, its pose from the last one is published
  ("bridged") while the map waits for the camera.
- Every pose carries a 6x6 covariance: the target's, or this frame's fit (``pose_fit``)
  plus the drift since the target was last trusted (``hold.Drift``).
- No pose from any of these: the frame is "lost" (no estimate). Recovery is by the
  target, or by ``relocalised()`` when the caller matched the image to keyframes.
- Lost, and the target's pose is sure enough to begin a map (``init.max_position_std_m``)
  but not to anchor keyframes: Algorithms 1 and 2 run again on it, as at the start, while
  the map gives no pose, and the map they begin joins this one (``beginning_again``); the
  caller keeps looking for the map's keyframes meanwhile, and a relocalisation into them
  ends it.
"""

from __future__ import annotations

import concurrent.futures
from dataclasses import replace

import numpy as np
import structlog

from calib.camera_info import CameraCalibration
from positioning.camera_model import project, undistort
from positioning.estimator import FrameResult, PoseEstimate, PoseSource, PoseState
from positioning.geometry import Transform
from positioning.tracking import bundle
from positioning.tracking.beginning import MapBeginning
from positioning.tracking.hold import Drift, RayHold, position_sigma
from positioning.tracking.initialiser import InitFrame, Initialiser, InitStatus
from positioning.tracking.loop_closure import LoopClosure
from positioning.tracking.map import Map
from positioning.tracking.odometry import OdometryPrior
from positioning.tracking.options import TrackerOptions
from positioning.tracking.pose_fit import beyond_motion, pose_from_map, pose_from_target_and_map
from positioning.tracking.types import TargetObservation, TrackerOutput, Tracks

log = structlog.get_logger()


class Tracker(MapBeginning, LoopClosure):
    def __init__(self, calibration: CameraCalibration, options: TrackerOptions | None = None) -> None:
        self.calibration = calibration
        self.options = options or TrackerOptions()
        self.fx = calibration.fx
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._pending: concurrent.futures.Future | None = None
        self.bundle_runs: list[bundle.BundleSolution] = []  # the last few, for benchmarks and tests
        self.odometry: OdometryPrior | None = None  # wheel odometry, when the robot gives it (kept on reset)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the map and initialise again on the target."""
        self._drain_bundle()
        self.map = Map()
        self.initialiser = Initialiser(self.options.init, self.fx)
        self.initialised, self.lost = False, False
        self._last: Transform | None = None  # pose of the last frame with one
        self._last_stamp, self._last_covariance = 0, None  # and its time stamp and covariance
        # camera motion per second (rotation vector, translation of T_last_next in the last camera's
        # frame): per second, as a live camera's frames come irregularly (the queue skips when behind)
        self._velocity: tuple[np.ndarray, np.ndarray] | None = None
        self._after_relocalisation = False  # the last pose came from relocalised()
        self._measured: tuple[Transform, int] | None = None  # the last pose measured (not held), its stamp
        self._frame_tracks, self._frame_xn = Tracks.empty(), np.zeros((0, 2))
        self._frame_pose: Transform | None = None
        self._frame_target: TargetObservation | None = None
        self._frame_stamp = 0
        self._frame_keyframe = None
        self._frame_sigma = 0.0  # this frame's pose: its own position standard deviation
        self._scale_points_added = 0  # the map's points_added when the drift's scale was last measured
        self._reference_target: TargetObservation | None = None
        # lost, and the target sure enough to begin a map, not to anchor keyframes:
        # Algorithms 1 and 2 run again and add their map to this one (beginning.py)
        self._beginning_again = False
        self._best_target: TargetObservation | None = None  # of the initialiser's best frame B
        self._kf_points_at_insert = 0
        self._frames_since_keyframe = 0
        self._target_seen = False  # the last frame had a trusted target pose
        self._target_stamp = 0  # when the target was last trusted (the drift's start)
        self.loops_closed, self.loops_refused = 0, 0  # loop closures applied and refused (close_loop)
        self.last_closure: tuple[int, Transform, Transform] | None = None  # its stamp, the pose before and after
        self._loop_evidence: list[tuple] = []  # close_loop's matches not yet applied
        self._bundle_due = False  # a keyframe arrived while bundle adjustment was running
        # the rays that hold the orientation when few map points are in view; the drift since the target
        self._hold = RayHold(self.options, self.fx)
        self._drift = Drift(self.options)

    def close(self) -> None:
        self._drain_bundle()
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None

    # ------------------------------------------------------------------ per frame
    def step(self, stamp_ns: int, tracks: Tracks, target: TargetObservation | None) -> TrackerOutput:
        self._collect_bundle(wait=False)
        xn = undistort(tracks.pixels, self.calibration)
        self._frame_tracks, self._frame_xn, self._frame_stamp = tracks, xn, stamp_ns
        self._frame_target, self._frame_keyframe, self._frame_pose = target, None, None
        trusted = target if target is not None and target.planes >= self.options.init.min_planes else None
        if not self.initialised:
            return self._initialising(stamp_ns, tracks, xn, trusted)

        prediction = self.predict(stamp_ns)
        tracked, inliers, drop, rms, covariance = pose_from_map(self.map, tracks, xn, prediction, self.options,
                                                                self.fx)
        if self.odometry is not None:  # the wheels' motion since the last pose: a relative-motion factor
            tracked, covariance = self.odometry.fuse(tracked, covariance, self._last, self._last_stamp, stamp_ns)
        begun = self._beginning_again_on(stamp_ns, tracks, xn, trusted, tracked is not None)
        if begun is not None:
            return begun
        held = None
        if tracked is None and trusted is None and prediction is not None:
            odometry = None if self.odometry is None or not self.odometry.as_prior else self.odometry.covariance(
                self._hold.since or self._last_stamp, stamp_ns)
            held = self._hold.hold(stamp_ns, self._last, self._last_stamp, prediction, tracks, xn, self.map, odometry)
        if trusted is None and self._beginning_again:
            departed = self._departed(held, stamp_ns, tracks)
            if departed is not None:
                return departed
        if trusted is not None and tracked is not None and self._anchors(trusted):
            # how far the map's own pose is from the target's: what a tracking pose may be
            # off by as soon as the target leaves (the drift's floor)
            self._drift.agreement(float(np.linalg.norm(tracked.translation - trusted.T_world_camera.translation)))
        if trusted is not None and tracked is not None and not self.lost and not self._anchors(trusted):
            # the target at a grazing angle or the image edge is less sure than the map:
            # the map's pose goes out, and the target neither corrects nor anchors it
            trusted = None
        if trusted is not None:
            pose = trusted.T_world_camera
            state = PoseState.TARGET
            # the map's own pose: after a hold the prediction is the motion model's, and a
            # correction by it would move the map by the hold's error
            before = tracked if tracked is not None else (None if self.lost or self.holding else prediction)
            if self.lost:
                state = PoseState.RELOCALISED
            elif before is not None and not self._target_seen and (tracked is not None or self.jumped(before, pose)):
                # the map drifted while the target was away: spread the correction along it
                self.map.correct(pose @ before.inverse(), self._drift.grown_m)
                log.debug("tracker.corrected", jump_m=float(np.linalg.norm(pose.translation - before.translation)))
                state = PoseState.RELOCALISED if self.jumped(before, pose) else state
            if tracked is not None and state is PoseState.TARGET and self.options.fuse_target_with_map:
                fused = pose_from_target_and_map(self.map, trusted.corners_world,
                                                 undistort(trusted.corners_px, self.calibration), tracks, xn, pose,
                                                 self.options.pnp_reproj_px, self.fx)
                pose = fused if fused is not None and not self.jumped(fused, pose) else pose
            estimate = PoseEstimate(pose, state, trusted.planes, trusted.tag_ids, trusted.reproj_rms_px,
                                    trusted.published_covariance, PoseSource.TARGET)
        elif tracked is not None or held is not None:
            pose, covariance = (tracked, covariance) if tracked is not None else held
            state = PoseState.RELOCALISED if self.lost else PoseState.TRACKING
            source = PoseSource.MAP if tracked is not None else PoseSource.HELD
            estimate = PoseEstimate(pose, state, 0, (), rms, self._drift.covariance(self._last, pose, covariance),
                                    source)
        else:
            self.lost, self._velocity, self._target_seen = True, None, False
            self._hold.end()
            detail = f"{inliers} map points agree with a pose, {self.options.min_pnp_inliers} needed"
            bridged = None if self.odometry is None or self._last is None else self.odometry.bridge(
                self._last, self._last_stamp, self._last_covariance, stamp_ns, self.options.max_hold_s)
            if bridged is not None:  # published, and nothing else: the map waits for the camera
                estimate = PoseEstimate(bridged[0], PoseState.TRACKING, 0, (), 0.0, bridged[1], PoseSource.ODOMETRY)
                return TrackerOutput(FrameResult(estimate, "bridged", f"wheel odometry; {detail}"), False, drop)
            return TrackerOutput(FrameResult(None, "lost", detail), False, drop)

        forced = state is PoseState.RELOCALISED
        self._target_seen = trusted is not None
        if trusted is not None:
            self._drift.reset()
            self._target_stamp = stamp_ns
        self.lost = False
        if held is None:
            self._hold.end()
        self._hold.rebase(pose if held is None else None, tracks.ids, xn)
        self._frame_sigma = position_sigma(trusted.covariance if trusted is not None else covariance)
        self._last_covariance = estimate.covariance
        # a visible correction is where the camera is, not how it moved, and the steps into
        # and out of a target pose too uncertain to anchor are its error: the velocity stays
        self._after_relocalisation = self._after_relocalisation or forced
        noisy = trusted is not None and not self._anchors(trusted)
        self._update_motion(pose, stamp_ns, noisy=noisy)
        if held is None and not noisy:
            self._measured = (pose, stamp_ns)
        self._frame_pose = pose
        if held is not None:
            # no keyframe from a pose whose position is only held: nothing is triangulated
            # from it; fresh corners keep the rays coming
            return TrackerOutput(FrameResult(estimate, "ok", "held: orientation from rays"), True, drop)
        status = "ok" if state is not PoseState.RELOCALISED else "relocalised"
        if trusted is not None and not self._anchors(trusted):
            # nor from a target pose too uncertain to anchor: each is off on its own, and points
            # triangulated between two of them are off by as much as their baseline
            return TrackerOutput(FrameResult(estimate, status, "target pose too uncertain to map from"), True, drop)
        want = self._maybe_keyframe(stamp_ns, pose, tracks, xn, trusted, inliers, forced)
        return TrackerOutput(FrameResult(estimate, status), want, drop, keyframe=want)

    @property
    def holding(self) -> bool:
        """The last pose came from rays and the motion model (too few map points in view)."""
        return self._hold.holding

    def add_tracks(self, tracks: Tracks) -> None:
        """Fresh corners detected in the frame just stepped (after ``want_features``)."""
        if len(tracks.ids) == 0:
            return
        xn = undistort(tracks.pixels, self.calibration)
        pose = self._frame_pose if self._frame_pose is not None else (
            self._frame_target.T_world_camera if self._frame_target is not None else None)
        if pose is not None:
            self._hold.add(pose, tracks.ids, xn)
        all_ids, all_xn = np.concatenate([self._frame_tracks.ids, tracks.ids]), np.concatenate([self._frame_xn, xn])
        self._frame_tracks = Tracks(all_ids, np.concatenate([self._frame_tracks.pixels, tracks.pixels]))
        self._frame_xn = all_xn
        if self._frame_keyframe is not None:
            self._frame_keyframe.add_observations(tracks.ids, xn)
        elif (not self.initialised or self._beginning_again) and self._anchors(self._frame_target):
            frame = InitFrame(self._frame_stamp, self._frame_target.T_world_camera, self._frame_target.planes,
                              all_ids, all_xn)
            if self.initialiser.try_reference(frame).status is InitStatus.REFERENCE_SET:
                self._reference_target = self._frame_target

    def relocalised(self, stamp_ns: int, pose: Transform, tracks: Tracks, covariance: np.ndarray | None = None
                    ) -> np.ndarray | None:
        """The caller found ``pose`` by matching this frame to the keyframes, and follows
        the matched map points again as ``tracks``. The frame becomes a keyframe, so the
        fresh corners that ``add_tracks`` brings next can be triangulated against it.
        Returns the pose's covariance: the match's (``covariance``) plus the drift."""
        self._drift.relocalised(covariance)
        self._end_beginning_again()
        match, covariance = covariance, self._drift.covariance(self._last, pose, covariance)
        self._hold.end()
        self.lost = False
        # the velocity stays: a relocalisation corrects where the camera is, not how it
        # moves (spin_on_axis, 4.5 deg a frame: without it the next frame's unguided KLT
        # lost 3/4 of the tracks, three relocalisations in a row and then the track);
        # unless it cannot have brought the camera here from the last pose measured
        # (PnP would refuse this pose against its prediction): lost, the velocity is none
        # and held steps make it a standstill, and in a spin every frame after was then
        # found by relocalisation alone (narrow lens at 90 deg/s: 30 frames)
        if self._measured is not None:
            before, before_stamp = self._measured
            dt = (stamp_ns - before_stamp) / 1e9
            if 0.0 < dt <= self.options.max_extrapolation_s:
                expected = before if self._velocity is None else self._extrapolated(before, dt)
                if beyond_motion(pose, expected, self.options):
                    self._velocity = _velocity(before, pose, dt)
        self._measured = (pose, stamp_ns)
        self._last, self._last_stamp, self._last_covariance = pose, stamp_ns, covariance
        self._after_relocalisation = True
        self._frame_pose, self._frame_stamp = pose, stamp_ns
        self._frame_tracks, self._frame_xn = tracks, undistort(tracks.pixels, self.calibration)
        self._frame_keyframe = self.map.add_keyframe(stamp_ns, pose, tracks.ids, self._frame_xn)
        self._frame_keyframe.position_sigma_m, self._frame_keyframe.drift_m = position_sigma(match), self._drift.grown_m
        self._frames_since_keyframe, self._kf_points_at_insert = 0, len(tracks.ids)
        return covariance

    @property
    def last_pose(self) -> Transform | None:
        return self._last

    # ------------------------------------------------------------------ tracking
    def predict(self, stamp_ns: int) -> Transform | None:
        """The pose at ``stamp_ns`` by the constant-velocity motion model (the last pose
        when the velocity is unknown or the gap too long to extrapolate; None when lost
        or without a pose): where tracks and the target are looked for."""
        if self._last is None or self.lost:
            return None
        carried = None if self.odometry is None else self.odometry.prior(self._last, self._last_stamp, stamp_ns)
        if carried is not None:  # the wheels' motion, where there is odometry and it is the prior
            return carried
        dt = (stamp_ns - self._last_stamp) / 1e9
        if self._velocity is None or not 0.0 < dt <= self.options.max_extrapolation_s:
            return self._last
        return self._extrapolated(self._last, dt)

    def _extrapolated(self, pose: Transform, dt: float) -> Transform:
        """``pose`` carried ``dt`` seconds on by the velocity."""
        rotation_per_s, translation_per_s = self._velocity
        return pose @ Transform.from_rvec_tvec(rotation_per_s * dt, translation_per_s * dt)

    def _update_motion(self, pose: Transform, stamp_ns: int, noisy: bool = False) -> None:
        """Take ``pose`` as the last one and the step to it as the velocity, unless the
        step is a correction or ``noisy`` (then the velocity stays, also for the next step)."""
        dt = (stamp_ns - self._last_stamp) / 1e9
        if self._last is None or not 0.0 < dt <= self.options.max_extrapolation_s:
            self._velocity = None
        elif noisy:
            pass
        elif self._after_relocalisation and self._velocity is not None:
            # the step from a relocalised pose measures its correction (its match is some
            # millimetres off), not the camera's motion: the velocity it had stays one
            # more frame (spin_on_axis: 11.6 -> 5.3 mm RMS, blank_wall 25 -> 15 mm)
            pass
        else:
            self._velocity = _velocity(self._last, pose, dt)
        self._after_relocalisation = noisy
        self._last, self._last_stamp = pose, stamp_ns

    def predict_pixels(self, stamp_ns: int, ids: np.ndarray, pixels: np.ndarray) -> np.ndarray | None:
        """Where the tracks ``ids`` (now at ``pixels``, in the last frame with a pose) should
        be in the frame at ``stamp_ns``, by the motion model; None when it knows nothing.

        The front end starts its search there, so a fast turn or a skipped frame does not
        carry the features beyond KLT's reach (its pyramid follows ~80 px; a 2 deg/frame
        turn at 10 fps moves them ~60 px, twice that when a frame is skipped). Tracks with
        a map point are projected from it; the others as if at the map's median depth."""
        if self._last_stamp != self._frame_stamp:
            return None  # the last pose is older than the tracks' frame (no pose there)
        prediction = self.predict(stamp_ns)
        if prediction is None or self._velocity is None or len(ids) == 0:
            return None
        T_next_last = prediction.inverse() @ self._last
        rays = np.column_stack([undistort(pixels, self.calibration), np.ones(len(ids))])
        has = np.array([int(t) in self.map.points for t in ids], dtype=bool)
        in_last = np.zeros((len(ids), 3))
        if has.any():
            world = np.array([self.map.points[int(t)] for t in ids[has]])
            in_last[has] = self._last.inverse().apply(world)
        depths = in_last[has, 2][in_last[has, 2] > 0]
        # without map points (initialising) the target's distance is the best guess there is
        depth = float(np.median(depths)) if len(depths) else float(np.linalg.norm(self._last.translation))
        in_last[~has] = rays[~has] * float(np.clip(depth, 0.2, 50.0))
        in_next = T_next_last.apply(in_last)
        projected = project(in_next, self.calibration)
        # a point behind the camera has no sensible guess: search from where it was
        unusable = (in_next[:, 2] <= 1e-3) | ~np.all(np.isfinite(projected), axis=1)
        projected[unusable] = np.asarray(pixels, np.float64).reshape(-1, 2)[unusable]
        return projected

    def _anchors(self, target: TargetObservation | None, bound: float | None = None) -> bool:
        """Is this target pose sure enough to hold a keyframe (and so the map) in place? A less sure one
        is published, not bent to; with no map to track on (before one exists, or beginning
        again) ``init.max_position_std_m`` (none is worse). ``bound`` asks for another."""
        if target is None or target.reproj_rms_px > self.options.anchor_max_reproj_px:
            return False
        if bound is None:
            beginning = not self.initialised or self._beginning_again
            bound = self.options.init.max_position_std_m if beginning else self.options.anchor_max_position_std_m
        return target.covariance is None or position_sigma(target.covariance) <= bound

    def jumped(self, a: Transform, b: Transform) -> bool:
        """``a`` and ``b`` further apart than ``relocalised_jump_*``: a visible correction."""
        return (np.linalg.norm(a.translation - b.translation) > self.options.relocalised_jump_m
                or np.degrees(a.rotation_angle_to(b)) > self.options.relocalised_jump_deg)

    def _maybe_keyframe(self, stamp_ns: int, pose: Transform, tracks: Tracks, xn: np.ndarray,
                        trusted: TargetObservation | None, inliers: int, forced: bool) -> bool:
        o = self.options
        self._frames_since_keyframe += 1
        last = self.map.last_keyframe
        if last is None:
            forced = True
        if not forced:
            with_points = [self.map.points[int(t)] for t in tracks.ids if int(t) in self.map.points]
            depth = np.median(pose.inverse().apply(np.array(with_points))[:, 2]) if with_points else 1.0
            baseline = np.linalg.norm(pose.translation - last.T_world_camera.translation) / max(depth, 1e-3)
            ratio = o.anchored_keyframe_baseline_ratio if trusted is not None else o.keyframe_baseline_ratio
            needed = (baseline > ratio
                      or inliers < o.keyframe_tracked_ratio * self._kf_points_at_insert
                      or inliers < o.keyframe_min_points)
            # running short of map points (a turn carries them out of view): a keyframe every
            # frame, so each new track is triangulated as soon as its parallax allows
            starving = inliers < o.keyframe_starving_points
            if not needed or (self._frames_since_keyframe < 2 and not starving):
                return False
        anchor = trusted if self._anchors(trusted) else None
        target_world = anchor.corners_world if anchor is not None else None
        target_xn = undistort(anchor.corners_px, self.calibration) if anchor is not None else None
        kf = self.map.add_keyframe(stamp_ns, pose, tracks.ids, xn, target_world, target_xn)
        kf.position_sigma_m, kf.drift_m = self._frame_sigma, self._drift.grown_m
        self._frame_keyframe = kf
        self._frames_since_keyframe = 0
        self.map.triangulate(kf, self.fx, o.triangulation_starving_parallax_deg
                             if inliers < o.triangulation_starving_points else o.triangulation_min_parallax_deg,
                             o.triangulation_max_reproj_px, o.triangulation_min_baseline_sigmas)
        self._kf_points_at_insert = sum(1 for t in kf.track_ids if int(t) in self.map.points)
        live = {int(t) for t in tracks.ids}
        if o.loop_closure:  # places left behind stay, a few, for a loop to close on
            self.map.thin(o.max_keyframes + o.loop_kept_keyframes, o.max_keyframes, live, keep_fixed=True)
        else:
            self.map.cull(o.max_keyframes, live)
        self._schedule_bundle()
        return True

    # ------------------------------------------------------------------ bundle adjustment
    def _schedule_bundle(self) -> None:
        if self._pending is not None:
            self._bundle_due = True  # one at a time: the next run starts when this one ends
            return
        self._bundle_due = False
        problem = bundle.build_problem(self.map, self.options.bundle)
        if problem is None:
            return
        if not self.options.bundle.background:
            self._apply(bundle.solve(problem, self.options.bundle, self.fx, self.options.track_sigma_px))
            return
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="cubeloc-ba")
        self._pending = self._executor.submit(bundle.solve, problem, self.options.bundle, self.fx,
                                              self.options.track_sigma_px)

    def _collect_bundle(self, wait: bool) -> None:
        if self._pending is None or not (wait or self._pending.done()):
            return
        future, self._pending = self._pending, None
        self._apply(future.result())
        if self._bundle_due:  # keyframes came while it ran: adjust them too
            self._schedule_bundle()

    def wait_for_bundle(self) -> None:
        """Block until the running bundle adjustment (if any) is done and applied. The frame
        loop never calls this; replays that feed frames faster than a camera do."""
        self._collect_bundle(wait=True)

    def _drain_bundle(self) -> None:
        if getattr(self, "_pending", None) is not None:
            self._pending.result()
            self._pending = None

    def _apply(self, solution: bundle.BundleSolution) -> None:
        applied = bundle.apply_solution(self.map, solution)
        if applied and solution.scale_var is not None:
            # the share of the window's points added since the last solution measured the scale
            renewed = (solution.points_added - self._scale_points_added) / max(len(solution.point_ids), 1)
            self._scale_points_added = solution.points_added
            self._drift.scale_measured(solution.scale_var, renewed, solution.held_by_target)
        self.bundle_runs = [*self.bundle_runs[-19:], replace(solution, points=np.zeros((0, 3)))]
        log.debug("tracker.bundle", applied=applied, seconds=round(solution.seconds, 3),
                  rms_before=round(solution.initial_rms_px, 3), rms_after=round(solution.final_rms_px, 3))


def _velocity(a: Transform, b: Transform, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The camera's motion per second from ``a`` to ``b``, ``dt`` seconds apart (rotation vector
    and translation of T_a_b, in a's frame)."""
    step = a.inverse() @ b
    return step.rvec() / dt, step.translation / dt
