"""Where the tracker's map begins (a mixin of ``tracker.Tracker``, whose state it shares).

- On the target, by the paper's Algorithms 1 and 2 (``initialiser``): a reference frame A,
  then a frame B whose median parallax against it is enough.
- On the longest baseline the target gave, when the target leaves before that parallax
  (out of the view, the hold on rays ended, or the reference's tracks run out:
  ``Initialiser.on_departure``).
- Again when the tracker is lost and the target's pose is sure enough to begin a map
  (``init.max_position_std_m``) but not to anchor keyframes (``anchor.max_position_std_m``):
  the same two algorithms, and the map they begin joins the old one. An anchoring pose
  completes the pair too; a relocalisation into the old map, a pose from it or a
  keyframe anchored on the target ends it (docs/tracker.md).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import structlog

from cubeloc.positioning.camera_model import undistort
from cubeloc.positioning.estimator import FrameResult, PoseEstimate, PoseSource, PoseState
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking.initialiser import InitFrame, InitResult, InitStatus, out_of_view
from cubeloc.positioning.tracking.map import Keyframe
from cubeloc.positioning.tracking.types import TargetObservation, TrackedFrame, TrackerOutput

log = structlog.get_logger()


class MapBeginning:
    """The ``Tracker`` methods that begin its map; they read and write its state (``reset``)."""

    @property
    def beginning_again(self) -> bool:
        """Lost, and Algorithms 1 and 2 run again on the target (``_begins_again``) until
        the map gives a pose again or the target anchors a keyframe."""
        return self._beginning_again

    def _initialising(self, frame: TrackedFrame, trusted: TargetObservation | None) -> TrackerOutput:
        """A frame while no map exists, or while it begins again: Algorithm 1 or 2 on a
        trusted target pose; without one, the hold on rays, or the map begun on the
        target's longest baseline when the target has left."""
        empty = np.zeros(0, np.int64)
        stamp_ns, tracks, xn = frame.stamp_ns, frame.tracks, frame.xn
        if trusted is None:
            status = InitStatus.NO_TARGET_POSE
            prediction = self.predict(stamp_ns)
            held = None if prediction is None else self._hold.hold(stamp_ns, self.motion, prediction, tracks, xn,
                                                                    self.map)
            departed = self._departed(frame, held)
            if departed is not None:
                return departed
            if held is None:
                self._hold.end()
                return TrackerOutput(FrameResult(None, "initialising", "waiting for the target"), False, empty, status,
                                     frame=frame)
            # the target hidden (a passer-by) before the map exists: held on the rays of
            # tracks born on target poses, the map still waits for the target
            pose, covariance = held[0], self._drift.covariance(self.motion.last, held[0], held[1])  # the path since
            self._hold.rebase(None, tracks.ids, xn)
            self.motion.update(pose, stamp_ns, own=held[1], held=True)
            estimate = PoseEstimate(pose, PoseState.TRACKING, 0, (), 0.0, covariance, PoseSource.HELD)
            return TrackerOutput(FrameResult(estimate, "ok", "held: orientation from rays (initialising)"), False,
                                 empty, status, frame=replace(frame, pose=pose))
        self._hold.end()
        state = PoseState.TARGET
        if self.initialised:  # beginning again: the map gave no pose in this frame
            state = PoseState.RELOCALISED if self.lost else state
            self.lost, self._target_seen, self.motion.covariance = False, True, trusted.published_covariance
            self._drift.reset()
        estimate = PoseEstimate(trusted.T_world_camera, state, trusted.planes, trusted.tag_ids,
                                trusted.reproj_rms_px, trusted.published_covariance, PoseSource.TARGET)
        status = "relocalised" if state is PoseState.RELOCALISED else "ok"
        self._hold.rebase(trusted.T_world_camera, tracks.ids, xn, trusted.published_covariance)
        # beginning again, the pose is too unsure to anchor a keyframe: not taken for motion either
        self.motion.update(trusted.T_world_camera, stamp_ns, noisy=self.initialised,
                           own=trusted.published_covariance)
        if not self._anchors(trusted):
            # published, but too uncertain to fix the map's scale and frame
            return TrackerOutput(FrameResult(estimate, status, "initialising: target pose too uncertain to anchor"),
                                 False, empty, InitStatus.UNCERTAIN_TARGET_POSE, frame=frame)
        init = InitFrame(stamp_ns, trusted.T_world_camera, trusted.planes, tracks.ids, xn, trusted.position_covariance)
        if self.initialiser.reference is None:
            # Algorithm 1 runs on this frame once the front end has added fresh corners
            return TrackerOutput(FrameResult(estimate, status, "initialising: reference frame"), True, empty,
                                 InitStatus.REFERENCE_SET, frame=frame)
        result = self.initialiser.step(init)
        best = self._best_target
        if self.initialiser.best is init or self.initialiser.best is None:
            self._best_target = trusted if self.initialiser.best is init else None
        if result.status is InitStatus.TOO_FEW_MATCHES:
            return TrackerOutput(FrameResult(estimate, status, result.detail), True, empty, result.status, frame=frame)
        if result.status is not InitStatus.INITIALISED:
            return TrackerOutput(FrameResult(estimate, status, result.detail), False, empty, result.status,
                                 frame=frame)
        if result.frame is not init:  # the reference's tracks ran out: the longest baseline weighed
            return self._begin_on_earlier_frame(result, best, frame)
        keyframe = self._start_map(result, trusted)
        return TrackerOutput(FrameResult(estimate, status, result.detail), True, empty, result.status,
                             frame=replace(frame, pose=trusted.T_world_camera, keyframe=keyframe))

    def _departed(self, frame: TrackedFrame, held: tuple[Transform, np.ndarray] | None) -> TrackerOutput | None:
        """The target has left the view (or nothing holds the pose without it) before
        Algorithm 2's median parallax: the map begins on the target's longest baseline, and
        this frame is tracked on it; None when there is no such baseline or it does not begin."""
        best = self._best_target
        if best is None or (held is not None and not out_of_view(held[0], best.corners_world, self.calibration)):
            return None
        result = self.initialiser.on_departure()
        self._best_target = None
        if result.status is not InitStatus.INITIALISED:
            return None
        return self._begin_on_earlier_frame(result, best, frame)

    def _begin_on_earlier_frame(self, result: InitResult, target_b: TargetObservation, frame: TrackedFrame
                                ) -> TrackerOutput:
        """The map begins on an earlier frame B (``Initialiser.on_departure``), and this
        frame is tracked on it."""
        self._start_map(result, target_b)
        self._hold.end()
        return replace(self.step(frame.stamp_ns, frame.tracks, frame.target), init_status=result.status)

    def _start_map(self, result: InitResult, target_b: TargetObservation) -> Keyframe:
        """The map of an initialisation: keyframes A and B, anchored on the target, and the
        points; returns B."""
        log.debug("tracker.initialised", detail=result.detail)
        a, ta, b = result.reference, self._reference_target, result.frame
        kf_a = self.map.add_keyframe(a.stamp_ns, a.T_world_camera, a.track_ids, a.xn,
                                     ta.corners_world, undistort(ta.corners_px, self.calibration))
        kf_b = self.map.add_keyframe(b.stamp_ns, b.T_world_camera, b.track_ids, b.xn,
                                     target_b.corners_world, undistort(target_b.corners_px, self.calibration))
        kf_a.anchor_covariance, kf_b.anchor_covariance = ta.position_covariance, target_b.position_covariance
        self._drift.begun_on(kf_a.anchor_covariance, kf_b.anchor_covariance)
        for track_id, point in zip(result.track_ids, result.points_world, strict=True):
            self.map.add_point(int(track_id), point, kf_a.kf_id)
        self.initialised, self.lost = True, False
        self._beginning_again = False
        self.initialiser.reset()
        self._kf_points_at_insert, self._frames_since_keyframe = len(result.track_ids), 0
        self._schedule_bundle()
        return kf_b

    def _beginning_again_on(self, frame: TrackedFrame, trusted: TargetObservation | None, tracked: bool
                            ) -> TrackerOutput | None:
        """A frame of a map that exists: this frame's output when the map begins again on
        ``trusted`` (or goes on beginning), None when the frame takes the usual way
        (``tracked``: the map gave a pose, which ends a beginning, as an anchoring pose does)."""
        if not tracked and trusted is not None and self._begins_again(trusted):
            return self._initialising(frame, trusted)
        anchoring = self._anchors(trusted, self.options.anchor.max_position_std_m)
        if not tracked and anchoring and self._beginning_again:
            # a pose that anchors keyframes is also Algorithm 2's frame B for the reference held
            begun = self._completes_beginning(frame, trusted)
            if begun is not None:
                return begun
        if tracked or anchoring:
            self._end_beginning_again()
        return None

    def _begins_again(self, target: TargetObservation) -> bool:
        """The tracker is lost and ``target`` is too unsure to anchor a keyframe, but sure
        enough to begin a map: Algorithms 1 and 2 run on it again (their baseline makes its
        error small against the depths, as at the start), and the map they begin joins this
        one; they go on while the map gives no pose. This is what a lost map can begin from
        (the cube small at the image's edge: 5-11 mm poses, each refused as an anchor)."""
        if self._anchors(target, self.options.anchor.max_position_std_m):
            return False  # anchors keyframes: the map goes on from it
        if not self._anchors(target, self.options.init.max_position_std_m):
            return False
        if not self._beginning_again:
            if not self.lost:
                return False  # the map was tracked until the last frame
            self._beginning_again = True
            self.initialiser.reset()
            self._best_target = None
        return True

    def _completes_beginning(self, frame: TrackedFrame, trusted: TargetObservation) -> TrackerOutput | None:
        """Algorithm 2 on an anchoring target pose while the map begins again: when it
        pairs with the reference, the map begins and this frame is tracked on it; else None
        (the anchored keyframes take it from here)."""
        earlier, stamp_ns = self._best_target, frame.stamp_ns
        result = self.initialiser.step(InitFrame(stamp_ns, trusted.T_world_camera, trusted.planes, frame.tracks.ids,
                                                 frame.xn, trusted.position_covariance))
        if result.status is not InitStatus.INITIALISED:
            return None
        self._start_map(result, trusted if result.frame.stamp_ns == stamp_ns else earlier)
        self._hold.end()
        return replace(self.step(stamp_ns, frame.tracks, trusted), init_status=result.status)

    def _end_beginning_again(self) -> None:
        """The map gives a pose again (or the target anchors one): Algorithm 2 stops."""
        if self._beginning_again:
            self._beginning_again = False
            self.initialiser.reset()
            self._best_target = None
