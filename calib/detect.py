"""Find a calibration board in one image: image points, their board points, and sharpness.

Detection is kept apart from solving (as mrcal does): ``calib.corners_cache`` stores
what this module finds next to the images, so a re-solve never detects twice.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from cubeloc.calib.boards import APRILGRID_FAMILY, BoardSpec

MIN_BOARD_POINTS = 8  # a partial view (ChArUco, AprilGrid: two tags) with fewer does not constrain its pose well
MAX_EDGE_WIDTH_PX = 5.0  # a 10-90 % edge wider than this is a blurred view


@dataclass(frozen=True)
class Detection:
    """The board as seen in one image."""

    image_points: np.ndarray  # (N, 2) float32 pixels, OpenCV convention
    object_points: np.ndarray  # (N, 3) float32 board frame, metres
    ids: np.ndarray  # (N,) int32 index of each point in ``BoardSpec.object_points()``
    edge_width_px: float  # median blur estimate at the points (about 1 px when sharp)

    @property
    def count(self) -> int:
        return len(self.image_points)

    @property
    def is_sharp(self) -> bool:
        return self.edge_width_px <= MAX_EDGE_WIDTH_PX


def detect_board(image: np.ndarray, board: BoardSpec) -> Detection | None:
    """The board's points in a (H, W) uint8 image, or None when it is not found."""
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"expected a (H, W) uint8 image, got {image.dtype} {image.shape}")
    if board.kind == "charuco":
        found = _detect_charuco(image, board)
    elif board.kind == "aprilgrid":
        found = _detect_aprilgrid(image, board)
    elif board.kind == "chessboard":
        found = _detect_chessboard(image, board)
    else:
        found = _detect_circles(image, board)
    if found is None:
        return None
    points, ids = found
    all_object = board.object_points()
    return Detection(
        image_points=points.astype(np.float32),
        object_points=all_object[ids],
        ids=ids.astype(np.int32),
        edge_width_px=edge_width_px(image, points),
    )


def _detect_charuco(image: np.ndarray, board: BoardSpec) -> tuple[np.ndarray, np.ndarray] | None:
    charuco = board.charuco_board()
    detector = cv2.aruco.CharucoDetector(charuco)
    corners, ids, _, _ = detector.detectBoard(image)
    if ids is None or len(ids) < MIN_BOARD_POINTS:
        return None
    ids = ids.reshape(-1)
    if charuco.checkCharucoCornersCollinear(ids):
        return None
    return corners.reshape(-1, 2), ids


@functools.lru_cache(maxsize=1)
def _aprilgrid_detector():
    from cubeloc.positioning.detection import TagDetector

    return TagDetector(APRILGRID_FAMILY, border_bits=2)


def _detect_aprilgrid(image: np.ndarray, board: BoardSpec) -> tuple[np.ndarray, np.ndarray] | None:
    # The tags as the AprilGrid targets find them (OpenCV's aruco decoder, two-cell
    # borders), each corner moved to the saddle point where the tag meets its gap square
    # (positioning.detection): 0.25 px RMS on the real EuRoC frame where the decoder's
    # own corners give 2.5. Tags whose saddles cannot be found are left out.
    from cubeloc.positioning.detection import refine_corners

    detector = _aprilgrid_detector()
    found = detector.detect(image)
    if any(d.tag_id >= board.cols * board.rows for d in found):
        return None  # another grid: its tags would sit in the wrong places
    points, ids, seen = [], [], set()
    for detection in found:  # sorted by id, the surest decode of a repeated id first
        if detection.tag_id in seen:
            continue
        seen.add(detection.tag_id)
        refined = refine_corners(image, detection, None, detector.cells, saddles=True)
        if refined is not None:
            points.append(refined.corners)
            ids.append(4 * detection.tag_id + np.arange(4))
    if 4 * len(points) < MIN_BOARD_POINTS:
        return None
    return np.concatenate(points), np.concatenate(ids)


def _detect_chessboard(image: np.ndarray, board: BoardSpec) -> tuple[np.ndarray, np.ndarray] | None:
    # The classic detector refined by cornerSubPix, then by a fit of the corner's model
    # (``_fit_x_junctions``). Measured on exactly rendered noise-free 1280x1024 views, RMS
    # corner error: this 0.001 px, cornerSubPix alone 0.023, findChessboardCornersSB 0.058
    # (0.029 with CALIB_CB_ACCURACY).
    pattern = board.inner_corners
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCorners(image, pattern, flags=flags)
    if not ok:
        return None
    corners = corners.reshape(-1, 2)
    spacing = _min_spacing(corners, pattern)
    # The start of the fit below. The window must stay well inside one square: at 0.25
    # of the spacing and more the corner next to the board's outer edge is pulled by up
    # to 1.3 px (measured).
    half = int(np.clip(0.15 * spacing, 3, 8))
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
    refined = cv2.cornerSubPix(image, corners.reshape(-1, 1, 2).copy(), (half, half), (-1, -1), criteria)
    corners = _fit_x_junctions(image, refined.reshape(-1, 2), pattern)
    if not _grid_is_regular(corners, board):
        return None
    return corners, np.arange(pattern[0] * pattern[1])


FIT_RADIUS_SPACING = 0.35  # fit window radius, as a fraction of the distance to the nearest corner
FIT_RADIUS_PX = (3.0, 12.0)  # ... clipped to this
FIT_ITERATIONS = 12


def _fit_x_junctions(image: np.ndarray, corners: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    """Chessboard corners refined by fitting each one's model to the pixels around it.

    cornerSubPix reads the image between pixels by bilinear interpolation; on sharp
    edges (a good lens) that leaves an error that depends on where the corner falls
    within its pixel: RMS 0.02 px, up to 0.05 px, on analytic corners (0.5 px blur) and
    on exact renders, where this fit leaves 0.002 px. Such structured error moved a
    25-view solve's principal point by up to 1 px. Here the pixels themselves are fitted, by
    Gauss-Newton, with a blurred X-junction: two straight lines through the corner
    c (the grid lines, any angle: perspective keeps them straight), and
    I = m + a * erf(d1 / (sqrt(2) s)) * erf(d2 / (sqrt(2) s)), d1, d2 the signed distances
    to the lines. All corners are solved at once. A corner whose fit fails (moves more
    than 1 px, or does not converge: a blurred or partly hidden corner) keeps its
    cornerSubPix position.
    """
    from scipy.special import erf

    cols, rows = pattern
    start = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    grid = start.reshape(rows, cols, 2)
    along_row = np.gradient(grid, axis=1).reshape(-1, 2)
    along_col = np.gradient(grid, axis=0).reshape(-1, 2)
    nearest = np.full((rows, cols), np.inf)
    row_gap = np.linalg.norm(np.diff(grid, axis=1), axis=-1)
    col_gap = np.linalg.norm(np.diff(grid, axis=0), axis=-1)
    nearest[:, :-1] = np.minimum(nearest[:, :-1], row_gap)
    nearest[:, 1:] = np.minimum(nearest[:, 1:], row_gap)
    nearest[:-1] = np.minimum(nearest[:-1], col_gap)
    nearest[1:] = np.minimum(nearest[1:], col_gap)
    radius = np.clip(FIT_RADIUS_SPACING * nearest.ravel(), *FIT_RADIUS_PX)

    reach = int(np.ceil(FIT_RADIUS_PX[1]))
    offsets = np.arange(-reach, reach + 1)
    dy_grid, dx_grid = np.meshgrid(offsets, offsets, indexing="ij")
    centre = np.rint(start).astype(np.int64)
    xs = centre[:, :1] + dx_grid.ravel()[None]  # (N, P) pixel columns
    ys = centre[:, 1:] + dy_grid.ravel()[None]
    height, width = image.shape
    inside = (xs >= 0) & (xs < width) & (ys >= 0) & (ys < height)
    values = image[np.clip(ys, 0, height - 1), np.clip(xs, 0, width - 1)].astype(np.float64)
    weights = (inside & ((xs - start[:, :1]) ** 2 + (ys - start[:, 1:]) ** 2 <= radius[:, None] ** 2)).astype(np.float64)

    # parameters per corner: cx, cy, angle of line 1, angle of line 2, log blur, m, a
    params = np.column_stack([
        start,
        np.arctan2(along_row[:, 1], along_row[:, 0]),
        np.arctan2(along_col[:, 1], along_col[:, 0]),
        np.zeros(len(start)),
        np.zeros(len(start)),
        np.zeros(len(start)),
    ])
    root_pi = 2.0 / np.sqrt(np.pi)
    step = np.zeros_like(params)
    for iteration in range(FIT_ITERATIONS):
        dx = xs - params[:, :1]
        dy = ys - params[:, 1:2]
        sin1, cos1 = np.sin(params[:, 2:3]), np.cos(params[:, 2:3])
        sin2, cos2 = np.sin(params[:, 3:4]), np.cos(params[:, 3:4])
        d1 = cos1 * dy - sin1 * dx
        d2 = cos2 * dy - sin2 * dx
        k = 1.0 / (np.sqrt(2.0) * np.exp(params[:, 4:5]))
        e1, e2 = erf(d1 * k), erf(d2 * k)
        product = e1 * e2
        if iteration == 0:  # m and a by linear least squares for the starting geometry
            sw, sp = weights.sum(1), (weights * product).sum(1)
            spp, si = (weights * product**2).sum(1), (weights * values).sum(1)
            spi = (weights * product * values).sum(1)
            with np.errstate(divide="ignore", invalid="ignore"):
                params[:, 6] = (sw * spi - sp * si) / (sw * spp - sp**2)
                params[:, 5] = (si - params[:, 6] * sp) / sw
        m, a = params[:, 5:6], params[:, 6:7]
        residual = values - (m + a * product)
        g1 = root_pi * np.exp(-((d1 * k) ** 2)) * k  # d erf(d1 k) / d d1
        g2 = root_pi * np.exp(-((d2 * k) ** 2)) * k
        jacobian = np.stack([
            a * (g1 * sin1 * e2 + e1 * g2 * sin2),
            -a * (g1 * cos1 * e2 + e1 * g2 * cos2),
            -a * g1 * (cos1 * dx + sin1 * dy) * e2,
            -a * e1 * g2 * (cos2 * dx + sin2 * dy),
            -a * (g1 * d1 * e2 + e1 * g2 * d2),
            np.ones_like(product),
            product,
        ], axis=-1)
        weighted = jacobian * weights[..., None]
        normal = np.matmul(weighted.transpose(0, 2, 1), jacobian) + 1e-9 * np.eye(7)
        gradient = np.matmul(weighted.transpose(0, 2, 1), residual[..., None])[..., 0]
        with np.errstate(all="ignore"):
            try:
                step = np.linalg.solve(normal, gradient[..., None])[..., 0]
            except np.linalg.LinAlgError:
                return start.astype(np.float32)
        step[:, :2] = np.clip(step[:, :2], -0.5, 0.5)
        step[:, 2:4] = np.clip(step[:, 2:4], -0.2, 0.2)
        params = params + step
        params[:, 4] = np.clip(params[:, 4], np.log(0.3), np.log(6.0))  # blur sigma 0.3 .. 6 px
        if np.abs(step[:, :2]).max() < 1e-4:  # every corner has settled
            break
    fitted = params[:, :2]
    good = (
        np.isfinite(fitted).all(axis=1)
        & (np.abs(step[:, :2]).max(axis=1) < 1e-3)
        & (np.linalg.norm(fitted - start, axis=1) < 1.0)
        & (weights.sum(1) >= 12)
    )
    return np.where(good[:, None], fitted, start).astype(np.float32)


def _blob_detector(image_shape: tuple[int, int]) -> cv2.SimpleBlobDetector:
    # OpenCV's defaults reject spurious blobs well; only the area cap (5000 px^2) is too
    # small for a near board on a 1.3 MP sensor. A cap much larger lets dark background
    # regions in as blobs, so it grows with the image: 1 % of it.
    params = cv2.SimpleBlobDetector_Params()
    params.maxArea = max(5000.0, 0.01 * image_shape[0] * image_shape[1])
    return cv2.SimpleBlobDetector_create(params)


def _detect_circles(image: np.ndarray, board: BoardSpec) -> tuple[np.ndarray, np.ndarray] | None:
    pattern = board.inner_corners
    grid = cv2.CALIB_CB_SYMMETRIC_GRID if board.kind == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
    detector = _blob_detector(image.shape)
    # The default grid finder fails on some steep views that clustering solves, and
    # clustering sometimes orders a grid wrongly: try both, keep what passes the checks.
    for flags in (grid, grid | cv2.CALIB_CB_CLUSTERING):
        ok, centres = cv2.findCirclesGrid(image, pattern, flags=flags, blobDetector=detector)
        if ok and centres is not None:
            centres = centres.reshape(-1, 2)
            if _grid_is_regular(centres, board) and _faces_camera(centres, board):
                return centres, np.arange(pattern[0] * pattern[1])
    return None


def _faces_camera(points: np.ndarray, board: BoardSpec) -> bool:
    """False for a mirrored point order: seen from the front, board x right and y down
    map to image directions with a positive cross product (as x right, y down do)."""
    object_xy = board.object_points()[:, :2].astype(np.float64)
    design = np.column_stack([object_xy, np.ones(len(object_xy))])
    affine, *_ = np.linalg.lstsq(design, points.astype(np.float64), rcond=None)
    return float(np.linalg.det(affine[:2, :2])) > 0.0


def _min_spacing(points: np.ndarray, pattern: tuple[int, int]) -> float:
    grid = points.reshape(pattern[1], pattern[0], 2)
    along_rows = np.linalg.norm(np.diff(grid, axis=1), axis=2)
    along_cols = np.linalg.norm(np.diff(grid, axis=0), axis=2)
    return float(min(along_rows.min(), along_cols.min()))


def _grid_is_regular(points: np.ndarray, board: BoardSpec) -> bool:
    """False when the detector put a point in the wrong grid cell.

    Along a row (and a column) of a grid seen in perspective, the second difference
    p[i-1] - 2 p[i] + p[i+1] is a small fraction of the spacing, even with lens
    distortion; a mis-assigned point makes it about one spacing. Grid detectors do
    mis-assign now and then at steep tilts, and such a view would bend the solve.
    """
    cols, rows = board.inner_corners
    grid = points.reshape(rows, cols, 2)
    row_step = 2 if board.kind == "acircles" else 1  # acircles: same x every other row
    checks = []
    if cols >= 3:
        checks.append((grid[:, :-2] - 2 * grid[:, 1:-1] + grid[:, 2:], np.diff(grid, axis=1)))
    if rows >= 2 * row_step + 1:
        g = grid[::1]
        second = g[: -2 * row_step] - 2 * g[row_step:-row_step] + g[2 * row_step :]
        checks.append((second, g[row_step:] - g[:-row_step]))
    for second, first in checks:
        spacing = np.median(np.linalg.norm(first, axis=-1))
        if spacing <= 0 or np.linalg.norm(second, axis=-1).max() > 0.25 * spacing:
            return False
    return True


def edge_width_px(image: np.ndarray, points: np.ndarray) -> float:
    """Median width (px) of the steepest edge near each point: contrast / max gradient.

    A step edge blurred by a Gaussian of sigma s has width contrast / slope = 2.5 s; a sharp
    edge sampled by pixels about 1 px. The patch around each point is sized from the
    spacing of the points, so it holds an edge of the pattern (square or circle rim).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(points) < 2:
        return float("inf")
    gap = np.linalg.norm(points[1:] - points[:-1], axis=1)
    spacing = float(np.median(gap[gap > 0])) if np.any(gap > 0) else 10.0
    half = int(np.clip(0.4 * spacing, 3, 20))
    smooth = image.astype(np.float32)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    magnitude = np.hypot(gx, gy)
    height, width = image.shape
    widths = []
    for u, v in points[:: max(1, len(points) // 40)]:
        j, i = int(round(u)), int(round(v))
        i0, i1, j0, j1 = max(i - half, 0), min(i + half + 1, height), max(j - half, 0), min(j + half + 1, width)
        if i1 - i0 < 3 or j1 - j0 < 3:
            continue
        patch = smooth[i0:i1, j0:j1]
        low, high = np.percentile(patch, [5, 95])
        slope = float(magnitude[i0:i1, j0:j1].max())
        if high - low > 10 and slope > 0:
            widths.append((high - low) / slope)
    return float(np.median(widths)) if widths else float("inf")


def diagnose_missing_board(images: list[np.ndarray], board: BoardSpec) -> str:
    """Why no image shows ``board``: a hint naming the board that is there, if any.

    Catches the usual off-by-one (squares counted instead of inner corners, rows and
    columns swapped) and, for ChArUco, markers of another dictionary or counts that do
    not fit the markers seen.
    """
    if board.kind == "charuco":
        return _diagnose_charuco(images, board)
    if board.kind == "aprilgrid":
        return _diagnose_aprilgrid(images, board)
    c, r = board.cols, board.rows
    candidates = [(c + 1, r + 1), (c - 1, r - 1), (r, c), (c + 1, r), (c, r + 1), (c - 1, r), (c, r - 1)]
    for image in images[:4]:
        for cols, rows in candidates:
            if min(cols, rows) < 2 or (cols, rows) == (c, r):
                continue
            alternative = board.with_counts(cols, rows)
            if detect_board(image, alternative) is not None:
                hint = f"{alternative.description} is there: use --board {alternative.text}"
                if board.kind == "chessboard":
                    hint += " (a chessboard spec counts inner corners, not squares)"
                return hint
    return ""


def _diagnose_charuco(images: list[np.ndarray], board: BoardSpec) -> str:
    wanted = board.charuco_board().getDictionary()
    detector = cv2.aruco.ArucoDetector(wanted)
    for image in images[:4]:
        _, ids, _ = detector.detectMarkers(image)
        if ids is not None and len(ids) >= 4:
            expected = board.cols * board.rows // 2
            if int(ids.max()) >= expected:
                return (
                    f"markers up to id {int(ids.max())} are there while {board.cols}x{board.rows} squares "
                    f"hold ids 0..{expected - 1}: check the square counts (ChArUco counts squares)"
                )
            return "its markers are there: check the square counts and the square/marker sizes"
    for name in ("DICT_4X4_50", "DICT_5X5_100", "DICT_6X6_250", "DICT_7X7_250", "DICT_APRILTAG_36h11", "DICT_ARUCO_ORIGINAL"):
        if name == board.dictionary:
            continue
        other = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)))
        for image in images[:2]:
            _, ids, _ = other.detectMarkers(image)
            if ids is not None and len(ids) >= 4:
                return f"markers of {name} are there: the dictionary in the spec is {board.dictionary}"
    return ""


def _diagnose_aprilgrid(images: list[np.ndarray], board: BoardSpec) -> str:
    from cubeloc.positioning.detection import TagDetector

    for image in images[:4]:
        found = _aprilgrid_detector().detect(image)
        if found and max(d.tag_id for d in found) >= board.cols * board.rows:
            return (f"tags up to id {max(d.tag_id for d in found)} are there while {board.cols}x{board.rows} tags "
                    f"hold ids 0..{board.cols * board.rows - 1}: check the tag counts (tagCols x tagRows)")
        if TagDetector(APRILGRID_FAMILY).detect(image):
            return (f"{APRILGRID_FAMILY} tags with a one-cell border are there, not an AprilGrid's two-cell ones: "
                    "calibrate with another board, or use them as a target")
    return ""
