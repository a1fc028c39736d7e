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

KLT matches intensities, so a change of brightness between two frames (an auto-exposure
step, the lights going on) breaks its matches. The tracks it keeps measure the change
(``brightness_ratio``); when there is one, KLT runs again with the brighter image dimmed
to the darker one's brightness. An exposure step of 0.66 on the family lost 128 of 188
tracks in one frame, and the map with them.
"""

from __future__ import annotations

import cv2
import numpy as np

from cubeloc.positioning.geometry import robust_sigma
from cubeloc.positioning.tracking.options import FeatureOptions
from cubeloc.positioning.tracking.patch_alignment import PatchAligner
from cubeloc.positioning.tracking.types import Tracks


def view_at_scale(view_mask: np.ndarray, scale: int) -> np.ndarray:
    """``view_mask`` reduced as ``find_corners`` reduces the image (``detect_scale``): a
    block is usable only when all of it is."""
    if scale <= 1:
        return view_mask
    h, w = view_mask.shape[0] // scale, view_mask.shape[1] // scale
    return view_mask[: h * scale, : w * scale].reshape(h, scale, w, scale).min(axis=(1, 3))


def local_brightness(image: np.ndarray) -> np.ndarray:
    """The image's brightness around each pixel, at a quarter of its size (float32): the
    mean over ~20 x 20 pixels, about KLT's window (4 x 4 blocks, then a 5 x 5 box)."""
    h, w = max(1, image.shape[0] // 4), max(1, image.shape[1] // 4)
    small = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
    return cv2.blur(small, (5, 5))


def brightness_ratio(previous: np.ndarray, previous_pixels: np.ndarray, current: np.ndarray,
                     current_pixels: np.ndarray) -> float:
    """How much brighter ``current`` is than ``previous`` (``local_brightness`` maps), from
    matched pixels (a track's position in each): the median of their ratios, over those
    neither dark nor saturated in either. 1 when the median does not differ from 1 by
    three of its standard errors (what the matches' own scatter allows), or when it
    would move no pixel value by half a level, or with fewer than 16 matches: then
    nothing measurably changed."""

    def at(brightness: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        # a quarter-size pixel j is the mean of full-size pixels 4j .. 4j+3 (centre 4j+1.5)
        xy = ((np.asarray(pixels, np.float32).reshape(-1, 1, 2) - 1.5) / 4.0).astype(np.float32)
        return cv2.remap(brightness, xy[..., 0], xy[..., 1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE).ravel()

    if len(previous_pixels) < 16:
        return 1.0
    before, after = at(previous, previous_pixels), at(current, current_pixels)
    usable = (before > 16) & (before < 240) & (after > 16) & (after < 240)
    if usable.sum() < 16:
        return 1.0
    logs = np.log(after[usable] / before[usable])
    median = float(np.median(logs))
    # the median's standard error: 1.2533 sigma / sqrt(n), sigma from the MAD
    standard_error = robust_sigma(logs, median, times=1.2533) / np.sqrt(len(logs))
    gain = float(np.exp(median))
    if abs(median) <= 3.0 * standard_error or abs(gain - 1.0) * 255.0 < 0.5:
        return 1.0
    return gain


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
        self._previous_brightness: np.ndarray | None = None  # its local_brightness
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

    def _set_previous(self, image: np.ndarray, brightness: np.ndarray | None = None) -> None:
        self._previous, self._image_shape = image, image.shape
        self._previous_brightness = local_brightness(image) if brightness is None else brightness
        self._previous_float = image.astype(np.float32) if self._aligner is not None else None

    @property
    def tracks(self) -> Tracks:
        return Tracks(self.ids.copy(), self.pixels.astype(np.float64))

    def track(self, image: np.ndarray, guesses: np.ndarray | None = None) -> Tracks:
        """Follow the live tracks into ``image``; tracks that fail the forward-backward
        check or leave the image end here. ``guesses`` ((N, 2), one per live track, in the
        order of ``tracks``) are where the motion model expects them: KLT starts there."""
        # OpenCV 5's Python binding takes images only (no prebuilt pyramids), so each call
        # builds its own pyramid: a millisecond or two per image at 1280x1024.
        if self._previous is None or len(self.ids) == 0 or image.shape != self._image_shape:
            if image.shape != self._image_shape:  # a new camera mode: nothing carries over
                self._keep(np.zeros(len(self.ids), bool))
            self._set_previous(image)
            return self.tracks
        guided = guesses is not None and np.shape(guesses) == (len(self.ids), 2)
        start = np.asarray(guesses, np.float32).reshape(-1, 1, 2) if guided else None  # _flow copies it
        forward, keep = self._flow(self._previous, image, start)
        # The tracks KLT kept measure any change of brightness (an auto-exposure step):
        # with one, both images at the darker one's brightness (no pixel saturates by
        # it), and KLT again, for every track
        brightness = local_brightness(image)
        gain = brightness_ratio(self._previous_brightness, self.pixels[keep], brightness, forward[keep])
        if gain != 1.0:
            previous, current = self._previous, image
            if gain < 1.0:
                previous = cv2.convertScaleAbs(previous, alpha=gain)
            else:
                current = cv2.convertScaleAbs(current, alpha=1.0 / gain)
            forward, keep = self._flow(previous, current, start)
        self.pixels = forward.astype(np.float32)
        self._keep(keep)
        self._set_previous(image, brightness)
        if self._aligner is not None and len(self.ids):
            refined, aligned = self._aligner.refine(self._previous_float, self.ids, self.pixels)
            self.pixels = refined.astype(np.float32)
            # no longer like its birth patch (occluded, or seen too obliquely): it goes on
            # from here, with this frame's patch as its template
            self._aligner.add(self._previous_float, self.ids[~aligned], self.pixels[~aligned])
        return self.tracks

    def _flow(self, previous: np.ndarray, current: np.ndarray, start: np.ndarray | None
              ) -> tuple[np.ndarray, np.ndarray]:
        """KLT from ``previous`` into ``current`` for every live track, from ``start`` when
        given: (positions (N, 2), which tracks hold: the forward-backward check, inside the
        image border and the view mask)."""
        o = self.options
        window = (o.window_px, o.window_px)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
        prev = self.pixels.reshape(-1, 1, 2)
        forward, status, _ = cv2.calcOpticalFlowPyrLK(
            previous, current, prev, None if start is None else start.copy(), winSize=window,
            maxLevel=o.pyramid_levels, criteria=criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW if start is not None else 0,
        )
        # Backwards, starting where they were and on the full-resolution level only: a
        # track that slid along an edge still converges to its own match (the check still
        # measures the slide), one that jumped to another corner does not converge at all;
        # the pyramid levels a search from scratch needs cost 3-4x as much (measured
        # 8.5 -> 1.9 ms for 300 tracks at 1280x1024).
        backward, back_status, _ = cv2.calcOpticalFlowPyrLK(
            current, previous, forward, prev.copy(), winSize=window, maxLevel=o.fb_check_levels,
            criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        forward = forward.reshape(-1, 2)
        fb_error = np.linalg.norm(backward.reshape(-1, 2) - self.pixels, axis=1)
        h, w = current.shape
        b = o.border_px / 2
        keep = (
            (status.ravel() == 1) & (back_status.ravel() == 1) & (fb_error <= o.max_fb_error_px)
            & (forward[:, 0] >= b) & (forward[:, 0] < w - b) & (forward[:, 1] >= b) & (forward[:, 1] < h - b)
        )
        if self.view_mask is not None and self.view_mask.shape == current.shape:
            rows, cols = np.round(forward[keep]).astype(int).T[::-1]
            keep[keep] = self.view_mask[np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)] > 0
        return forward, keep

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
