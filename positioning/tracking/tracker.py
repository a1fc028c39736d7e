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

import collections
import concurrent.futures
from dataclasses import replace

import numpy as np
import structlog

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.camera_model import project, undistort
from cubeloc.positioning.estimator import FrameResult, PoseEstimate, PoseSource, PoseState
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking import bundle
from cubeloc.positioning.tracking.beginning import MapBeginning
from cubeloc.positioning.tracking.floor import Floor, TargetView, floor_from_views
from cubeloc.positioning.tracking.hold import Drift, RayHold, position_sigma
from cubeloc.positioning.tracking.initialiser import InitFrame, Initialiser, InitStatus
from cubeloc.positioning.tracking.loop_closure import LoopClosure
from cubeloc.positioning.tracking.map import Keyframe, Map
from cubeloc.positioning.tracking.motion import MotionModel
from cubeloc.positioning.tracking.odometry import OdometryPrior
from cubeloc.positioning.tracking.options import TrackerOptions
from cubeloc.positioning.tracking.pose_fit import pose_from_map, pose_from_target_and_map
from cubeloc.positioning.tracking.types import (
    TargetObservation,
    TrackedFrame,
    TrackerOutput,
    Tracks,
)

log = structlog.get_logger()


class Tracker(MapBeginning, LoopClosure):
    def __init__(self, calibration: CameraCalibration, options: TrackerOptions | None = None,
                 odometry: OdometryPrior | None = None) -> None:
        self.calibration = calibration
        self.options = options or TrackerOptions()
        self.fx = calibration.fx
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._pending: concurrent.futures.Future | None = None
        self.bundle_runs: list[bundle.BundleSolution] = []  # the last few, for benchmarks and tests
        self.odometry = odometry  # wheel odometry, when the robot gives it (kept on reset)
        self.motion = MotionModel(self.options)
        # the surest target pose this camera has given (position standard deviation, and
        # its corners' fit), and whether one ever met the anchor bounds: a camera that never
        # did is held to what it can do instead (``_anchors``); kept through reset, as they
        # are the camera's and the target's
        self._surest_target_m, self._best_target_fit_px = np.inf, np.inf
        self._bounds_reached = False
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the map and initialise again on the target."""
        self._drain_bundle()
        self.map = Map()
        self.initialiser = Initialiser(self.options.init, self.fx)
        self.initialised, self.lost = False, False
        self.motion.reset()
        self._tracks_stamp = 0  # the frame the front end's tracks are in (the last stepped or relocalised)
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
        self.relocalised_ns = 0  # when a frame was last relocalised in the map: no loop closes just after
        self._bundle_due = False  # a keyframe arrived while bundle adjustment was running
        # the rays that hold the orientation when few map points are in view; the drift since the target
        self._hold = RayHold(self.options, self.fx)
        self._drift = Drift(self.options)
        self.floor: Floor | None = None  # the floor under the robot (floor.py), once the target shows it
        self._target_views: collections.deque[TargetView] = collections.deque(maxlen=150)  # anchoring ones
        self._floor_due = False  # target views came since the floor was last found

    def start_lost_on(self, world_map: Map) -> None:
        """Track on ``world_map`` (a saved map) from the next frame: lost on it until a
        relocalisation into its keyframes, or the target, gives a pose."""
        self.map = world_map
        self.initialised, self.lost = True, True

    def close(self) -> None:
        self._drain_bundle()
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None

    # ------------------------------------------------------------------ per frame
    def step(self, stamp_ns: int, tracks: Tracks, target: TargetObservation | None) -> TrackerOutput:
        """This frame's pose from its ``tracks`` and the ``target`` observed in it (None:
        not seen); the output's ``frame`` is what ``add_tracks`` takes next."""
        self._collect_bundle(wait=False)
        self._tracks_stamp = stamp_ns
        return self._step(TrackedFrame(stamp_ns, tracks, undistort(tracks.pixels, self.calibration), target))

    def _step(self, frame: TrackedFrame) -> TrackerOutput:
        stamp_ns, tracks, xn, target = frame.stamp_ns, frame.tracks, frame.xn, frame.target
        trusted = target if target is not None and target.planes >= self.options.init.min_planes else None
        if trusted is not None:  # (no covariance: taken as sure, as ``_anchors`` takes it)
            sigma = position_sigma(trusted.covariance)
            self._best_target_fit_px = min(self._best_target_fit_px, trusted.reproj_rms_px)
            self._surest_target_m = min(self._surest_target_m, sigma)
            self._bounds_reached = self._bounds_reached or (
                sigma <= self.options.anchor.max_position_std_m
                and trusted.reproj_rms_px <= self.options.anchor.max_reproj_px)
            if self.options.bundle.floor.enabled and self._anchors(trusted, self.options.anchor.max_position_std_m):
                # the frames the floor is found in (floor.py)
                self._target_views.append(TargetView(trusted.T_world_camera, tracks.ids.copy(), xn.copy()))
                self._floor_due = True
        if not self.initialised:
            return self._initialising(frame, trusted)

        prediction = self.predict(stamp_ns)
        tracked, inliers, drop, rms, covariance = pose_from_map(self.map, tracks, xn, prediction, self.options,
                                                                self.fx)
        last = self.motion.last
        if self.odometry is not None:  # the wheels' motion since the last pose: a relative-motion factor
            tracked, covariance = self.odometry.fuse(tracked, covariance, last, self.motion.stamp, stamp_ns)
        begun = self._beginning_again_on(frame, trusted, tracked is not None)
        if begun is not None:
            return begun
        held = None
        if tracked is None and trusted is None and prediction is not None:
            odometry = None if self.odometry is None or not self.odometry.as_prior else self.odometry.covariance(
                self._hold.since or self.motion.stamp, stamp_ns)
            held = self._hold.hold(stamp_ns, self.motion, prediction, tracks, xn, self.map, odometry)
        if trusted is None and self._beginning_again:
            departed = self._departed(frame, held)
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
            if tracked is not None and state is PoseState.TARGET and self.options.anchor.fuse_with_map:
                fused = pose_from_target_and_map(self.map, trusted.corners_world,
                                                 undistort(trusted.corners_px, self.calibration), tracks, xn, pose,
                                                 self.options.pnp.reproj_px, self.fx)
                pose = fused if fused is not None and not self.jumped(fused, pose) else pose
            estimate = PoseEstimate(pose, state, trusted.planes, trusted.tag_ids, trusted.reproj_rms_px,
                                    trusted.published_covariance, PoseSource.TARGET)
        elif tracked is not None or held is not None:
            pose, covariance = (tracked, covariance) if tracked is not None else held
            state = PoseState.RELOCALISED if self.lost else PoseState.TRACKING
            source = PoseSource.MAP if tracked is not None else PoseSource.HELD
            estimate = PoseEstimate(pose, state, 0, (), rms, self._drift.covariance(last, pose, covariance), source)
        else:
            self.lost, self._target_seen = True, False
            self.motion.stop()
            self._hold.end()
            detail = f"{inliers} map points agree with a pose, {self.options.pnp.min_inliers} needed"
            bridged = None if self.odometry is None or last is None else self.odometry.bridge(
                last, self.motion.stamp, self.motion.covariance, stamp_ns, self.options.hold.max_bridge_s)
            if bridged is not None:  # published, and nothing else: the map waits for the camera
                estimate = PoseEstimate(bridged[0], PoseState.TRACKING, 0, (), 0.0, bridged[1], PoseSource.ODOMETRY)
                return TrackerOutput(FrameResult(estimate, "bridged", f"wheel odometry; {detail}"), False, drop,
                                     frame=frame)
            return TrackerOutput(FrameResult(None, "lost", detail), False, drop, frame=frame)

        forced = state is PoseState.RELOCALISED
        self._target_seen = trusted is not None
        if trusted is not None:
            self._drift.reset()
            self._target_stamp = stamp_ns
        self.lost = False
        if held is None:
            self._hold.end()
        # this pose's own covariance (the target's, PnP's or the hold's; the drift apart): what
        # rays started on it, and a velocity measured to it, are worth
        own = trusted.published_covariance if trusted is not None else covariance
        self._hold.rebase(pose if held is None else None, tracks.ids, xn, own)
        sigma = position_sigma(trusted.covariance if trusted is not None else covariance)
        self.motion.covariance = estimate.covariance
        # a visible correction is where the camera is, not how it moved, and the steps into
        # and out of a target pose too uncertain to anchor are its error: the velocity stays
        self.motion.after_relocalisation = self.motion.after_relocalisation or forced
        noisy = trusted is not None and not self._anchors(trusted)
        self.motion.update(pose, stamp_ns, noisy=noisy, own=own, held=held is not None)
        if held is None and not noisy:
            self.motion.measured = (pose, stamp_ns)
        frame = replace(frame, pose=pose)
        if held is not None:
            # no keyframe from a pose whose position is only held: nothing is triangulated
            # from it; fresh corners keep the rays coming
            return TrackerOutput(FrameResult(estimate, "ok", "held: orientation from rays"), True, drop, frame=frame)
        status = "ok" if state is not PoseState.RELOCALISED else "relocalised"
        if trusted is not None and not self._anchors(trusted):
            # nor from a target pose too uncertain to anchor: each is off on its own, and points
            # triangulated between two of them are off by as much as their baseline
            return TrackerOutput(FrameResult(estimate, status, "target pose too uncertain to map from"), True, drop,
                                 frame=frame)
        keyframe = self._maybe_keyframe(frame, pose, sigma, trusted, inliers, forced)
        return TrackerOutput(FrameResult(estimate, status), keyframe is not None, drop,
                             frame=replace(frame, keyframe=keyframe))

    @property
    def holding(self) -> bool:
        """The last pose came from rays and the motion model (too few map points in view)."""
        return self._hold.holding

    def add_tracks(self, frame: TrackedFrame, tracks: Tracks) -> TrackedFrame:
        """Fresh corners detected in ``frame`` (after ``want_features``): the frame with them."""
        if len(tracks.ids) == 0:
            return frame
        xn = undistort(tracks.pixels, self.calibration)
        pose = frame.pose if frame.pose is not None else (
            frame.target.T_world_camera if frame.target is not None else None)
        if pose is not None:
            self._hold.add(pose, tracks.ids, xn)
        all_ids, all_xn = np.concatenate([frame.tracks.ids, tracks.ids]), np.concatenate([frame.xn, xn])
        frame = replace(frame, tracks=Tracks(all_ids, np.concatenate([frame.tracks.pixels, tracks.pixels])),
                        xn=all_xn)
        if frame.keyframe is not None:
            frame.keyframe.add_observations(tracks.ids, xn)
        elif (not self.initialised or self._beginning_again) and self._anchors(frame.target):
            init = InitFrame(frame.stamp_ns, frame.target.T_world_camera, frame.target.planes, all_ids, all_xn,
                             frame.target.position_covariance)
            if self.initialiser.try_reference(init).status is InitStatus.REFERENCE_SET:
                self._reference_target = frame.target
        return frame

    def relocalised(self, stamp_ns: int, pose: Transform, tracks: Tracks, covariance: np.ndarray | None = None
                    ) -> tuple[np.ndarray | None, TrackedFrame]:
        """The caller found ``pose`` by matching this frame to the keyframes, and follows
        the matched map points again as ``tracks``. The frame becomes a keyframe, so the
        fresh corners that ``add_tracks`` brings next can be triangulated against it.
        Returns the pose's covariance (the match's, ``covariance``, plus the drift) and
        the frame."""
        self._drift.relocalised(covariance)
        self.relocalised_ns = stamp_ns
        self._end_beginning_again()
        match, covariance = covariance, self._drift.covariance(self.motion.last, pose, covariance)
        self._hold.end()
        self.lost = False
        self.motion.relocalised(pose, stamp_ns, covariance, match)
        self._tracks_stamp = stamp_ns
        xn = undistort(tracks.pixels, self.calibration)
        keyframe = self.map.add_keyframe(stamp_ns, pose, tracks.ids, xn)
        keyframe.position_sigma_m, keyframe.drift_m = position_sigma(match), self._drift.grown_m
        self._frames_since_keyframe, self._kf_points_at_insert = 0, len(tracks.ids)
        return covariance, TrackedFrame(stamp_ns, tracks, xn, None, pose, keyframe)

    @property
    def last_pose(self) -> Transform | None:
        return self.motion.last

    # ------------------------------------------------------------------ tracking
    def predict(self, stamp_ns: int) -> Transform | None:
        """The pose at ``stamp_ns`` by the motion model (``motion.MotionModel.predict``;
        None when lost or without a pose): where tracks and the target are looked for."""
        return None if self.lost else self.motion.predict(stamp_ns, self.odometry)

    def predict_pixels(self, stamp_ns: int, ids: np.ndarray, pixels: np.ndarray) -> np.ndarray | None:
        """Where the tracks ``ids`` (now at ``pixels``, in the last frame with a pose) should
        be in the frame at ``stamp_ns``, by the motion model; None when it knows nothing.

        The front end starts its search there, so a fast turn or a skipped frame does not
        carry the features beyond KLT's reach (its pyramid follows ~80 px; a 2 deg/frame
        turn at 10 fps moves them ~60 px, twice that when a frame is skipped). Tracks with
        a map point are projected from it; the others as if at the map's median depth."""
        last = self.motion.last
        if self.motion.stamp != self._tracks_stamp:
            return None  # the last pose is older than the tracks' frame (no pose there)
        prediction = self.predict(stamp_ns)
        if prediction is None or self.motion.velocity is None or len(ids) == 0:
            return None
        T_next_last = prediction.inverse() @ last
        rays = np.column_stack([undistort(pixels, self.calibration), np.ones(len(ids))])
        has = self.map.mapped(ids)
        in_last = np.zeros((len(ids), 3))
        if has.any():
            world = np.array([self.map.points[int(t)] for t in ids[has]])
            in_last[has] = last.inverse().apply(world)
        depths = in_last[has, 2][in_last[has, 2] > 0]
        # without map points (initialising) the target's distance is the best guess there is
        depth = float(np.median(depths)) if len(depths) else float(np.linalg.norm(last.translation))
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
        again) ``init.max_position_std_m`` (none is worse). ``bound`` asks for another.
        A camera that has given target poses, none within ``anchor.max_position_std_m`` and
        ``anchor.max_reproj_px`` (a small lens, a far target), is held to what it can do
        where that is looser: ``anchor.best_ratio`` times the surest pose and the best
        corner fit it has given."""
        o = self.options
        fit_bound, reach = o.anchor.max_reproj_px, 0.0
        if not self._bounds_reached and np.isfinite(self._surest_target_m):
            fit_bound = max(fit_bound, o.anchor.best_ratio * self._best_target_fit_px)
            reach = o.anchor.best_ratio * self._surest_target_m
        if target is None or target.reproj_rms_px > fit_bound:
            return False
        if bound is None:
            beginning = not self.initialised or self._beginning_again
            bound = o.init.max_position_std_m if beginning else o.anchor.max_position_std_m
        return target.covariance is None or position_sigma(target.covariance) <= max(bound, reach)

    def jumped(self, a: Transform, b: Transform) -> bool:
        """``a`` and ``b`` further apart than ``relocalised_jump_*``: a visible correction."""
        return (np.linalg.norm(a.translation - b.translation) > self.options.anchor.jump_m
                or np.degrees(a.rotation_angle_to(b)) > self.options.anchor.jump_deg)

    def _maybe_keyframe(self, frame: TrackedFrame, pose: Transform, sigma: float, trusted: TargetObservation | None,
                        inliers: int, forced: bool) -> Keyframe | None:
        """The keyframe ``frame`` becomes at ``pose`` (its own position standard deviation
        ``sigma``), with the points it triangulates; None when it is not needed."""
        o = self.options
        tracks = frame.tracks
        self._frames_since_keyframe += 1
        last = self.map.last_keyframe
        if last is None:
            forced = True
        if not forced:
            with_points = [self.map.points[int(t)] for t in tracks.ids if int(t) in self.map.points]
            depth = np.median(pose.inverse().apply(np.array(with_points))[:, 2]) if with_points else 1.0
            baseline = np.linalg.norm(pose.translation - last.T_world_camera.translation) / max(depth, 1e-3)
            ratio = o.keyframes.anchored_baseline_ratio if trusted is not None else o.keyframes.baseline_ratio
            needed = (baseline > ratio
                      or inliers < o.keyframes.tracked_ratio * self._kf_points_at_insert
                      or inliers < o.keyframes.min_points)
            # running short of map points (a turn carries them out of view): a keyframe every
            # frame, so each new track is triangulated as soon as its parallax allows
            starving = inliers < o.keyframes.starving_points
            if not needed or (self._frames_since_keyframe < 2 and not starving):
                return None
        anchor = trusted if self._anchors(trusted) else None
        target_world = anchor.corners_world if anchor is not None else None
        target_xn = undistort(anchor.corners_px, self.calibration) if anchor is not None else None
        kf = self.map.add_keyframe(frame.stamp_ns, pose, tracks.ids, frame.xn, target_world, target_xn)
        kf.position_sigma_m, kf.drift_m = sigma, self._drift.grown_m
        kf.anchor_covariance = anchor.position_covariance if anchor is not None else None
        self._frames_since_keyframe = 0
        self.map.triangulate(kf, self.fx, o.triangulation.starving_parallax_deg
                             if inliers < o.triangulation.starving_points else o.triangulation.min_parallax_deg,
                             o.triangulation.max_reproj_px, o.triangulation.min_baseline_sigmas,
                             o.keyframes.max_kept)
        self._kf_points_at_insert = int(self.map.mapped(kf.track_ids).sum())
        live = {int(t) for t in tracks.ids}
        if o.loop.enabled:  # places left behind stay, a few, for a loop to close on
            self.map.thin(o.keyframes.max_kept + o.loop.kept_keyframes, o.keyframes.max_kept, live, keep_fixed=True)
        else:
            self.map.cull(o.keyframes.max_kept, live)
        self._schedule_bundle()
        return kf

    # ------------------------------------------------------------------ bundle adjustment
    def _schedule_bundle(self) -> None:
        if self._pending is not None:
            self._bundle_due = True  # one at a time: the next run starts when this one ends
            return
        self._bundle_due = False
        problem = bundle.build_problem(self.map, self.options.bundle, self.options.keyframes.max_kept, self.floor)
        if problem is not None and problem.held_by_target and self._floor_due and self.options.bundle.floor.enabled:
            self._floor_due = False
            # the target is in view: the floor as the frames it posed show it
            self.floor = floor_from_views(self._target_views, self.options.bundle.floor) or self.floor
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
            anchored = self.map.anchored_scale_var() if solution.held_by_target else 0.0
            self._drift.scale_measured(solution.scale_var, renewed, solution.held_by_target, anchored)
        self.bundle_runs = [*self.bundle_runs[-19:], replace(solution, points=np.zeros((0, 3)))]
        log.debug("tracker.bundle", applied=applied, seconds=round(solution.seconds, 3),
                  rms_before=round(solution.initial_rms_px, 3), rms_after=round(solution.final_rms_px, 3))
