"""Measure where the tags' corners landed in a rendered frame, against their true projection.

The proof that the renderer's geometry is exact. On a noise-free frame, each outer edge of
a tag's black border is a step from the black border to the white margin. Along one pixel
row (or column) crossing such an edge, the pixel values are the fractions of each pixel
the white side covers, so their sum gives the edge crossing of that row exactly, for any
edge angle (the covered area of a pixel row is a trapezoid whose width is taken at the
row's centre). The crossings, undistorted to normalised coordinates, lie on a straight
line; two adjacent lines meet at the corner, which is distorted back to pixels and
compared with ``fakes.optics.project`` of the tag's 3-D corner. No detector, no model of
the image blur: only area coverage, which supersampling approximates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.fakes.optics import project, undistort_pixels
from cubeloc.fakes.scene import INK_BLACK, PAPER_WHITE, face_brightness, tag_bits
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.target import Target

MAX_VIEW_ANGLE_DEG = 70.0  # faces seen more obliquely are skipped (edges too compressed)


@dataclass(frozen=True)
class CornerErrors:
    tag_ids: tuple[int, ...]  # one per measured tag
    measured_px: np.ndarray  # (N, 4, 2)
    true_px: np.ndarray  # (N, 4, 2)

    @property
    def errors_px(self) -> np.ndarray:
        """(4N,) Euclidean corner errors in pixels."""
        return np.linalg.norm(self.measured_px - self.true_px, axis=2).ravel()


def _crossing(start: np.ndarray, end: np.ndarray, line: int, a: int, b: int) -> float:
    """Where the straight segment start->end crosses scan line ``line`` (axis a), on axis b."""
    return float(start[b] + (line - start[a]) * (end[b] - start[b]) / (end[a] - start[a]))


def _edge_crossings(
    image: np.ndarray, edge: np.ndarray, inner: np.ndarray, outer: np.ndarray, dark: float, bright: float
) -> np.ndarray:
    """Sub-pixel points (M, 2) of the tag edge ``edge`` (2, 2), one per pixel row or column
    crossed in its middle 70 %. ``inner`` is the inner edge of the black border and ``outer``
    the face's edge, both (2, 2): the scan window stays between them (plateaus only)."""
    start, end = edge
    direction = end - start
    along_rows = abs(direction[1]) >= abs(direction[0])  # steep edge: one crossing per row
    a, b = (1, 0) if along_rows else (0, 1)  # a: the scan-line axis, b: the crossing axis
    lo, hi = sorted((start[a], end[a]))
    span = hi - lo
    points = []
    for line in range(int(np.ceil(lo + 0.15 * span)), int(np.floor(hi - 0.15 * span)) + 1):
        # the scan window must stay in this edge's strip, clear of the perpendicular edges:
        # so the scan line must cross the inner and outer edges between their end points
        if not all(0.05 < (line - p[0][a]) / (p[1][a] - p[0][a]) < 0.95 for p in (inner, outer)):
            continue
        at_inner = _crossing(*inner, line, a, b)
        at_outer = _crossing(*outer, line, a, b)
        # whole pixels of the plateaus, a pixel clear of the neighbouring edges (which
        # distortion bends slightly away from the straight prediction)
        first = int(np.ceil(min(at_inner, at_outer) + 1.0))
        last = int(np.floor(max(at_inner, at_outer) - 1.0))
        if last - first < 3 or first < 0 or last >= image.shape[1 - b]:
            continue
        values = image[line, first : last + 1] if along_rows else image[first : last + 1, line]
        fraction = (values.astype(np.float64) - dark) / (bright - dark)
        if at_inner > at_outer:  # bright (margin) first: the bright part is [first - 0.5, edge)
            crossing = first - 0.5 + fraction.sum()
        else:  # dark first: the bright part is [edge, last + 0.5)
            crossing = last + 0.5 - fraction.sum()
        point = np.empty(2)
        point[a], point[b] = line, crossing
        points.append(point)
    return np.array(points).reshape(-1, 2)


def _fit_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total least squares: (centroid, unit direction)."""
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid)
    return centroid, vt[0]


def _intersect(line1: tuple[np.ndarray, np.ndarray], line2: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    (p, d), (q, e) = line1, line2
    t = np.linalg.solve(np.column_stack([d, -e]), q - p)
    return p + t[0] * d


def measure_tag_corners(
    image: np.ndarray,
    T_world_camera: Transform,
    calibration: CameraCalibration,
    target: Target,
    *,
    exposure_gain: float = 1.0,
    hidden_tags: tuple[int, ...] = (),
) -> CornerErrors:
    """Measure the outer corners of every tag seen well enough in a noise-free ``image``."""
    T_camera_world = T_world_camera.inverse()
    camera_centre = T_world_camera.translation
    ids, measured, truth = [], [], []
    for tag in target.tags:
        if tag.tag_id in hidden_tags:
            continue
        to_camera = camera_centre - tag.center
        cos_view = float(tag.normal @ to_camera / np.linalg.norm(to_camera))
        if cos_view < np.cos(np.radians(MAX_VIEW_ANGLE_DEG)):
            continue
        corners_camera = T_camera_world.apply(tag.corners)
        if np.any(corners_camera[:, 2] <= 0):
            continue
        corners_px = project(corners_camera, calibration)
        if np.any(corners_px < 3) or np.any(corners_px > np.array(calibration.size) - 4):
            continue
        cells = tag_bits(target.family, tag.tag_id).shape[0]
        cell_m = tag.size_m / cells
        margin_m = (target.cube.side_m - tag.size_m) / 2 if target.cube is not None else cell_m
        # the inner edge of the black border and the edge of the face (or plate), in pixels
        centre = tag.center
        inner_px = project(T_camera_world.apply(centre + (tag.corners - centre) * (1 - 2 / cells)), calibration)
        outer_px = project(
            T_camera_world.apply(centre + (tag.corners - centre) * (1 + 2 * margin_m / tag.size_m)), calibration
        )
        light = face_brightness(tag.normal) * 255.0 * exposure_gain
        dark, bright = float(np.rint(INK_BLACK * light)), float(np.rint(PAPER_WHITE * light))
        lines = []
        for i in range(4):
            j = (i + 1) % 4
            crossings = _edge_crossings(
                image, corners_px[[i, j]], inner_px[[i, j]], outer_px[[i, j]], dark, bright
            )
            if len(crossings) < 5:
                break
            lines.append(_fit_line(undistort_pixels(crossings, calibration)))
        if len(lines) < 4:
            continue
        found = []
        for i in range(4):  # corner i is where edge i-1 (into it) meets edge i (out of it)
            xy = _intersect(lines[i - 1], lines[i])
            found.append(project(np.array([[xy[0], xy[1], 1.0]]), calibration)[0])
        ids.append(tag.tag_id)
        measured.append(found)
        truth.append(corners_px)
    return CornerErrors(tuple(ids), np.array(measured).reshape(-1, 4, 2), np.array(truth).reshape(-1, 4, 2))
