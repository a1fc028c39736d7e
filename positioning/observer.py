"""``TargetObserver``: the target in one image, searched, decoded, refined and posed.

One observer serves both modes: ``TargetPoseProcessor`` (``single_frame.py``, the pose
from the target alone) and the tracker's ``TrackingProcessor``, whose anchor observations
are therefore the same edge-aligned poses with the same checks. Per image:

* search: the tag regions predicted from a prior pose (decimated, fast; a tag missed there
  is searched again in a masked region, everything outside its predicted quiet zone
  painted white); the full frame (decimate 3) when they give fewer tags than last time,
  if the caller allows a full search, each small tag it finds decoded again in its own box
  at a finer decimation; after a full-frame pose, the masked regions of tags the pose says
  are in view but were not found; finer full-frame passes when the coarse one found
  nothing, or when the pose still leaves a tag in view unused; when the full frame gives
  one face only, faces whose residuals disagree or a second face too oblique, the
  neighbourhood of each tag without decimation (recovery);
* refine: corners from lines fitted to the tags' edges (``detection.refine_corners``),
  skipped in the steady state where the edge alignment replaces it;
* pose: ``target_pose.estimate_target_pose`` (EPnP + LM, residual and oblique checks), then
  aligned to every cell edge of the tags (``edge_alignment``), with its covariance;
* checks: the tag size against the layout, once per reset on a three-face pose, logged as
  ``target_scale_mismatch`` and repeated in the detail of refused frames.
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
from dataclasses import dataclass

import cv2
import numpy as np
import structlog

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning import jit
from cubeloc.positioning.camera_model import ahead, project_pose
from cubeloc.positioning.corner_pose import TargetPose, pose_covariance
from cubeloc.positioning.detection import (
    DetectorOptions,
    TagDetection,
    TagDetector,
    refine_corners,
)
from cubeloc.positioning.edge_alignment import refine_pose_on_edges
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tag_scale import check_tag_scale
from cubeloc.positioning.tag_search import (
    COMPLETION_GROWTH,
    LARGE_TAG_DECIMATE,
    LARGE_TAG_PX,
    NEIGHBOURHOOD_TAG_SIZES,
    REGION_GROWTH,
    REGION_MARGIN_PX,
    TagRegion,
    decimate_for,
    finest_empty_decimate,
    grey_percentile,
    predicted_tag_regions,
    tags_in_view,
)
from cubeloc.positioning.target import Target
from cubeloc.positioning.target_pose import (
    PoseOptions,
    PoseOutcome,
    Refusal,
    count_planes,
    estimate_target_pose,
    quad_width_px,
    single_plane_candidates,
    unique_target_detections,
)

log = structlog.get_logger()

@dataclass(frozen=True)
class Observation:
    """What the observer made of one image: a pose, or the refusal and why.

    ``corners_px`` are the used tags' corners (M, 2) where the returned pose puts them
    (after the edge alignment, the pose's projection of ``pose.points_world``: the edges'
    information, for the tracker's bundle adjustment); ``seen`` the target's tags decoded,
    ``outlines`` each of them with the library's corners (4, 2), for a viewer.
    """

    pose: TargetPose | None
    refusal: Refusal | None = None
    detail: str = ""
    seen: tuple[int, ...] = ()
    corners_px: np.ndarray | None = None
    search: str = ""  # "predicted", "full", "+completion", "+recovery"; "" when none ran
    outlines: tuple[tuple[int, np.ndarray], ...] = ()


def image_problem(image, calibration: CameraCalibration) -> str | None:
    """Why ``image`` cannot be processed with ``calibration`` (None when it can)."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 2:
        shape = getattr(image, "shape", None)
        dtype = getattr(image, "dtype", type(image).__name__)
        return f"expected an (H, W) uint8 image, got {dtype} {shape}"
    if image.shape != (calibration.height, calibration.width):
        return (f"image is {image.shape[1]}x{image.shape[0]}, the calibration is for "
                f"{calibration.width}x{calibration.height}")
    return None


class TargetObserver:
    """The target in one image at a time (see the module docstring for the search order).

    ``observe(image, prior, seq, full_search)``: ``prior`` (T_world_camera) predicts the tag
    regions and resolves a single face; ``full_search`` False keeps to the predicted
    regions (the tracker, while the target should be out of view, searches the full frame
    only every few frames). ``fine_search`` False leaves out the finer full-frame passes
    after small tags or none (the tracker's: see ``TrackingProcessor``). State kept between
    calls: how many tags the last pose used, which tags needed the masked search, whether
    the tag size was checked, and what the library's corners disagree with an aligned pose
    by on this camera's sharp images.
    """

    def __init__(self, target: Target, calibration: CameraCalibration, options: PoseOptions | None = None,
                 detector_options: DetectorOptions | None = None, edge_refinement: bool = True,
                 full_frame_decimate: float = 3.0, edge_alignment: bool = True, fine_search: bool = True) -> None:
        self.target = target
        self.calibration = calibration
        self.options = options or PoseOptions()
        self._detector = TagDetector(target.family, detector_options, target.border_bits)
        self.edge_refinement = edge_refinement
        self.edge_alignment = edge_alignment  # align the pose to every cell edge (edge_alignment.py)
        self.full_frame_decimate = full_frame_decimate
        self.fine_search = fine_search  # finer full-frame passes after small or no tags (``_search``)
        self._prior: Transform | None = None
        self._last_tag_count = 0
        self._scale_checked = False
        self.last_search = ""
        self._suspects: set[int] = set()  # this frame's tags whose quads failed refinement
        self._full_decimate = full_frame_decimate  # this frame's finest full-frame pass so far
        self._decoded: dict[int, np.ndarray] = {}  # this frame's tags decoded by any search: corners
        self._masked_ids: set[int] = set()  # tags found only by the masked search
        self._scale_message = ""  # the tag-size warning, repeated on every refused frame
        # the library's corners' RMS about the aligned pose on the last steady frames: what
        # a sharp image gives with this camera (kept through reset: it is the lens's)
        self._steady_corner_rms: collections.deque[float] = collections.deque(
            maxlen=self.options.edges.sharp_history_frames)
        if edge_refinement or edge_alignment:
            jit.warm_up()  # the compiled kernels now, not on the first frame

    def reset(self) -> None:
        self._scale_message = ""
        self._masked_ids = set()
        self._prior = None
        self._last_tag_count = 0
        self._scale_checked = False
        self.last_search = ""

    def _ours(self, detections: list[TagDetection]) -> list[TagDetection]:
        """The target's tags among ``detections`` (each id once), all of them noted as
        decoded; returned only where every corner looks less than 90 deg off the axis (a
        fisheye's image corners may look further: the solvers' normalised coordinates
        would place such a corner on the wrong side)."""
        ours = unique_target_detections(detections, self.target)
        self._decoded.update((d.tag_id, d.corners) for d in ours)
        return [d for d in ours if ahead(d.corners, self.calibration).all()]

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
            white = grey_percentile(crop[inside == 1], 90.0)
            crop[inside == 0] = np.uint8(white)
            # Decimated first (4x cheaper); without decimation only if that finds nothing.
            detections = [d for d in self._detector.detect(crop) if d.tag_id == region.tag_id]
            if not detections:
                detections = self._detector.detect(crop, None, 1.0)
            for detection in detections:
                found.append(TagDetection(detection.tag_id, detection.corners + (x0, y0),
                                          detection.decision_margin, detection.hamming))
        return self._ours(found)

    def _search(self, image: np.ndarray, full_search: bool) -> list[TagDetection]:
        found: list[TagDetection] = []
        if self._prior is not None:
            regions = predicted_tag_regions(self.target, self.calibration, self._prior)
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
        if not full_search:
            self.last_search = "predicted" if found else ""
            return found
        self.last_search = "full"
        # Coarse first (decimate 3: a third of the cost of the paper's 2). An empty result
        # pays for one finer pass, as fine as the library's decimation costs on the paper's
        # frame (``finest_empty_decimate``). Small tags found (the target far, or a
        # low-resolution camera) may have smaller neighbours the coarse pass missed: a finer
        # pass that finds their like (``_finer``) runs only if the pose from what was found,
        # with the completion search, leaves a tag in view unused (``_observe``).
        decimate = self.full_frame_decimate
        found = self._ours(self._detector.detect(image, None, decimate))
        if not self.fine_search:  # the library's own decimation, and only after nothing
            if not found and decimate > self._detector.options.quad_decimate:
                found = self._ours(self._detector.detect(image))
            return found
        self._full_decimate = decimate
        if found:
            return self._decoded_finer(image, found, decimate)
        return self._finer(image, found, decimate)

    def _decoded_finer(self, image: np.ndarray, found: list[TagDetection], decimate: float) -> list[TagDetection]:
        """``found`` with each tag too small for ``decimate`` decoded again in its own
        neighbourhood at the decimation that keeps it findable (``decimate_for``): the
        library's corners of a small tag are the better the finer its quad search, and the
        edge alignment starts from them."""
        out = []
        for detection in found:
            finer = decimate_for(quad_width_px(detection.corners), decimate)
            if finer < decimate:
                # its box with the margin of a predicted region (``predicted_tag_regions``)
                x0, y0 = np.floor(detection.corners.min(axis=0) - REGION_MARGIN_PX).astype(int)
                x1, y1 = np.ceil(detection.corners.max(axis=0) + REGION_MARGIN_PX).astype(int)
                again = [d for d in self._ours(self._detector.detect(image, (x0, y0, x1, y1), finer))
                         if d.tag_id == detection.tag_id]
                detection = again[0] if again else detection
            out.append(detection)
        return out

    def _finer(self, image: np.ndarray, found: list[TagDetection], decimate: float) -> list[TagDetection]:
        """Full-frame passes finer than ``decimate`` until one keeps the smallest tag found
        findable (``decimate_for``; after nothing, ``finest_empty_decimate``); ``found`` with
        what they add."""
        while True:
            if found:
                finer = decimate_for(min(quad_width_px(d.corners) for d in found), decimate)
            else:
                finer = min(decimate, finest_empty_decimate(image.shape, self._detector.options.quad_decimate))
            if finer >= decimate:
                return found
            decimate = self._full_decimate = finer
            more = self._ours(self._detector.detect(image, None, decimate))
            have = {d.tag_id for d in more}
            found = more + [d for d in found if d.tag_id not in have]

    def _every_tag_in_view(self, pose: TargetPose | None) -> bool:
        """Whether ``pose`` uses every tag it puts wholly in the image facing the camera."""
        if pose is None:
            return False
        return set(tags_in_view(self.target, self.calibration, pose.T_world_camera)) <= set(pose.tag_ids)

    def _complete(self, image: np.ndarray, detections: list[TagDetection], pose: Transform,
                  growth: float = REGION_GROWTH) -> list[TagDetection]:
        """Tags the pose says are in view but the full-frame search missed, if found;
        ``growth``: how far around each predicted tag to search (``predicted_tag_regions``)."""
        have = {d.tag_id for d in detections}
        missing = [r for r in predicted_tag_regions(self.target, self.calibration, pose, growth)
                   if r.tag_id not in have]
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
        of a cube are within one tag size of it, and so are a board's neighbouring tags),
        then the regions its two possible poses predict (masked). What they find joins
        every tag found so far, and that whole set is posed; the seed and its finds alone
        only when they span more planes than the whole (another face of a cube beside a
        bad quad), so a pose never rests on fewer tags of the same plane than were found."""
        known = {d.tag_id: d for d in detections}
        planes = count_planes(self.target, list(known))
        for seed in sorted(detections, key=lambda d: -d.decision_margin):
            low, high = seed.corners.min(axis=0), seed.corners.max(axis=0)
            reach = float((high - low).max()) * NEIGHBOURHOOD_TAG_SIZES
            x0, y0 = np.floor(low - reach).astype(int)
            x1, y1 = np.ceil(high + reach).astype(int)
            near = [d for d in self._ours(self._detector.detect(image, (x0, y0, x1, y1), 1.0))
                    if d.tag_id not in known]
            # searched in this order, each only if the ones before gave no pose
            attempts = itertools.chain(
                [self._refine(image, near)] if near else [],
                (self._complete(image, list(known.values()), candidate)
                 for candidate in single_plane_candidates([seed], self.target, self.calibration)))
            for extra in attempts:
                extra = [d for d in extra if d.tag_id not in known]
                if not extra:
                    continue
                known.update((d.tag_id, d) for d in extra)
                tries = [list(known.values())]
                if count_planes(self.target, [seed.tag_id, *(d.tag_id for d in extra)]) > planes:
                    tries.append([seed, *extra])
                for tags in tries:
                    outcome = estimate_target_pose(tags, self.target, self.calibration, self.options,
                                                   self._prior, with_covariance=False)
                    if outcome.pose is not None:
                        self.last_search = "full+recovery"
                        return outcome, tags
                planes = count_planes(self.target, list(known))
        return None

    def _refine(self, image: np.ndarray, detections: list[TagDetection]) -> list[TagDetection]:
        """Corners from lines fitted to the tags' edges (see detection.refine_corners; on
        the synthetic camera a quarter of the library's corner error at 2 m). A detection
        whose edges do not fit its quad (a wrong quad with a right id) is dropped, and
        its id kept in ``self._suspects`` so that it is searched for again."""
        if not self.edge_refinement:
            return detections
        cells = self._detector.cells
        refined = []
        for detection in detections:
            better = refine_corners(image, detection, self.calibration, cells, saddles=self.target.grid is not None)
            if better is None:
                self._suspects.add(detection.tag_id)
            else:
                refined.append(better)
        return refined

    def _sharp_corner_rms(self) -> float:
        """What the library's own corners disagree with the aligned pose by on a sharp image
        of this camera: the 10th percentile of the last steady frames' RMS, at least
        ``EdgeOptions.sharp_corner_rms_px`` (the paper's camera: 0.02-0.05 px). Behind a wide lens (f 450
        px) they are 0.4-0.55 px off a pose within 0.05 px of the truth: blur judged
        against 0.05 px claimed 18-25 mm for 2 mm poses (python -m bench intrinsics)."""
        edges = self.options.edges
        if len(self._steady_corner_rms) < edges.sharp_min_frames:
            return edges.sharp_corner_rms_px
        return max(edges.sharp_corner_rms_px, float(np.percentile(self._steady_corner_rms, 10)))

    def observe(self, image: np.ndarray, prior: Transform | None, seq: int = 0,
                full_search: bool = True) -> Observation:
        """The target's pose in ``image`` (checked by the caller: ``image_problem``)."""
        self._prior = prior
        try:
            observation = self._observe(image, seq, full_search)
        except (cv2.error, np.linalg.LinAlgError) as exc:  # a degenerate view, not a bug of the caller's
            observation = Observation(None, Refusal.SOLVER,
                                      f"no pose: {type(exc).__name__}: {str(exc).strip()[:200]}")
        if observation.pose is None:
            self._last_tag_count = 0
            self._masked_ids = set()
        else:
            self._last_tag_count = len(observation.pose.tag_ids)
        return observation

    def _observe(self, image: np.ndarray, seq: int, full_search: bool) -> Observation:
        self._suspects = set()
        self._decoded = {}
        found = self._search(image, full_search)
        if not found:
            return Observation(None, Refusal.NO_TARGET, "no tag of the target in view", (), None, self.last_search)
        outcome, detections, steady = self._pose_of(image, found)
        if self.last_search.startswith("full") and self.fine_search and not self._every_tag_in_view(outcome.pose):
            coarse = self._full_decimate
            finer = self._finer(image, found, coarse)
            if self._full_decimate < coarse:  # a finer pass ran: its tags and corners
                self._suspects = set()
                self.last_search = "full"
                outcome, detections, steady = self._pose_of(image, finer)
        seen = tuple(sorted(self._decoded))  # every tag decoded, used or not
        outlines = tuple((i, self._decoded[i]) for i in seen)
        if outcome.pose is None:
            detail = outcome.detail
            if outcome.rejected is not None:
                # Large residuals on several faces: is the tag size in the file wrong?
                if not self._scale_checked:
                    self._scale_message = self._warn_on_scale(detections, outcome.rejected, seq)
                detail = f"{detail}; {self._scale_message}" if self._scale_message else detail
            return Observation(None, outcome.refusal, detail, seen, None, self.last_search, outlines)
        pose = outcome.pose
        by_id = {d.tag_id: d for d in detections}
        corners_px = np.concatenate([by_id[i].corners for i in pose.tag_ids]).astype(np.float64)
        if self.edge_alignment:
            aligned = refine_pose_on_edges(image, pose, self.target, self.calibration,
                                           sharp_corner_rms_px=self._sharp_corner_rms() if steady else None,
                                           options=self.options.edges)
            if aligned is not pose:  # else the alignment failed: the corners' pose stands
                if steady:
                    self._steady_corner_rms.append(float(np.sqrt(np.mean(aligned.residuals_px**2))))
                pose = aligned
                corners_px = project_pose(pose.points_world, pose.rvec, pose.tvec, self.calibration)
        if pose.covariance is None:  # computed once, for the pose returned (a weighted one has its own)
            pose = dataclasses.replace(pose, covariance=pose_covariance(pose, self.calibration))
        if not self._scale_checked and pose.planes >= 3:
            self._warn_on_scale(detections, pose, seq)
        return Observation(pose, None, outcome.detail, seen, corners_px, self.last_search, outlines)

    def _pose_of(self, image: np.ndarray, found: list[TagDetection]
                 ) -> tuple[PoseOutcome, list[TagDetection], bool]:
        """The pose of the tags ``found`` (refined unless in the steady state), completed by
        the tags it says are in view after a full search, or recovered from single tags:
        (outcome, the detections it was posed from, steady)."""
        # In the steady state the edge alignment replaces the corner refinement: the
        # library's corners only need to bring the pose within a third of a cell.
        steady = self.edge_alignment and self.last_search == "predicted"
        detections = found if steady else self._refine(image, found)
        outcome = estimate_target_pose(detections, self.target, self.calibration, self.options, self._prior,
                                       with_covariance=False)
        if steady and (outcome.pose is None or len(outcome.pose.tag_ids) < len(detections)):
            # a tag left out or no pose from the library's corners (a blurred quad): the
            # refined corners drop a bad quad by its edges, not by its neighbours' pose
            detections = self._refine(image, found)
            outcome = estimate_target_pose(detections, self.target, self.calibration, self.options, self._prior,
                                           with_covariance=False)
        if outcome.pose is not None and (self.last_search == "full" or self._suspects):
            # Search again for the tags the pose says are in view but it did not use
            # (not found, or left out as a bad quad); keep what improves the pose.
            used = [d for d in detections if d.tag_id in outcome.pose.tag_ids]
            extra = self._complete(image, used, outcome.pose.T_world_camera, COMPLETION_GROWTH)
            if extra:
                completed = estimate_target_pose(used + extra, self.target, self.calibration, self.options,
                                                 self._prior, with_covariance=False)
                if completed.pose is not None and len(completed.pose.tag_ids) > len(outcome.pose.tag_ids):
                    outcome, detections = completed, used + extra
        elif self.last_search == "full" and outcome.refusal in (Refusal.ONE_FACE, Refusal.REPROJECTION,
                                                                 Refusal.OBLIQUE):
            recovered = self._recover(image, detections)
            if recovered is not None:
                outcome, detections = recovered
        return outcome, detections, steady

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
