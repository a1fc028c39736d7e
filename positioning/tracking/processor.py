"""``TrackingProcessor``: the whole pipeline as a ``FrameProcessor`` (image in, pose out).

Per frame: KLT tracks follow the features; the target observer (observer.py, the one
``cubeloc pose`` uses: edge-aligned poses, the tag-size check) searches where the current
pose says the target should be (and over the whole image every ``target_search_every``
frames while it is not found, so that it is found again even after drift); the tracker turns
tracks and the target pose into this frame's pose; on keyframes new corners are detected
and ORB descriptors stored; when lost, or held on rays (too few map points in view), the
frame is matched against the keyframes every ``relocalise_every`` frames. Started from a
saved map (``start_from_map``), each keyframe also finds the map's own points again
(``Relocaliser.refind``) and retires those no longer there (``Map.retire``).

States: ``target`` (the target is in view and trusted), ``tracking`` (the map alone, held
on rays, or bridged by the wheels: the estimate's ``PoseSource`` says which),
``relocalised`` (a visible correction); no estimate with status ``initialising``,
``waiting`` or ``verifying`` (started from a saved map) or ``lost``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.camera_model import ahead_mask, outline_pixels, project_normalised
from cubeloc.positioning.detection import DetectorOptions
from cubeloc.positioning.estimator import (
    FeatureState,
    FrameResult,
    FrameView,
    PoseEstimate,
    PoseSource,
    PoseState,
)
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.observer import TargetObserver, image_problem
from cubeloc.positioning.target import Target
from cubeloc.positioning.target_pose import PoseOptions, count_planes
from cubeloc.positioning.tracking.features import KltFrontEnd
from cubeloc.positioning.tracking.map import Map
from cubeloc.positioning.tracking.odometry import OdometryPrior
from cubeloc.positioning.tracking.options import TrackerOptions
from cubeloc.positioning.tracking.relocalise import Relocaliser
from cubeloc.positioning.tracking.tracker import Tracker
from cubeloc.positioning.tracking.types import (
    TargetObservation,
    TrackedFrame,
    TrackerOutput,
    Tracks,
)


@dataclass(frozen=True)
class ProcessorOptions:
    tracker: TrackerOptions = field(default_factory=TrackerOptions)
    pose: PoseOptions = field(default_factory=PoseOptions)
    detector: DetectorOptions = field(default_factory=DetectorOptions)
    target_search_every: int = 10  # full-image target search period while it should be out of view
    relocalise_every: int = 2  # while lost, match against the keyframes on every n-th frame
    # The target observer's refinements (observer.py): corners from the tags' edges, and
    # the pose aligned to every cell edge; both on by default, as in ``cubeloc pose``.
    edge_refinement: bool = True
    edge_alignment: bool = True
    # Started from a saved map (start_from_map): a relocalisation is published only after
    # this many frames tracked on from it in a row (a wrong one is worse than none)
    boot_verify_frames: int = 3

    @classmethod
    def in_frame_loop(cls) -> ProcessorOptions:
        """The defaults with bundle adjustment in the frame loop instead of its worker
        thread: every replay of the same frames gives the same poses (tests, benchmarks)."""
        options = cls()
        bundle = dataclasses.replace(options.tracker.bundle, background=False)
        return dataclasses.replace(options, tracker=dataclasses.replace(options.tracker, bundle=bundle))


class TrackingProcessor:
    def __init__(self, target: Target, calibration: CameraCalibration,
                 options: ProcessorOptions | None = None, odometry: OdometryPrior | None = None) -> None:
        """``odometry``: the robot's wheel odometry, the tracker's motion prior (None: vision alone)."""
        self.target = target
        self.calibration = calibration
        self.options = options or ProcessorOptions()
        # Without the finer full-frame passes: on the family they find the cube a frame or
        # two earlier, and the map's beginning moves with the reference frame (seed 0: the
        # reference two frames earlier, 53 points on the longest baseline where 60 are
        # needed, 98 -> 4 % coverage; docs/notes/2026-12-04-planar.md). They return when the
        # initialisation stops hanging on which frame is its reference.
        self.observer = TargetObserver(target, calibration, self.options.pose, self.options.detector,
                                       self.options.edge_refinement, edge_alignment=self.options.edge_alignment,
                                       fine_search=False)
        tracker_options = self.options.tracker
        planes = count_planes(target, target.ids)
        if planes < tracker_options.init.min_planes:
            # A board has one plane: its poses are trusted when its two solutions are told
            # apart by the data (target_pose._separated_plane), and the map starts on them.
            tracker_options = dataclasses.replace(
                tracker_options, init=dataclasses.replace(tracker_options.init, min_planes=planes))
        self.tracker = Tracker(calibration, tracker_options, odometry)
        self.front_end = KltFrontEnd(self.options.tracker.features, ahead_mask(calibration))
        self.relocaliser = Relocaliser(calibration, self.options.tracker)
        self._target_corners = np.concatenate([t.corners for t in target.tags])
        self._frames_without_target = 0
        self._last_target_pose: Transform | None = None
        self._lost_frames = 0
        self._booting = False  # started from a saved map, nothing published yet
        self._agreeing = 0  # frames tracked in a row since the boot relocalisation
        self._map_source: Callable[[], Map | None] | None = None

    def start_from_map(self, load: Callable[[], Map | None]) -> None:
        """From the next frame, and after every ``reset``, track on the map ``load()``
        gives (a ``map.Map`` read from a file, positioning/tracking/map_file.py): relocalise
        against its keyframes until a place is found, verified over
        ``boot_verify_frames``, or the cube is seen. A map with no keyframe (or None) is
        no map: the tracker initialises on the cube as without one."""
        self._map_source = load
        self.reset()

    def reset(self) -> None:
        self.tracker.reset()
        self.front_end.reset()
        self._frames_without_target = 0
        self._last_target_pose = None
        self._lost_frames = 0
        self._booting, self._agreeing = False, 0
        self.observer.reset()
        world_map = self._map_source() if self._map_source is not None else None
        if world_map is not None and world_map.keyframes:
            self.tracker.start_lost_on(world_map)
            ids = [max(world_map.points, default=-1)] + [int(kf.track_ids.max())
                                                         for kf in world_map.keyframes.values() if len(kf.track_ids)]
            self.front_end.ids_from(max(ids) + 1)
            self._booting = True

    def close(self) -> None:
        self.tracker.close()

    # ------------------------------------------------------------------ target
    def observe_target(self, image: np.ndarray, stamp_ns: int, seq: int
                       ) -> tuple[TargetObservation | None, tuple[int, ...], tuple]:
        """The target, searched where the motion model puts it in this frame (the last
        pose alone left a spinning camera's target outside its predicted regions); over the
        full frame when there is no pose, when lost, or every ``target_search_every``
        frames while it is not found (so that it is found again even after drift)."""
        prior = self.tracker.predict(stamp_ns) if self.tracker.initialised else None
        if prior is None:
            prior = self.tracker.last_pose if self.tracker.initialised else self._last_target_pose
        full = (prior is None or self.tracker.lost
                or self._frames_without_target + 1 >= self.options.target_search_every)
        observed = self.observer.observe(image, prior, seq, full_search=full)
        if observed.seen or observed.search.startswith("full"):
            self._frames_without_target = 0
        else:
            self._frames_without_target += 1
        pose = observed.pose
        if pose is None:
            self._last_target_pose = None
            return None, observed.seen, observed.outlines
        self._last_target_pose = pose.T_world_camera
        systematic = pose.systematic_covariance
        own = pose.covariance if systematic is None or pose.covariance is None else pose.covariance - systematic
        return TargetObservation(pose.T_world_camera, pose.planes, pose.tag_ids, pose.reproj_rms_px,
                                 observed.corners_px, pose.points_world, own, systematic), observed.seen, \
            observed.outlines

    def target_outline(self, pose: Transform | None) -> np.ndarray | None:
        """The target's outline in the image from ``pose`` (pixels), where no fresh corner is
        taken; None without a pose or with the target behind the camera."""
        if pose is None:
            return None
        xn, z = project_normalised(pose.inverse(), self._target_corners)
        if np.any(z <= 0):
            return None
        return outline_pixels(xn, self.calibration)

    # ------------------------------------------------------------------ frames
    def process(self, image: np.ndarray, stamp_ns: int, seq: int) -> FrameResult:
        problem = image_problem(image, self.calibration)
        if problem is not None:
            return FrameResult(None, "bad_image", problem)
        guesses = self.tracker.predict_pixels(stamp_ns, self.front_end.ids, self.front_end.pixels)
        tracks = self.front_end.track(image, guesses)
        observation, seen, outlines = self.observe_target(image, stamp_ns, seq)
        out = self.tracker.step(stamp_ns, tracks, observation)
        self.front_end.drop(out.drop_ids)
        result, frame = out.result, out.frame
        # lost (bridged by wheel odometry or not), held on rays, or beginning the map again
        # on the target: look for the map's keyframes; a match ends each
        bridged = _source(result) is PoseSource.ODOMETRY
        searching = self.tracker.initialised and (self.tracker.holding or self.tracker.lost
                                                  or self.tracker.beginning_again)
        if searching:
            self._lost_frames += 1
            every = 1 if self._booting else self.options.relocalise_every  # at boot nothing else can give a pose
            if (self._lost_frames - 1) % every == 0:  # it costs ~4 KLT steps
                result, frame = self._relocalise(image, stamp_ns, result, frame)
                bridged = _source(result) is PoseSource.ODOMETRY
            want = result.estimate is not None and not bridged
        else:
            want = out.want_features or self.tracker.holding  # held: fresh corners keep the rays coming
            if out.keyframe and self.options.tracker.loop.enabled and _source(result) is PoseSource.MAP:
                result, frame = self._close_loop(image, frame, result)
        if result.estimate is not None and not self.tracker.holding and not bridged:
            self._lost_frames = 0
        if want:
            self._add_features(image, frame, out.keyframe, result)
        if self._booting:
            result = self._verified(result)
        return FrameResult(result.estimate, result.status, result.detail, seen, self._view(outlines, tracks, out))

    def _verified(self, result: FrameResult) -> FrameResult:
        """While booting on a saved map: the cube's pose goes out at once; a place found
        in the map only after it was tracked on for ``boot_verify_frames`` frames in a row
        (held or lost frames start the count again), its first pose as ``relocalised``."""
        estimate = result.estimate
        if estimate is not None and estimate.planes > 0:  # the cube: trusted as always
            self._booting = False
            return result
        if estimate is None or estimate.source in (PoseSource.HELD, PoseSource.ODOMETRY):
            self._agreeing = 0
            return FrameResult(None, "waiting", "waiting for a known place of the map or the cube")
        self._agreeing += 1
        needed = self.options.boot_verify_frames
        if self._agreeing < needed:
            return FrameResult(None, "verifying", f"a place of the map found: {self._agreeing} of {needed} "
                                                  "frames agree")
        self._booting = False
        return FrameResult(dataclasses.replace(estimate, state=PoseState.RELOCALISED), "relocalised",
                           f"a place of the map, verified over {needed} frames")

    def _view(self, outlines: tuple, tracks: Tracks, out: TrackerOutput) -> FrameView:
        """The frame for a viewer: the tags decoded, the features followed into it by state."""
        states = np.full(len(tracks.ids), FeatureState.CANDIDATE, np.uint8)
        states[self.tracker.map.mapped(tracks.ids)] = FeatureState.MAPPED
        states[np.isin(tracks.ids, out.drop_ids)] = FeatureState.OUTLIER
        return FrameView(outlines, tracks.pixels, states)

    def _add_features(self, image: np.ndarray, frame: TrackedFrame, keyframe: bool, result: FrameResult) -> None:
        """Fresh corners for ``frame``; on a ``keyframe`` (made by ``Tracker.step``) its
        descriptors, and on a loaded map its points found again."""
        pose = result.estimate.T_world_camera if result.estimate is not None else self._last_target_pose
        new = self.front_end.detect(image, self.target_outline(pose))
        frame = self.tracker.add_tracks(frame, new)
        if keyframe and self.tracker.map.last_keyframe is not None:
            refind = result.estimate is not None and self.options.tracker.refind.enabled
            if refind and self.tracker.map.fixed:
                # on a loaded map: its points found again, and those not found where they should be retired
                again = self.relocaliser.refind(image, self.tracker.map, result.estimate.T_world_camera,
                                                self.front_end.ids)
                self._follow(frame, again.ids, again.pixels)
                self.tracker.map.retire(again.visible, again.found, result.estimate.T_world_camera.translation,
                                        self.options.tracker)
            places = self.tracker.loop_places(frame) if refind else []
            if places:  # a loop closed: the places kept in view followed again, as a loaded map's
                again = self.relocaliser.refind(image, self.tracker.map, result.estimate.T_world_camera,
                                                self.front_end.ids, places)
                self._follow(frame, again.ids, again.pixels)
                self.tracker.map.place_points.update(int(t) for t in again.ids)
            tracks = self.front_end.tracks
            self.relocaliser.describe(image, self.tracker.map.last_keyframe, self.tracker.map, tracks.ids,
                                      tracks.pixels)

    def _follow(self, frame: TrackedFrame, ids: np.ndarray, pixels: np.ndarray) -> TrackedFrame:
        """Map points found again at ``pixels`` followed from here as tracks under their ids."""
        self.front_end.adopt(ids, pixels)
        return self.tracker.add_tracks(frame, Tracks(ids, pixels))

    def _relocalise(self, image: np.ndarray, stamp_ns: int, lost: FrameResult, frame: TrackedFrame
                    ) -> tuple[FrameResult, TrackedFrame]:
        found = self.relocaliser.relocalise(image, self.tracker.map, thorough=self._booting)
        if found is None:
            return lost, frame
        self.front_end.adopt(found.point_ids, found.pixels)
        covariance, frame = self.tracker.relocalised(stamp_ns, found.T_world_camera,
                                                     Tracks(found.point_ids, found.pixels), found.covariance)
        estimate = PoseEstimate(found.T_world_camera, PoseState.RELOCALISED, 0, (), 0.0, covariance,
                                PoseSource.RELOCALISED)
        return FrameResult(estimate, "relocalised", f"{len(found.point_ids)} map points found again"), frame

    def _close_loop(self, image: np.ndarray, frame: TrackedFrame, tracked: FrameResult
                    ) -> tuple[FrameResult, TrackedFrame]:
        """A keyframe tracked on the map, near keyframes made long ago: matched against
        their points (not those tracked now), the match one piece of evidence for
        ``Tracker.close_loop``; when the loop closes (or the evidence agrees with the map)
        the points found again are followed as tracks (bundle adjustment then ties the old
        and the new keyframes), and a closed loop gives this frame's pose."""
        candidates = self.tracker.loop_keyframes(frame)
        if not candidates:
            return tracked, frame
        found = self.relocaliser.relocalise(image, self.tracker.map, among=candidates,
                                            excluding={int(t) for t in self.front_end.ids})
        if found is None:
            return tracked, frame
        reference = max(candidates, key=lambda kf: np.isin(found.point_ids, kf.descriptor_ids).sum())
        outcome, frame = self.tracker.close_loop(frame, found.T_world_camera, found.covariance, reference)
        if outcome in ("refused", "pending"):
            return tracked, frame
        frame = self._follow(frame, found.point_ids, found.pixels)
        if outcome == "agrees":
            return tracked, frame
        before, after = tracked.estimate, frame.pose
        jumped = self.tracker.jumped(before.T_world_camera, after)
        estimate = dataclasses.replace(before, T_world_camera=after,
                                       state=PoseState.RELOCALISED if jumped else before.state,
                                       source=PoseSource.RELOCALISED)
        return FrameResult(estimate, "relocalised" if jumped else tracked.status,
                           f"loop closed: {len(found.point_ids)} points of keyframe {reference.kf_id} found again"), frame


def _source(result: FrameResult) -> PoseSource | None:
    return None if result.estimate is None else result.estimate.source
