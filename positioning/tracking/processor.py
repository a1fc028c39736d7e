"""``TrackingProcessor``: the whole pipeline as a ``FrameProcessor`` (image in, pose out).

Per frame: KLT tracks follow the features; the target is searched where the current pose
says it should be (and over the whole image every ``target_search_every`` frames while it
should be out of view, so that it is found again even after drift); the tracker turns
tracks and the target pose into this frame's pose; on keyframes new corners are detected
and ORB descriptors stored; when lost, or held on rays (too few map points in view), the
frame is matched against the keyframes every ``relocalise_every`` frames.

States: ``target`` (the target is in view and trusted), ``tracking`` (the map alone, or
held: detail ``held: orientation from rays``), ``relocalised`` (a visible correction),
no estimate with status ``initialising`` or ``lost``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from calib.camera_info import CameraCalibration
from positioning.detection import (
    FAMILY_CELLS,
    DetectorOptions,
    TagDetection,
    TagDetector,
    refine_corners,
)
from positioning.estimator import FrameResult, PoseEstimate, PoseState
from positioning.geometry import Transform
from positioning.target import Target
from positioning.target_pose import PoseOptions, estimate_target_pose, unique_target_detections
from positioning.tracking.features import KltFrontEnd
from positioning.tracking.options import TrackerOptions
from positioning.tracking.relocalise import Relocaliser
from positioning.tracking.tracker import Tracker
from positioning.tracking.twoview import project_normalised
from positioning.tracking.types import TargetObservation, TrackerOutput, Tracks


def target_roi(target_corners: np.ndarray, calibration: CameraCalibration, T_world_camera: Transform,
               growth: float, margin_px: int) -> tuple[int, int, int, int] | None:
    """Pixel box (x0, y0, x1, y1) where the target should appear from ``T_world_camera``,
    enlarged for motion and drift; None when it is not wholly in front of the camera or
    not in the image at all."""
    in_camera = T_world_camera.inverse().apply(target_corners)
    if np.any(in_camera[:, 2] <= 0.05):
        return None
    # Far outside the field of view the distortion polynomial folds points back into the
    # image (measured: a cube 60+ degrees off-axis gave a whole-image box, 18 ms of search
    # per frame for nothing). Keep to a field of view half as wide again as the image's.
    k = calibration.camera_matrix
    xn = in_camera[:, :2] / in_camera[:, 2:]
    low_n = -k[:2, 2] / np.diag(k)[:2]
    high_n = (np.array([calibration.width, calibration.height]) - 1 - k[:2, 2]) / np.diag(k)[:2]
    spread = 0.25 * (high_n - low_n)
    if np.any(xn < low_n - spread) or np.any(xn > high_n + spread):
        return None
    pixels, _ = cv2.projectPoints(in_camera, np.zeros(3), np.zeros(3), calibration.camera_matrix,
                                  calibration.distortion)
    pixels = pixels.reshape(-1, 2)
    low, high = pixels.min(axis=0), pixels.max(axis=0)
    pad = (high - low).max() * growth + margin_px
    x0, y0 = (max(int(v), 0) for v in np.floor(low - pad))
    x1 = min(int(np.ceil(high[0] + pad)) + 1, calibration.width)
    y1 = min(int(np.ceil(high[1] + pad)) + 1, calibration.height)
    return (x0, y0, x1, y1) if x1 - x0 >= 16 and y1 - y0 >= 16 else None


@dataclass(frozen=True)
class ProcessorOptions:
    tracker: TrackerOptions = field(default_factory=TrackerOptions)
    pose: PoseOptions = field(default_factory=PoseOptions)
    detector: DetectorOptions = field(default_factory=DetectorOptions)
    target_search_every: int = 10  # full-image target search period while it should be out of view
    relocalise_every: int = 2  # while lost, match against the keyframes on every n-th frame
    roi_growth: float = 0.5  # the predicted target box grows by this fraction of its size per side
    roi_margin_px: int = 24
    # Corners from lines fitted to the tags' edges (detection.refine_corners): on the
    # synthetic camera a quarter of the library's corner error; a tag whose edges do not
    # fit its quad is left out of the pose.
    edge_refinement: bool = True


class TrackingProcessor:
    def __init__(self, target: Target, calibration: CameraCalibration,
                 options: ProcessorOptions | None = None) -> None:
        self.target = target
        self.calibration = calibration
        self.options = options or ProcessorOptions()
        self._detector = TagDetector(target.family, self.options.detector)
        self.tracker = Tracker(calibration, self.options.tracker)
        self.front_end = KltFrontEnd(self.options.tracker.features)
        self.relocaliser = Relocaliser(calibration, self.options.tracker)
        self._target_corners = np.concatenate([t.corners for t in target.tags])
        self._frames_without_target = 0
        self._last_target_pose: Transform | None = None
        self._lost_frames = 0

    def reset(self) -> None:
        self.tracker.reset()
        self.front_end.reset()
        self._frames_without_target = 0
        self._last_target_pose = None
        self._lost_frames = 0

    def close(self) -> None:
        self.tracker.close()

    # ------------------------------------------------------------------ target
    def _search_target(self, image: np.ndarray) -> list[TagDetection]:
        pose = self.tracker.last_pose if self.tracker.initialised else self._last_target_pose
        roi = None if pose is None else target_roi(self._target_corners, self.calibration, pose,
                                                   self.options.roi_growth, self.options.roi_margin_px)
        if roi is not None:
            found = unique_target_detections(self._detector.detect(image, roi), self.target)
            if found:
                return found
        self._frames_without_target += 1
        if pose is None or self.tracker.lost or self._frames_without_target >= self.options.target_search_every:
            self._frames_without_target = 0
            return unique_target_detections(self._detector.detect(image), self.target)
        return []

    def _refine(self, image: np.ndarray, detections: list[TagDetection]) -> list[TagDetection]:
        if not self.options.edge_refinement:
            return detections
        k, d = self.calibration.camera_matrix, self.calibration.distortion
        cells = FAMILY_CELLS.get(self.target.family, 8)
        refined = (refine_corners(image, detection, k, d, cells) for detection in detections)
        return [r for r in refined if r is not None]

    def _observe_target(self, image: np.ndarray) -> tuple[TargetObservation | None, tuple[int, ...]]:
        found = self._search_target(image)
        seen = tuple(d.tag_id for d in found)
        detections = self._refine(image, found)
        if not detections:
            self._last_target_pose = None
            return None, seen
        self._frames_without_target = 0
        outcome = estimate_target_pose(detections, self.target, self.calibration, self.options.pose,
                                       self.tracker.last_pose)
        if outcome.pose is None:
            self._last_target_pose = None
            return None, seen
        pose = outcome.pose
        self._last_target_pose = pose.T_world_camera
        by_id = {d.tag_id: d for d in detections}
        corners_px = np.concatenate([by_id[i].corners for i in pose.tag_ids]).astype(np.float64)
        return TargetObservation(pose.T_world_camera, pose.planes, pose.tag_ids, pose.reproj_rms_px,
                                 corners_px, self.target.corners_of(pose.tag_ids), pose.covariance), seen

    def _target_outline(self, pose: Transform | None) -> np.ndarray | None:
        if pose is None:
            return None
        xn, z = project_normalised(pose.inverse(), self._target_corners)
        if np.any(z <= 0):
            return None
        k = self.calibration.camera_matrix
        return xn @ k[:2, :2].T + k[:2, 2]  # the outline needs no distortion: it has a margin

    # ------------------------------------------------------------------ frames
    def process(self, image: np.ndarray, stamp_ns: int, seq: int) -> FrameResult:
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 2:
            return FrameResult(None, "bad_image", f"expected an (H, W) uint8 image, got {getattr(image, 'shape', None)}")
        if image.shape != (self.calibration.height, self.calibration.width):
            return FrameResult(None, "bad_image", f"image is {image.shape[1]}x{image.shape[0]}, the calibration is "
                                                  f"for {self.calibration.width}x{self.calibration.height}")
        guesses = self.tracker.predict_pixels(stamp_ns, self.front_end.ids, self.front_end.pixels)
        tracks = self.front_end.track(image, guesses)
        observation, seen = self._observe_target(image)
        out = self.tracker.step(stamp_ns, tracks, observation)
        self.front_end.drop(out.drop_ids)
        result = out.result
        # lost, or held on rays: look for the map's keyframes; a match ends either
        searching = self.tracker.initialised and (self.tracker.holding or (
            result.estimate is None and self.tracker.lost))
        if searching:
            self._lost_frames += 1
            if (self._lost_frames - 1) % self.options.relocalise_every == 0:  # it costs ~4 KLT steps
                result = self._relocalise(image, stamp_ns, result)
            want = result.estimate is not None
        else:
            want = out.want_features or self.tracker.holding  # held: fresh corners keep the rays coming
        if result.estimate is not None and not self.tracker.holding:
            self._lost_frames = 0
        if want:
            self._add_features(image, out, result)
        return FrameResult(result.estimate, result.status, result.detail, seen)

    def _add_features(self, image: np.ndarray, out: TrackerOutput, result: FrameResult) -> None:
        pose = result.estimate.T_world_camera if result.estimate is not None else self._last_target_pose
        new = self.front_end.detect(image, self._target_outline(pose))
        self.tracker.add_tracks(new)
        if out.keyframe and self.tracker.map.last_keyframe is not None:
            tracks = self.front_end.tracks
            self.relocaliser.describe(image, self.tracker.map.last_keyframe, self.tracker.map, tracks.ids,
                                      tracks.pixels)

    def _relocalise(self, image: np.ndarray, stamp_ns: int, lost: FrameResult) -> FrameResult:
        found = self.relocaliser.relocalise(image, self.tracker.map)
        if found is None:
            return lost
        self.front_end.adopt(found.point_ids, found.pixels)
        covariance = self.tracker.relocalised(stamp_ns, found.T_world_camera, Tracks(found.point_ids, found.pixels),
                                              found.covariance)
        estimate = PoseEstimate(found.T_world_camera, PoseState.RELOCALISED, 0, (), 0.0, covariance)
        return FrameResult(estimate, "relocalised", f"{len(found.point_ids)} map points found again")
