"""The single-frame target pose as a ``FrameProcessor``: image in, pose (or reason) out.

Keeps one detector for its whole life and the last pose, from which it predicts where the
target will be in the next frame: detection runs in that region first (the steady state
is fast) and on the full frame when the region does not give as many faces as before.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
import structlog

from calib.camera_info import CameraCalibration
from positioning.detection import (
    FAMILY_CELLS,
    DetectorOptions,
    TagDetection,
    TagDetector,
    refine_corners,
)
from positioning.edge_alignment import refine_pose_on_edges
from positioning.estimator import FrameResult, PoseEstimate, PoseState
from positioning.geometry import Transform
from positioning.target import Target
from positioning.target_pose import (
    PoseOptions,
    Refusal,
    check_tag_scale,
    estimate_target_pose,
    pose_covariance,
    single_plane_candidates,
    unique_target_detections,
)

log = structlog.get_logger()

# A predicted tag region grows by this fraction of the tag's size on each side, plus a
# fixed margin: the camera moves between frames and the prediction is last frame's pose.
REGION_GROWTH = 0.35
REGION_MARGIN_PX = 16
# Tags seen more obliquely than this are not predicted (they rarely decode anyway).
MAX_PREDICTED_ANGLE_DEG = 80.0


# A predicted tag this large (pixels) is searched with more decimation: its quad is still
# 30 px or more in the decimated image, and a third cheaper to find.
LARGE_TAG_PX = 90.0
LARGE_TAG_DECIMATE = 3.0

# Recovery searches this many tag sizes around a lone tag for its neighbours.
NEIGHBOURHOOD_TAG_SIZES = 1.2
# A tag needs a white quiet zone one cell wide; the masked search keeps this much of it.
QUIET_ZONE_KEPT_CELLS = 0.8


@dataclass(frozen=True)
class TagRegion:
    tag_id: int
    roi: tuple[int, int, int, int]  # x0, y0, x1, y1 pixels
    quiet_zone: np.ndarray  # (4, 2) pixels: the tag and most of its white margin, predicted
    size_px: float = 0.0  # the tag's predicted size (longest side of its pixel box)


def predicted_tag_regions(target: Target, calibration: CameraCalibration, T_world_camera: Transform,
                          growth: float = REGION_GROWTH, margin_px: int = REGION_MARGIN_PX) -> list[TagRegion]:
    """Where each tag facing the camera at ``T_world_camera`` should appear, one pixel box
    per tag, enlarged for motion; tags behind the camera or out of the image are left out."""
    T_camera_world = T_world_camera.inverse()
    cos_limit = np.cos(np.radians(MAX_PREDICTED_ANGLE_DEG))
    regions = []
    for tag in target.tags:
        to_camera = T_world_camera.translation - tag.center
        if float(tag.normal @ to_camera) <= cos_limit * float(np.linalg.norm(to_camera)):
            continue  # seen edge-on or from behind
        in_camera = T_camera_world.apply(tag.corners)
        if np.any(in_camera[:, 2] <= 0.05):
            continue
        grow = 1.0 + 2.0 * QUIET_ZONE_KEPT_CELLS / FAMILY_CELLS[target.family]
        centre = in_camera.mean(axis=0)
        outline = np.concatenate([in_camera, centre + grow * (in_camera - centre)])
        pixels, _ = cv2.projectPoints(outline, np.zeros(3), np.zeros(3), calibration.camera_matrix,
                                      calibration.distortion)
        pixels, quiet_zone = pixels.reshape(-1, 2)[:4], pixels.reshape(-1, 2)[4:]
        low, high = pixels.min(axis=0), pixels.max(axis=0)
        pad = (high - low).max() * growth + margin_px
        x0, y0 = np.floor(low - pad).astype(int)
        x1, y1 = np.ceil(high + pad).astype(int) + 1
        x0, y0 = max(int(x0), 0), max(int(y0), 0)
        x1, y1 = min(int(x1), calibration.width), min(int(y1), calibration.height)
        if x1 - x0 >= 16 and y1 - y0 >= 16:
            regions.append(TagRegion(tag.tag_id, (x0, y0, x1, y1), quiet_zone, float((high - low).max())))
    return regions


class TargetPoseProcessor:
    """The camera pose from the target alone, frame by frame (``state = target``).

    Search order: the tag regions predicted from the last pose (decimated, fast; a tag
    missed there is searched again in a masked region: everything outside its predicted
    quiet zone painted white); the full frame (decimate 3) when they give fewer tags than
    last time; after a full-frame pose, the masked regions of tags the pose says are in
    view but were not found (next to a bright background a shaded face can lose its quad
    to the decimated threshold). When the full frame gives one face only, faces whose
    residuals disagree, or a second face too oblique to trust, the neighbourhood of each
    tag is searched for the others without decimation. ``last_search`` says which ran:
    "predicted", "full", and "+completion" or "+recovery" when those searches added tags.
    """

    def __init__(self, target: Target, calibration: CameraCalibration, options: PoseOptions | None = None,
                 detector_options: DetectorOptions | None = None, edge_refinement: bool = True,
                 full_frame_decimate: float = 3.0, edge_alignment: bool = True) -> None:
        self.target = target
        self.calibration = calibration
        self.options = options or PoseOptions()
        self._detector = TagDetector(target.family, detector_options)
        self.edge_refinement = edge_refinement
        self.edge_alignment = edge_alignment  # align the pose to every cell edge (edge_alignment.py)
        self.full_frame_decimate = full_frame_decimate
        self._last_pose: Transform | None = None
        self._last_tag_count = 0
        self._scale_checked = False
        self.last_search = ""
        self._suspects: set[int] = set()  # this frame's tags whose quads failed refinement
        self._masked_ids: set[int] = set()  # tags found only by the masked search
        self._scale_message = ""  # the tag-size warning, repeated on every refused frame

    def reset(self) -> None:
        self._scale_message = ""
        self._masked_ids = set()
        self._last_pose = None
        self._last_tag_count = 0
        self._scale_checked = False
        self.last_search = ""

    def _ours(self, detections: list[TagDetection]) -> list[TagDetection]:
        return unique_target_detections(detections, self.target)

    def _detect_in(self, image: np.ndarray, regions: list[TagRegion], decimate: float | None) -> list[TagDetection]:
        found: list[TagDetection] = []
        for region in regions:
            region_decimate = decimate
            if decimate is None and region.size_px >= LARGE_TAG_PX:
                region_decimate = LARGE_TAG_DECIMATE
            found.extend(self._detector.detect(image, region.roi, region_decimate))
        return self._ours(found)

    def _detect_masked(self, image: np.ndarray, regions: list[TagRegion]) -> list[TagDetection]:
        """Search each region with everything outside the tag's predicted quiet zone
        painted white, so the background cannot break its quad."""
        found: list[TagDetection] = []
        for region in regions:
            x0, y0, x1, y1 = region.roi
            crop = image[y0:y1, x0:x1].copy()
            inside = np.zeros(crop.shape, np.uint8)
            cv2.fillConvexPoly(inside, np.round(region.quiet_zone - (x0, y0)).astype(np.int32), 1)
            if not inside.any():
                continue
            white = np.percentile(crop[inside == 1], 90)
            crop[inside == 0] = np.uint8(white)
            # Decimated first (4x cheaper); without decimation only if that finds nothing.
            detections = [d for d in self._detector.detect(crop) if d.tag_id == region.tag_id]
            if not detections:
                detections = self._detector.detect(crop, None, 1.0)
            for detection in detections:
                found.append(TagDetection(detection.tag_id, detection.corners + (x0, y0),
                                          detection.decision_margin, detection.hamming))
        return self._ours(found)

    def _search(self, image: np.ndarray) -> list[TagDetection]:
        if self._last_pose is not None:
            regions = predicted_tag_regions(self.target, self.calibration, self._last_pose)
            if regions:
                # Tags that needed the masked search last frame go straight to it.
                masked = [r for r in regions if r.tag_id in self._masked_ids]
                found = self._detect_in(image, [r for r in regions if r.tag_id not in self._masked_ids], None)
                found += self._detect_masked(image, masked)
                if found and len(found) < self._last_tag_count:
                    have = {d.tag_id for d in found}
                    found += self._detect_masked(image, [r for r in regions if r.tag_id not in have])
                if found and len(found) >= self._last_tag_count:
                    self.last_search = "predicted"
                    return found
        self.last_search = "full"
        # Coarse first (decimate 3: a third of the cost of the paper's 2); the tags it
        # misses next to found ones are recovered by the completion search, and only an
        # empty result pays for the finer pass.
        found = self._ours(self._detector.detect(image, None, self.full_frame_decimate))
        if not found and self.full_frame_decimate > self._detector.options.quad_decimate:
            found = self._ours(self._detector.detect(image))
        return found

    def _complete(self, image: np.ndarray, detections: list[TagDetection], pose: Transform) -> list[TagDetection]:
        """Tags the pose says are in view but the full-frame search missed, if found."""
        have = {d.tag_id for d in detections}
        missing = [r for r in predicted_tag_regions(self.target, self.calibration, pose) if r.tag_id not in have]
        if not missing:
            return []
        extra = [d for d in self._detect_masked(image, missing) if d.tag_id not in have]
        self._masked_ids |= {d.tag_id for d in extra}
        if extra:
            self.last_search = f"{self.last_search}+completion"
        return self._refine(image, extra)

    def _recover(self, image: np.ndarray, detections: list[TagDetection]):
        """One face found, or faces that disagree (a bad quad with a valid id). From each
        tag alone: first the neighbourhood of the tag without decimation (the other faces
        of a cube are within one tag size of it), then the regions its two possible poses
        predict (masked); tags found there settle the pose, if any is right."""
        for seed in sorted(detections, key=lambda d: -d.decision_margin):
            low, high = seed.corners.min(axis=0), seed.corners.max(axis=0)
            reach = float((high - low).max()) * NEIGHBOURHOOD_TAG_SIZES
            x0, y0 = np.floor(low - reach).astype(int)
            x1, y1 = np.ceil(high + reach).astype(int)
            near = [d for d in self._ours(self._detector.detect(image, (x0, y0, x1, y1), 1.0))
                    if d.tag_id != seed.tag_id]
            attempts = [self._refine(image, near)] if near else []
            attempts += [self._complete(image, [seed], candidate)
                         for candidate in single_plane_candidates([seed], self.target, self.calibration)]
            for extra in attempts:
                if not extra:
                    continue
                outcome = estimate_target_pose([seed, *extra], self.target, self.calibration, self.options,
                                               self._last_pose)
                if outcome.pose is not None:
                    self.last_search = "full+recovery"
                    return outcome, [seed, *extra]
        return None

    def _refine(self, image: np.ndarray, detections: list[TagDetection]) -> list[TagDetection]:
        """Corners from lines fitted to the tags' edges (see detection.refine_corners; on
        the synthetic camera a quarter of the library's corner error at 2 m). A detection
        whose edges do not fit its quad (a wrong quad with a right id) is dropped, and
        its id kept in ``self._suspects`` so that it is searched for again."""
        if not self.edge_refinement:
            return detections
        cells = FAMILY_CELLS[self.target.family]
        k, d = self.calibration.camera_matrix, self.calibration.distortion
        refined = []
        for detection in detections:
            better = refine_corners(image, detection, k, d, cells)
            if better is None:
                self._suspects.add(detection.tag_id)
            else:
                refined.append(better)
        return refined

    def process(self, image: np.ndarray, stamp_ns: int, seq: int) -> FrameResult:
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 2:
            shape = getattr(image, "shape", None)
            dtype = getattr(image, "dtype", type(image).__name__)
            return FrameResult(None, "bad_image", f"expected an (H, W) uint8 image, got {dtype} {shape}")
        if image.shape != (self.calibration.height, self.calibration.width):
            return FrameResult(
                None, "bad_image",
                f"image is {image.shape[1]}x{image.shape[0]}, the calibration is for "
                f"{self.calibration.width}x{self.calibration.height}",
            )
        try:
            return self._process(image, seq)
        except (cv2.error, np.linalg.LinAlgError) as exc:  # a degenerate view, not a bug of the caller's
            self.reset()
            return FrameResult(None, "solver", f"no pose: {type(exc).__name__}: {str(exc).strip()[:200]}")

    def _process(self, image: np.ndarray, seq: int) -> FrameResult:
        self._suspects = set()
        found = self._search(image)
        # In the steady state the edge alignment replaces the corner refinement: the
        # library's corners only need to bring the pose within a third of a cell.
        steady = self.edge_alignment and self.last_search == "predicted"
        detections = found if steady else self._refine(image, found)
        outcome = estimate_target_pose(detections, self.target, self.calibration, self.options, self._last_pose,
                                       with_covariance=not self.edge_alignment)
        if outcome.pose is not None and (self.last_search == "full" or self._suspects):
            # Search again for the tags the pose says are in view but it did not use
            # (not found, or left out as a bad quad); keep what improves the pose.
            used = [d for d in detections if d.tag_id in outcome.pose.tag_ids]
            extra = self._complete(image, used, outcome.pose.T_world_camera)
            if extra:
                completed = estimate_target_pose(used + extra, self.target, self.calibration, self.options,
                                                 self._last_pose)
                if completed.pose is not None and len(completed.pose.tag_ids) > len(outcome.pose.tag_ids):
                    outcome, detections = completed, used + extra
        elif self.last_search == "full" and outcome.refusal in (Refusal.ONE_FACE, Refusal.REPROJECTION,
                                                                 Refusal.OBLIQUE):
            recovered = self._recover(image, detections)
            if recovered is not None:
                outcome, detections = recovered
        seen = tuple(sorted({d.tag_id for d in detections}))
        if outcome.pose is None:
            self._last_pose = None
            self._last_tag_count = 0
            self._masked_ids = set()
            detail = outcome.detail
            if outcome.rejected is not None:
                # Large residuals on several faces: is the tag size in the file wrong?
                if not self._scale_checked:
                    self._scale_message = self._warn_on_scale(detections, outcome.rejected, seq)
                detail = f"{detail}; {self._scale_message}" if self._scale_message else detail
            return FrameResult(None, outcome.refusal.value, detail, seen)
        pose = outcome.pose
        if self.edge_alignment:
            pose = refine_pose_on_edges(image, pose, self.target, self.calibration)
            if pose.covariance is None:  # the alignment failed: the corners' pose stands
                pose = dataclasses.replace(pose, covariance=pose_covariance(pose, self.calibration))
        self._last_pose = pose.T_world_camera
        self._last_tag_count = len(pose.tag_ids)
        if not self._scale_checked and pose.planes >= 3:
            self._warn_on_scale(detections, pose, seq)
        estimate = PoseEstimate(
            T_world_camera=pose.T_world_camera,
            state=PoseState.TARGET,
            planes=pose.planes,
            tag_ids=pose.tag_ids,
            reproj_rms_px=pose.reproj_rms_px,
            covariance=pose.covariance,
        )
        return FrameResult(estimate, "ok", "", seen)

    def _warn_on_scale(self, detections: list[TagDetection], pose, seq: int) -> str:
        """Once per reset: does the target file's tag size match the printed tags?
        Returns the warning ("" when they agree or it cannot tell)."""
        self._scale_checked = True
        check = check_tag_scale(detections, self.target, self.calibration, pose)
        if check is None or check.agrees:
            return ""
        log.warning("target_scale_mismatch", seq=seq, tag_scale=round(check.tag_scale, 4),
                    detail=check.message(), target=self.target.source)
        return check.message()
