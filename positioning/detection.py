"""AprilTag detection: the AprilTag 3 C library through ``robotpy-apriltag``; tags with a
two-cell black border (a Kalibr AprilGrid) through OpenCV's ``ArucoDetector``.

The binding was chosen by measurement (docs/detector_choice.md): of pupil-apriltags,
pyapriltags, robotpy-apriltag and OpenCV's aruco module with the AprilTag dictionary, it
is the one that finds all 47 reference tags of the real photographs (46 within 0.1 px of
the library's own reference corners), and the AprilTag 3 bindings beat aruco's corners by
a factor of 4-8 in camera-position error on cube renders.

Two conventions are converted here, once, so nothing downstream knows about them:

* pixels: the C library puts the centre of the top-left pixel at (0.5, 0.5); OpenCV (and
  cubeloc) at (0, 0). We subtract 0.5.
* corner order: the library wraps the corners counter-clockwise in its own tag frame
  (in the image of an upright tag: TR, TL, BL, BR). cubeloc uses TL, TR, BR, BL of the tag
  printed upright, the order of ``cv2.aruco`` for a ``generateImageMarker`` image.

The AprilTag library expects a one-cell border with white around it. An AprilGrid's tags
have a two-cell border and black squares touching their corners: the library decodes none
of them, where ``cv2.aruco`` with ``markerBorderBits = 2`` decodes 35 of 36 (EuRoC) and 36
of 36 (TUM-VI) on the real frames of ``../shared/data/aprilgrid-real``. Its corners lie
0.5-1.5 px inside the tags' outer edges there; ``refine_corners(saddles=True)`` finds them
where the tags meet the grid's gap squares (docs/planar.md).

One ``TagDetector`` should live as long as the process: creating detectors is expensive,
and one binding was seen to crash in the destructor of a detector collected while another
one was alive (tests/test_detection.py exercises that lifecycle with this binding).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.camera_model import distort, undistort
from cubeloc.positioning.jit import compiled, read_only
from cubeloc.positioning.step_profiles import step_positions
from cubeloc.positioning.tag_bits import ARUCO_DICTIONARIES
from cubeloc.positioning.target import KNOWN_FAMILIES

# Library corner index for each of our TL, TR, BR, BL (see the module docstring).
LIBRARY_TO_UPRIGHT = np.array([1, 0, 3, 2])
LIBRARY_PIXEL_OFFSET = 0.5  # library pixel-centre convention minus OpenCV's
# OpenCV's decoder gives no confidence: its detections all count as this margin (the
# library's own default floor is 10; its sure decodes reach 50-150).
ARUCO_DECISION_MARGIN = 100.0
# Saddle corners (``_saddle_corners``): the search window's half-width in cells (1-1.6
# cells gave 0.25 px on the real EuRoC frame, 1 px 2.4 px, 2 cells 0.33 px), at most this
# many pixels, and the iteration's stop.
SADDLE_WINDOW_CELLS = 1.25
MAX_SADDLE_WINDOW_PX = 12
SADDLE_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.001)
# Cells across a tag with a one-cell black border included (the tag size spans these).
FAMILY_CELLS = {"tag36h11": 8, "tag36h10": 8, "tag25h9": 7, "tag16h5": 6}


def cells_across(family: str, border_bits: int = 1) -> int:
    """Cells across a tag of ``family`` with a black border of ``border_bits`` cells."""
    return FAMILY_CELLS[family] + 2 * (border_bits - 1)


@dataclass(frozen=True)
class TagDetection:
    """One decoded tag in an image."""

    tag_id: int
    corners: np.ndarray  # (4, 2) float64 pixels (OpenCV convention), TL TR BR BL as printed
    decision_margin: float  # the library's decode confidence; larger is better
    hamming: int  # bits corrected to decode

    @property
    def center(self) -> np.ndarray:
        return self.corners.mean(axis=0)


@dataclass(frozen=True)
class DetectorOptions:
    """Settings of the AprilTag 3 pipeline (the paper's values by default).

    ``quad_decimate`` 2 halves 1280x1024 to 640x512 for the quad search; ``refine_edges``
    then fits the edges on the full-resolution image, so corner accuracy is kept.
    """

    quad_decimate: float = 2.0
    quad_sigma: float = 0.0
    refine_edges: bool = True
    decode_sharpening: float = 0.25
    max_hamming: int = 1  # bits the decoder may correct; more admits false decodes
    min_decision_margin: float = 10.0
    min_cluster_pixels: int = 5  # the C library's default (robotpy's own is 300)
    critical_angle_deg: float = 10.0  # quads with a sharper corner angle are rejected
    threads: int = 1


def library_decimate(factor: float) -> float:
    """The largest decimation at most ``factor`` that the AprilTag library performs: 1.5 or
    a whole number (any other factor is resampled as its whole part while the quads are
    scaled back by the factor itself, and every tag is lost: 0 of 36 at 1.05 and 2.5)."""
    if factor < 1.5:
        return 1.0
    if factor < 2.0:
        return 1.5
    return float(int(factor))


class TagDetector:
    """A long-lived AprilTag detector for one family.

    ``detect(image, roi)`` searches the whole image or only ``roi = (x0, y0, x1, y1)``
    (pixel bounds, clipped to the image); corners always come back in full-image pixels.
    """

    def __init__(self, family: str = "tag36h11", options: DetectorOptions | None = None,
                 border_bits: int = 1) -> None:
        import robotpy_apriltag

        if family not in KNOWN_FAMILIES:
            raise ValueError(f"unrecognised tag family {family!r}; families I know: {', '.join(KNOWN_FAMILIES)}")
        if border_bits not in (1, 2):
            raise ValueError(f"border_bits must be 1 or 2, got {border_bits!r}")
        self.family = family
        self.border_bits = border_bits
        self.cells = cells_across(family, border_bits)
        self.options = options or DetectorOptions()
        o = self.options
        self._aruco = None
        if border_bits == 2:
            parameters = cv2.aruco.DetectorParameters()
            parameters.markerBorderBits = 2
            parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE  # refine_corners fits the edges
            dictionary = cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARIES[family])
            self._aruco = cv2.aruco.ArucoDetector(dictionary, parameters)
        detector = robotpy_apriltag.AprilTagDetector()
        if not detector.addFamily(family, o.max_hamming):
            raise ValueError(f"the AprilTag library does not know the family {family!r}")
        config = detector.getConfig()
        config.quadDecimate = o.quad_decimate
        config.quadSigma = o.quad_sigma
        config.refineEdges = o.refine_edges
        config.decodeSharpening = o.decode_sharpening
        config.numThreads = o.threads
        detector.setConfig(config)
        quad = detector.getQuadThresholdParameters()
        quad.minClusterPixels = o.min_cluster_pixels
        quad.criticalAngle = math.radians(o.critical_angle_deg)
        detector.setQuadThresholdParameters(quad)
        self._detector = detector
        self._decimate = o.quad_decimate
        self._sigma = o.quad_sigma

    def detect(self, image: np.ndarray, roi: tuple[int, int, int, int] | None = None,
               decimate: float | None = None, sigma: float | None = None) -> list[TagDetection]:
        """Decoded tags of ``image`` ((H, W) uint8), sorted by id, surest decode first.

        An id may appear more than once (two prints, a reflection); choosing is the
        caller's business. ``decimate`` overrides ``options.quad_decimate`` for this call
        (1 finds tags that decimation loses next to a bright background, at 4x the cost:
        for small regions); ``sigma`` overrides ``options.quad_sigma`` (the library's
        Gaussian blur of the decimated image before its quad search).
        """
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError(f"expected an (H, W) uint8 image, got {image.dtype} {image.shape}")
        original, x0, y0 = image, 0, 0
        if roi is not None:
            height, width = image.shape
            x0, y0 = max(0, int(roi[0])), max(0, int(roi[1]))
            x1, y1 = min(width, int(roi[2])), min(height, int(roi[3]))
            if x1 - x0 < 8 or y1 - y0 < 8:
                return []
            image = image[y0:y1, x0:x1]
        # The binding reads the buffer row by row: a crop must be made contiguous.
        image = np.ascontiguousarray(image)
        if self._aruco is not None:
            return self._detect_aruco(image, x0, y0)
        self._configure(decimate if decimate is not None else self.options.quad_decimate,
                        sigma if sigma is not None else self.options.quad_sigma)
        if self._sigma != 0 and self._decimate == 1 and np.shares_memory(image, original):
            # Undecimated, the library blurs (or sharpens) the buffer it is given in place:
            # it works on a copy, and the caller's image is left as it was.
            image = image.copy()
        corner_buffer = [0.0] * 8
        found = []
        for raw in self._detector.detect(image):
            margin = float(raw.getDecisionMargin())
            if margin < self.options.min_decision_margin:
                continue
            library_corners = np.array(raw.getCorners(corner_buffer), dtype=np.float64).reshape(4, 2)
            corners = library_corners[LIBRARY_TO_UPRIGHT] - LIBRARY_PIXEL_OFFSET + (x0, y0)
            found.append(TagDetection(int(raw.getId()), corners, margin, int(raw.getHamming())))
        found.sort(key=lambda d: (d.tag_id, -d.decision_margin))
        return found

    def _detect_aruco(self, image: np.ndarray, x0: int, y0: int) -> list[TagDetection]:
        """Two-cell borders: OpenCV's decoder (no decimation; its corners come in cubeloc's
        order and pixel convention). It reports no decision margin: each counts as
        ``ARUCO_DECISION_MARGIN``."""
        corners, ids, _ = self._aruco.detectMarkers(image)
        if ids is None:
            return []
        found = [TagDetection(int(i), c.reshape(4, 2).astype(np.float64) + (x0, y0), ARUCO_DECISION_MARGIN, 0)
                 for c, i in zip(corners, ids.ravel(), strict=True)]
        found.sort(key=lambda d: d.tag_id)
        return found

    def _configure(self, decimate: float, sigma: float) -> None:
        decimate = library_decimate(decimate)
        if decimate != self._decimate or sigma != self._sigma:
            config = self._detector.getConfig()
            config.quadDecimate = float(decimate)
            config.quadSigma = float(sigma)
            self._detector.setConfig(config)
            self._decimate, self._sigma = decimate, sigma

    def close(self) -> None:
        """Free the library's detector now (it is also freed when collected)."""
        self._detector.close()


# Edge refinement ------------------------------------------------------------------------
#
# The library's own edge refinement leaves ~0.1 px of corner noise on a clean 1280x1024
# render (a few mm of camera position at 4 m). Every outer edge of a tag is a straight
# black/white step about one cell wide on each side, so we can do much better: find the
# step on many short profiles across each edge (``step_profiles``), undistort those points,
# fit a straight line per edge (straight only without distortion), intersect neighbours,
# and distort the corners back.

_NEXT = np.array([1, 2, 3, 0])  # corner k's neighbour along the quad
EDGE_END_FRACTION = 0.12  # skip the edge ends, where the neighbouring edge's blur reaches
PROFILE_STEP_PX = 0.25
MIN_PROFILE_CONTRAST = 25.0  # grey levels between the black border and the white margin
MIN_EDGE_SAMPLES = 6


def _profile_layout(corners, half_width, step_px, end_fraction, min_samples):
    """The compiled loop under ``_edge_points``: K profiles across each edge k -> k+1
    (K from the shortest edge, less its ends), from the black border (inside) out to the
    white margin. Returns (starts (4K, 2), deltas (4K, 2), samples a profile, K)."""
    shortest = np.inf
    for k in range(4):
        shortest = min(shortest, np.hypot(corners[(k + 1) % 4, 0] - corners[k, 0],
                                          corners[(k + 1) % 4, 1] - corners[k, 1]))
    count = max(min_samples, int(shortest * (1 - 2 * end_fraction)))
    samples = int(np.ceil((2 * half_width + 1e-9) / step_px))  # as np.arange(-h, h + 1e-9, step)
    starts = np.empty((4 * count, 2))
    deltas = np.empty((4 * count, 2))
    for k in range(4):
        dx, dy = corners[(k + 1) % 4, 0] - corners[k, 0], corners[(k + 1) % 4, 1] - corners[k, 1]
        length = np.hypot(dx, dy) + 1e-300  # (compiled, a division by zero would raise)
        out_x, out_y = dy / length, -dx / length  # corners turn clockwise on screen
        for j in range(count):
            fraction = end_fraction + (1 - 2 * end_fraction) * j / (count - 1)
            row = k * count + j
            starts[row, 0] = corners[k, 0] + fraction * dx - half_width * out_x
            starts[row, 1] = corners[k, 1] + fraction * dy - half_width * out_y
            deltas[row, 0], deltas[row, 1] = step_px * out_x, step_px * out_y
    return starts, deltas, samples, count


def _warm_up_layout() -> None:
    _edge_points(np.zeros((16, 16), np.uint8), np.array([[4.0, 4.0], [12.0, 4.0], [12.0, 12.0], [4.0, 12.0]]), 1.0)


_compiled_layout = compiled(_profile_layout, _warm_up_layout)  # see positioning/jit.py


def _edge_points(image: np.ndarray, corners: np.ndarray, half_width_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel points (4, K, 2) of the black-to-white step on K profiles across each
    edge k -> k+1, and which are clean steps (4, K): none on an edge with clean steps
    over less than half its length. The layout compiled (``_profile_layout``): a tag of
    ~130 px in 0.12-0.20 ms with its step profiles, 0.25-0.30 ms as numpy (side by side)."""
    starts, deltas, samples, count = _compiled_layout()(read_only(corners, np.float64), float(half_width_px),
                                                        PROFILE_STEP_PX, EDGE_END_FRACTION, MIN_EDGE_SAMPLES)
    position, good, clean = step_positions(image, starts, deltas, samples, np.repeat(np.arange(4), count), 4,
                                           MIN_PROFILE_CONTRAST, rising_only=True)  # one edge a group
    points = (starts + position[:, None] * deltas).reshape(4, count, 2)
    enough = clean >= max(MIN_EDGE_SAMPLES, count // 2)
    return points, good.reshape(4, count) & enough[:, None]


def _fit(points, use, min_samples):
    """The compiled loop under ``_fit_lines``: (centre (E, 2), direction (E, 2), fitted)."""
    edges, count = use.shape
    use = use.copy()
    centre = np.zeros((edges, 2))
    direction = np.zeros((edges, 2))
    distance = np.empty(count)
    for _ in range(2):
        changed = False
        for e in range(edges):
            n = 0
            cx = 0.0
            cy = 0.0
            for k in range(count):
                if use[e, k]:
                    n += 1
                    cx += points[e, k, 0]
                    cy += points[e, k, 1]
            if n < min_samples:
                return centre, direction, False
            cx /= n
            cy /= n
            sxx = 0.0
            syy = 0.0
            sxy = 0.0
            for k in range(count):
                if use[e, k]:
                    dx, dy = points[e, k, 0] - cx, points[e, k, 1] - cy
                    sxx += dx * dx
                    syy += dy * dy
                    sxy += dx * dy
            # Direction of the largest spread of a 2x2 scatter matrix, in closed form.
            angle = 0.5 * np.arctan2(2.0 * sxy / n, (sxx - syy) / n)
            ux, uy = np.cos(angle), np.sin(angle)
            spread = 0.0
            for k in range(count):
                distance[k] = abs(-(points[e, k, 0] - cx) * uy + (points[e, k, 1] - cy) * ux)
                if use[e, k]:
                    spread += distance[k]
            spread = 1.25 * spread / n + 1e-12  # ~sigma for Gaussian scatter
            for k in range(count):
                if use[e, k] and distance[k] > 3.0 * spread:
                    use[e, k] = False
                    changed = True
            centre[e, 0], centre[e, 1] = cx, cy
            direction[e, 0], direction[e, 1] = ux, uy
        if not changed:
            break
    return centre, direction, True


def _warm_up() -> None:
    _fit_lines(np.zeros((4, MIN_EDGE_SAMPLES, 2)), np.ones((4, MIN_EDGE_SAMPLES), bool))


_compiled_fit = compiled(_fit, _warm_up)  # see positioning/jit.py


def _fit_lines(points: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(points (4, 2), unit directions (4, 2)) of the total-least-squares lines through
    the ``use``d points (4, K) of each edge's points (4, K, 2), after one outlier pass
    (points further than 3x 1.25x their mean distance, ~3 sigma); None when an edge has
    fewer than ``MIN_EDGE_SAMPLES``."""
    centre, direction, fitted = _compiled_fit()(read_only(points, np.float64), read_only(use, np.bool_),
                                                MIN_EDGE_SAMPLES)
    return (centre, direction) if fitted else None


def _corners_of(centre: np.ndarray, direction: np.ndarray) -> np.ndarray | None:
    """Corner k where line k-1 (into it) meets line k (out of it), by Cramer's rule; None
    when two neighbours are parallel."""
    pa, da = centre[[3, 0, 1, 2]], direction[[3, 0, 1, 2]]
    determinant = direction[:, 0] * da[:, 1] - da[:, 0] * direction[:, 1]
    if np.abs(determinant).min() < 1e-9:
        return None
    gap = centre - pa
    return pa + ((direction[:, 0] * gap[:, 1] - gap[:, 0] * direction[:, 1]) / determinant)[:, None] * da


def refine_corners(image: np.ndarray, detection: TagDetection, calibration: CameraCalibration | None = None,
                   cells: int = 8, passes: int = 1, saddles: bool = False) -> TagDetection | None:
    """The detection with corners from straight lines fitted to its four outer edges.

    With ``calibration`` the lines are fitted in undistorted
    coordinates, where the edges really are straight. ``cells`` is the number of cells
    across the tag including its black border (8 for tag36h11): profiles stay within
    0.4 of a cell on either side. Returns the detection unchanged when the tag is too
    small to gain from it, and None when its edges are not clean straight steps near the
    library's quad (occlusion, glare, or a quad the library fitted to the wrong edges
    while still decoding the id): such a detection should not be trusted.

    ``saddles``: each corner is where the tag meets a black square diagonally (a Kalibr
    AprilGrid), a saddle point that ``_saddle_corners`` finds instead.
    """
    if saddles:
        return _saddle_corners(image, detection, cells)
    corners = detection.corners.copy()
    for _ in range(passes):
        sides = corners[_NEXT] - corners
        size = float(np.mean(np.hypot(sides[:, 0], sides[:, 1])))
        half_width = min(0.4 * size / cells, 4.0)
        if half_width < 1.0:
            return detection  # cells under ~2.5 px: the library's corners are as good
        points, use = _edge_points(image, corners, half_width)
        if calibration is not None:
            points = undistort(points.reshape(-1, 2), calibration).reshape(points.shape)
        lines = _fit_lines(points, use)
        new = None if lines is None else _corners_of(*lines)
        if new is None:
            return None
        if calibration is not None:
            new = distort(new, calibration)
        if np.abs(new - detection.corners).max() > max(2.0, 0.05 * size):
            return None  # the edges are not where the library put them: a bad quad
        corners = new
    return TagDetection(detection.tag_id, corners, detection.decision_margin, detection.hamming)


def _saddle_corners(image: np.ndarray, detection: TagDetection, cells: int) -> TagDetection | None:
    """Corners at the saddle points where the tag's black border meets a black square
    diagonally (``cv2.cornerSubPix``, as Kalibr refines its AprilGrids), each searched
    within ``SADDLE_WINDOW_CELLS`` cells of the detector's corner, a cell measured along the
    shorter of the corner's two sides: inside the tag's two-cell border and the square's
    three cells however obliquely the tag is seen. On the real EuRoC frame the 35 tags'
    corners then fit one pose of the grid at 0.25 px RMS, where OpenCV's own were 2.5 px
    (0.5-1.5 px inside the tags, some a cell). None when a corner's search leaves its window (no saddle
    within reach: the decoder's corner a cell or more off, or no square there); a corner
    left where the decoder put it would be off by up to that much.
    """
    sides = np.roll(detection.corners, -1, axis=0) - detection.corners
    lengths = np.hypot(sides[:, 0], sides[:, 1])  # side k runs from corner k to corner k + 1
    # each corner's cell: along the shorter of its two sides (a tag seen obliquely)
    cell_px = np.minimum(lengths, np.roll(lengths, 1)) / cells
    corners = np.empty((4, 2))
    for k in range(4):
        half = int(np.clip(round(SADDLE_WINDOW_CELLS * cell_px[k]), 2, MAX_SADDLE_WINDOW_PX))
        start = detection.corners[k].astype(np.float32).reshape(1, 1, 2)
        found = cv2.cornerSubPix(image, start.copy(), (half, half), (-1, -1), SADDLE_CRITERIA)
        # cornerSubPix puts a corner back where it started when its search leaves the window
        if np.all(found == start) or not np.all(np.isfinite(found)):
            return None
        corners[k] = found.reshape(2)
    return TagDetection(detection.tag_id, corners, detection.decision_margin, detection.hamming)
