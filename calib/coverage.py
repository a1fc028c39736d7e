"""How well the accepted views cover what calibration needs, and what to do next.

After ROS ``camera_calibration``: each view is scored by X and Y (where the board sits in
the image), size (how much of the image it fills) and skew (how tilted it is), each in
[0, 1]. Progress on a score is the spread of the accepted views over a target range.
A view is accepted only when it is sharp and adds something: it is far enough from
every accepted view in (X, Y, size, skew), or it puts points into a part of the image no
view has reached yet. The image is cut into 3 x 3 cells for that; empty corner cells are
what technicians most often miss, and what bends distortion estimates most.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from cubeloc.calib.boards import BoardSpec
from cubeloc.calib.detect import Detection

SCORES = ("X", "Y", "size", "skew")
TARGET_SPREAD = (0.7, 0.7, 0.4, 0.5)  # ROS camera_calibration's param_ranges
MIN_DISTANCE = 0.2  # ROS: a new view must differ by this much (sum of |score changes|)
CELL_NAMES = (
    ("top-left corner", "top edge", "top-right corner"),
    ("left edge", "centre", "right edge"),
    ("bottom-left corner", "bottom edge", "bottom-right corner"),
)
CORNER_CELLS = ((0, 0), (0, 2), (2, 0), (2, 2))
MIN_POINTS_IN_CELL = 3


@dataclass(frozen=True)
class ViewScore:
    x: float
    y: float
    size: float
    skew: float
    cells: frozenset[tuple[int, int]]  # (row, col) of the 3 x 3 cells holding points

    def as_tuple(self) -> tuple[float, float, float, float]:
        return (self.x, self.y, self.size, self.skew)


def _angle(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """Angle at b between ba and bc."""
    ab, cb = a - b, c - b
    cosine = float(ab @ cb / (np.linalg.norm(ab) * np.linalg.norm(cb)))
    return math.acos(max(-1.0, min(1.0, cosine)))


def score_view(detection: Detection, board: BoardSpec, image_size: tuple[int, int]) -> ViewScore:
    """ROS-style scores of one view. For partial ChArUco views the board's outline is
    found through the homography of the points seen, so a part counts as its board."""
    width, height = image_size
    object_xy = board.object_points()[:, :2].astype(np.float64)
    lo, hi = object_xy.min(axis=0), object_xy.max(axis=0)
    outline = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    homography, _ = cv2.findHomography(detection.object_points[:, :2].astype(np.float64), detection.image_points.astype(np.float64))
    if homography is None:
        corners = np.array(cv2.boxPoints(cv2.minAreaRect(detection.image_points.astype(np.float32))), dtype=np.float64)
    else:
        corners = cv2.perspectiveTransform(outline.reshape(-1, 1, 2), homography).reshape(-1, 2)
    x, y = corners[:, 0], corners[:, 1]
    area = 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))
    border = math.sqrt(area)
    clamp = lambda value: min(1.0, max(0.0, value))  # noqa: E731 - a one-liner reads best here
    score_x = clamp((float(x.mean()) - border / 2) / max(width - border, 1.0))
    score_y = clamp((float(y.mean()) - border / 2) / max(height - border, 1.0))
    size = math.sqrt(area / (width * height))
    skew = min(1.0, 2.0 * abs(math.pi / 2 - _angle(corners[0], corners[1], corners[2])))
    points = detection.image_points
    cols = np.clip((points[:, 0] / width * 3).astype(int), 0, 2)
    rows = np.clip((points[:, 1] / height * 3).astype(int), 0, 2)
    counts = np.zeros((3, 3), int)
    np.add.at(counts, (rows, cols), 1)
    cells = frozenset((int(r), int(c)) for r, c in zip(*np.nonzero(counts >= MIN_POINTS_IN_CELL), strict=True))
    return ViewScore(score_x, score_y, min(1.0, size), skew, cells)


@dataclass(frozen=True)
class Offer:
    accepted: bool
    reason: str  # why (accepted: what it added; refused: what is wrong)
    score: ViewScore | None = None


class CoverageTracker:
    """The accepted views' coverage, for a live capture. Pure: detections in, advice out."""

    def __init__(self, board: BoardSpec, image_size: tuple[int, int], *, min_views: int = 15, max_views: int = 40) -> None:
        self.board = board
        self.image_size = image_size
        self.min_views = min_views
        self.max_views = max_views
        self.scores: list[ViewScore] = []

    def offer(self, detection: Detection | None) -> Offer:
        """Score a new view; accept it (and remember it) only if it is sharp and new."""
        if detection is None:
            return Offer(False, f"{self.board.description} not in view")
        if not detection.is_sharp:
            return Offer(False, f"blurred (edges {detection.edge_width_px:.1f} px wide): hold the board still")
        score = score_view(detection, self.board, self.image_size)
        new_cells = score.cells - self.covered_cells
        if not self.scores:
            self.scores.append(score)
            return Offer(True, "first view", score)
        distance = min(sum(abs(a - b) for a, b in zip(score.as_tuple(), s.as_tuple(), strict=True)) for s in self.scores)
        if new_cells:
            reason = "reaches the " + ", ".join(sorted(CELL_NAMES[r][c] for r, c in new_cells))
        elif distance > MIN_DISTANCE:
            reason = f"new position/size/tilt (distance {distance:.2f})"
        else:
            return Offer(False, "too like an accepted view: move or tilt the board", score)
        self.scores.append(score)
        return Offer(True, reason, score)

    @property
    def covered_cells(self) -> frozenset[tuple[int, int]]:
        cells: set[tuple[int, int]] = set()
        for s in self.scores:
            cells |= s.cells
        return frozenset(cells)

    def progress(self) -> dict[str, float]:
        """Per score, the spread of the accepted views over its target range, in [0, 1]."""
        if not self.scores:
            return dict.fromkeys(SCORES, 0.0)
        values = np.array([s.as_tuple() for s in self.scores])
        spread = values.max(axis=0) - values.min(axis=0)
        # skew: what matters is reaching tilted views at all, so count from zero
        spread[3] = values[:, 3].max()
        return {name: float(min(1.0, spread[i] / TARGET_SPREAD[i])) for i, name in enumerate(SCORES)}

    @property
    def done(self) -> bool:
        if len(self.scores) >= self.max_views:
            return True
        return len(self.scores) >= self.min_views and not self.missing()

    def missing(self) -> list[str]:
        """What the views still lack, as instructions, most important first."""
        advice = []
        empty = [CELL_NAMES[r][c] for r, c in CORNER_CELLS if (r, c) not in self.covered_cells]
        if empty:
            advice.append(f"{' and '.join(empty)} empty" if len(empty) < 4 else "fill the image corners")
        progress = self.progress()
        if progress["skew"] < 1.0:
            advice.append("tilt the board")
        if progress["size"] < 1.0:
            sizes = [s.size for s in self.scores] or [0.0]
            advice.append("closer" if max(sizes) < 0.55 else "farther")
        if self.scores:
            xs, ys = [s.x for s in self.scores], [s.y for s in self.scores]
            if progress["X"] < 1.0:
                advice.append("to the left edge" if min(xs) > 1.0 - max(xs) else "to the right edge")
            if progress["Y"] < 1.0:
                advice.append("to the top edge" if min(ys) > 1.0 - max(ys) else "to the bottom edge")
        if len(self.scores) < self.min_views:
            advice.append(f"more views ({len(self.scores)} of {self.min_views})")
        return advice

    def status_line(self, width: int = 10) -> str:
        """One terminal line: views, a bar per score, and the next thing to do."""
        bars = []
        for name, value in self.progress().items():
            filled = int(value * width)  # floor: a full bar means done
            bars.append(f"{name} [{'#' * filled}{'-' * (width - filled)}]")
        todo = self.missing()
        tail = "; ".join(todo[:3]) if todo else "coverage good: finishing"
        return f"views {len(self.scores):2d}  " + " ".join(bars) + f"  | {tail}"
