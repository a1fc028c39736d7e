"""The feature front end: Shi-Tomasi corners tracked frame to frame with pyramidal KLT.

Why KLT and not ORB matching for tracking: on two shared cores at 1280x1024 a KLT step
on a few hundred corners costs a few milliseconds, where ORB extraction
and matching on every frame costs several times that. KLT also gives sub-pixel positions, which the metric accuracy
needs, and a track's id carries its map point from frame to frame, so no descriptor
matching is needed while tracking. ORB descriptors are computed only on keyframes, for
relocalisation (``relocalise``).

Corners are found on a half-size image (4x less work, and corners of a 2x2 area are
what KLT's window locks on anyway), away from existing tracks (``min_distance_px``),
away from the image border and outside the target's outline: the target's corners reach
the tracker as fixed world points already, and points on a small cube would bunch.
"""

from __future__ import annotations

import cv2
import numpy as np

from positioning.tracking.options import FeatureOptions
from positioning.tracking.patch_alignment import PatchAligner
from positioning.tracking.types import Tracks


def view_at_scale(view_mask: np.ndarray, scale: int) -> np.ndarray:
    """``view_mask`` reduced as ``find_corners`` reduces the image (``detect_scale``): a
    block is usable only when all of it is."""
    if scale <= 1:
        return view_mask
    h, w = view_mask.shape[0] // scale, view_mask.shape[1] // scale
    return view_mask[: h * scale, : w * scale].reshape(h, scale, w, scale).min(axis=(1, 3))


def find_corners(image: np.ndarray, count: int, options: FeatureOptions, mask: np.ndarray | None = None,
                 min_distance_px: int | None = None) -> np.ndarray:
    """Up to ``count`` Shi-Tomasi corners (K, 2), full-resolution pixels, found on the
    image reduced by ``detect_scale`` (``mask`` is at that reduced size). Relocalisation
    uses the same function, so it finds the very corners the tracks started from."""
    s = max(1, options.detect_scale)
    small = cv2.resize(image, (image.shape[1] // s, image.shape[0] // s), interpolation=cv2.INTER_AREA) \
        if s > 1 else image
    distance = options.min_distance_px if min_distance_px is None else min_distance_px
    corners = cv2.goodFeaturesToTrack(small, count, options.quality_level, max(1, distance // s),
                                      mask=mask, blockSize=options.block_size)
    if corners is None:
        return np.zeros((0, 2))
    return corners.reshape(-1, 2) * s + (s - 1) / 2.0  # the centre of the s x s block


class KltFrontEnd:
    """KLT tracks of Shi-Tomasi corners. ``view_mask`` ((height, width) uint8, 255 where
    usable; ``camera_model.ahead_mask``): where corners may be born and tracks may go (a
    fisheye's pixels more than 90 deg off the axis are not)."""

    def __init__(self, options: FeatureOptions | None = None, view_mask: np.ndarray | None = None) -> None:
        self.options = options or FeatureOptions()
        self.view_mask = view_mask
        # the same at detect_scale, worked out once: detect() runs every frame
        self._detect_view = None if view_mask is None else view_at_scale(view_mask, max(1, self.options.detect_scale))
        alignment = self.options.alignment
        self._aligner = PatchAligner(alignment) if alignment is not None else None
        self.reset()

    def reset(self) -> None:
        self._previous: np.ndarray | None = None  # the previous image
        self._previous_float: np.ndarray | None = None  # the same as float32, for the aligner
        self._image_shape: tuple[int, int] | None = None
        self.ids = np.zeros(0, np.int64)
        self.pixels = np.zeros((0, 2), np.float32)
        self._next_id = 0
        if self._aligner is not None:
            self._aligner.reset()

    def ids_from(self, first: int) -> None:
        """New tracks get ids from ``first`` on (above a loaded map's point ids)."""
        self._next_id = max(self._next_id, int(first))

    def _keep(self, keep: np.ndarray) -> None:
        self.ids, self.pixels = self.ids[keep], self.pixels[keep]
        if self._aligner is not None:
            self._aligner.keep_only(self.ids)

    def _set_previous(self, image: np.ndarray) -> None:
        self._previous, self._image_shape = image, image.shape
        self._previous_float = image.astype(np.float32) if self._aligner is not None else None

    @property
    def tracks(self) -> Tracks:
        return Tracks(self.ids.copy(), self.pixels.astype(np.float64))

    def track(self, image: np.ndarray, guesses: np.ndarray | None = None) -> Tracks:
        """Follow the live tracks into ``image``; tracks that fail the forward-backward
        check or leave the image end here. ``guesses`` ((N, 2), one per live track, in the
        order of ``tracks``) are where the motion model expects them: KLT starts there."""
        o = self.options
        # OpenCV 5's Python binding takes images only (no prebuilt pyramids), so each call
        # builds its own pyramid: a millisecond or two per image at 1280x1024.
        if self._previous is None or len(self.ids) == 0 or image.shape != self._image_shape:
            if image.shape != self._image_shape:  # a new camera mode: nothing carries over
                self._keep(np.zeros(len(self.ids), bool))
            self._set_previous(image)
            return self.tracks
        window = (o.window_px, o.window_px)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
        prev = self.pixels.reshape(-1, 1, 2)
        guided = guesses is not None and np.shape(guesses) == (len(self.ids), 2)
        start = np.asarray(guesses, np.float32).reshape(-1, 1, 2).copy() if guided else None
        forward, status, _ = cv2.calcOpticalFlowPyrLK(
            self._previous, image, prev, start, winSize=window, maxLevel=o.pyramid_levels,
            criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW if guided else 0,
        )
        # Backwards, starting where they were and on the full-resolution level only: a
        # track that slid along an edge still converges to its own match (the check still
        # measures the slide), one that jumped to another corner does not converge at all;
        # the pyramid levels a search from scratch needs cost 3-4x as much (measured
        # 8.5 -> 1.9 ms for 300 tracks at 1280x1024).
        backward, back_status, _ = cv2.calcOpticalFlowPyrLK(
            image, self._previous, forward, prev.copy(), winSize=window, maxLevel=o.fb_check_levels,
            criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        forward = forward.reshape(-1, 2)
        fb_error = np.linalg.norm(backward.reshape(-1, 2) - self.pixels, axis=1)
        h, w = image.shape
        b = o.border_px / 2
        keep = (
            (status.ravel() == 1) & (back_status.ravel() == 1) & (fb_error <= o.max_fb_error_px)
            & (forward[:, 0] >= b) & (forward[:, 0] < w - b) & (forward[:, 1] >= b) & (forward[:, 1] < h - b)
        )
        if self.view_mask is not None and self.view_mask.shape == image.shape:
            rows, cols = np.round(forward[keep]).astype(int).T[::-1]
            keep[keep] = self.view_mask[np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)] > 0
        self.pixels = forward.astype(np.float32)
        self._keep(keep)
        self._set_previous(image)
        if self._aligner is not None and len(self.ids):
            refined, aligned = self._aligner.refine(self._previous_float, self.ids, self.pixels)
            self.pixels = refined.astype(np.float32)
            # no longer like its birth patch (occluded, or seen too obliquely): it goes on
            # from here, with this frame's patch as its template
            self._aligner.add(self._previous_float, self.ids[~aligned], self.pixels[~aligned])
        return self.tracks

    def detect(self, image: np.ndarray, exclude_polygon: np.ndarray | None = None) -> Tracks:
        """New corners in ``image`` (the one last tracked), up to ``max_features`` live
        tracks in all, outside ``exclude_polygon`` ((K, 2) pixels, the target's outline)."""
        o = self.options
        need = o.max_features - len(self.ids)
        if need <= 0:
            return Tracks.empty()
        s = max(1, o.detect_scale)
        mask = np.zeros((image.shape[0] // s, image.shape[1] // s), np.uint8)
        border = max(1, o.border_px // s)
        mask[border:-border, border:-border] = 255
        if self._detect_view is not None and self.view_mask.shape == image.shape:
            mask &= self._detect_view
        radius = max(1, o.min_distance_px // s)
        for x, y in self.pixels / s:
            cv2.circle(mask, (int(round(x)), int(round(y))), radius, 0, -1)
        if exclude_polygon is not None and len(exclude_polygon) >= 3:
            hull = cv2.convexHull(np.asarray(exclude_polygon, np.float32) / s).astype(np.int32)
            cv2.fillConvexPoly(mask, hull, 0)
            cv2.polylines(mask, [hull], True, 0, thickness=max(1, 2 * o.target_margin_px // s))
        pixels = find_corners(image, need, o, mask)
        if len(pixels) == 0:
            return Tracks.empty()
        return self.add(pixels)

    def add(self, pixels: np.ndarray) -> Tracks:
        """Start new tracks at ``pixels``; returns them with their fresh ids."""
        pixels = np.asarray(pixels, np.float32).reshape(-1, 2)
        ids = np.arange(self._next_id, self._next_id + len(pixels), dtype=np.int64)
        self._next_id += len(pixels)
        self._append(ids, pixels)
        return Tracks(ids, pixels.astype(np.float64))

    def _append(self, ids: np.ndarray, pixels: np.ndarray) -> None:
        """New tracks in the image last tracked."""
        self.ids = np.concatenate([self.ids, ids])
        self.pixels = np.concatenate([self.pixels, pixels])
        if self._aligner is not None and self._previous_float is not None:
            self._aligner.add(self._previous_float, ids, pixels)

    def adopt(self, ids: np.ndarray, pixels: np.ndarray) -> None:
        """Follow the given (existing) track ids from ``pixels``: after relocalisation,
        the matched map points come back as tracks under their own ids."""
        ids = np.asarray(ids, np.int64)
        fresh = ~np.isin(ids, self.ids)
        self._append(ids[fresh], np.asarray(pixels, np.float32).reshape(-1, 2)[fresh])

    def drop(self, ids: np.ndarray) -> None:
        if len(ids):
            self._keep(~np.isin(self.ids, ids))
