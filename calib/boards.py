"""Calibration boards: the spec a technician types, the points on the board, its picture.

A board spec is ``KIND:COLSxROWS:SIZE[:MORE]`` (lengths in metres) or a YAML file:

==============================================  ==========================================
``charuco:11x8:0.030:0.022:DICT_5X5_100``       ChArUco: 11 x 8 **squares**, square side
                                                30 mm, marker side 22 mm, aruco dictionary
``chessboard:9x6:0.025``                        chessboard: 9 x 6 **inner corners** (where
                                                four squares meet; 10 x 7 squares), 25 mm
``circles:7x5:0.030[:0.015]``                   symmetric circle grid: 7 x 5 circles,
                                                30 mm centre to centre, [diameter]
``acircles:4x11:0.020[:0.016]``                 asymmetric circle grid (OpenCV's): 4 circles
                                                per row, 11 rows; rows 20 mm apart, circles
                                                in a row 40 mm apart, odd rows shifted 20 mm
``aprilgrid:6x6:0.088:0.3``                     Kalibr AprilGrid: 6 x 6 tag36h11 tags with
                                                two-cell borders, 88 mm each, 0.3 x 88 mm
                                                between them, black squares in the gaps
``kalibr:FILE.yaml``                            a Kalibr target file: ``aprilgrid``, or
                                                ``checkerboard`` (a chessboard)
==============================================  ==========================================

YAML board files carry the same fields::

    kind: charuco            # charuco | chessboard | circles | acircles
    cols: 11
    rows: 8
    size: 0.030              # square side / circle spacing, metres
    marker_size: 0.022       # charuco only
    dictionary: DICT_5X5_100 # charuco only
    diameter: 0.015          # circle grids only (optional)
    spacing: 0.3             # aprilgrid only: the gap between tags, a fraction of size

A Kalibr target file (``target_type: 'aprilgrid'`` or ``'checkerboard'``) is read as it is.

The board frame: origin at the top-left corner of the printed pattern, x to the right,
y down, z into the board (so a board facing the camera squarely has the identity rotation).
Chessboard and ChArUco corner (r, c) sits at ((c + 1) s, (r + 1) s), as OpenCV's
``CharucoBoard`` puts them; circle grids leave one spacing of white around the circles. An AprilGrid's points are its
tags' corners, tag t's corner k (as ``positioning.target.make_aprilgrid`` orders them) at
index 4 t + k, in Kalibr's layout turned to this frame; the pattern starts at the outer edge
of its corner squares.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from cubeloc.errors import InputFileError

KINDS = ("charuco", "chessboard", "circles", "acircles", "aprilgrid")
APRILGRID_FAMILY = "tag36h11"  # Kalibr's AprilGrids are tag36h11
APRILGRID_TAGS = 587  # ids in tag36h11
DEFAULT_BOARD = "charuco:11x8:0.030:0.022:DICT_5X5_100"

BOARD_HELP = (
    "calibration board: KIND:COLSxROWS:SIZE[:...] in metres, or a YAML board file. "
    "charuco:11x8:0.030:0.022:DICT_5X5_100 counts SQUARES (11 across, 8 down; square 30 mm, "
    "marker 22 mm); chessboard:9x6:0.025 counts INNER CORNERS, where four squares meet "
    "(a board of 10x7 squares; square 25 mm); circles:7x5:0.030[:DIAMETER] counts circles "
    "(30 mm centre to centre); acircles:4x11:0.020[:DIAMETER] is OpenCV's asymmetric grid "
    "(4 circles per row, 11 rows 20 mm apart, 40 mm between circles of a row); "
    "aprilgrid:6x6:0.088:0.3 is a Kalibr AprilGrid (6 x 6 tags of 88 mm, gaps 0.3 x 88 mm); "
    "kalibr:FILE.yaml reads a Kalibr target file (aprilgrid or checkerboard)"
)


class BoardSpecError(InputFileError):
    """A board spec or board file that cannot be understood."""


def _dictionary_names() -> list[str]:
    return sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_") and n.upper() == n)


@dataclass(frozen=True)
class BoardSpec:
    """One calibration board. Lengths in metres; ``cols`` x ``rows`` as the spec counts them."""

    kind: str
    cols: int
    rows: int
    size_m: float  # chessboard/charuco: square side; circles: centre spacing (acircles: row pitch)
    marker_m: float = 0.0  # charuco marker side
    dictionary: str = ""  # charuco aruco dictionary name
    diameter_m: float = 0.0  # circle grids: circle diameter
    spacing: float = 0.0  # aprilgrid: gap between tags / tag size (Kalibr's tagSpacing)

    @property
    def text(self) -> str:
        """The canonical spec string (what the report and the printed sheet show)."""
        head = f"{self.kind}:{self.cols}x{self.rows}:{self.size_m:g}"
        if self.kind == "charuco":
            return f"{head}:{self.marker_m:g}:{self.dictionary}"
        if self.kind in ("circles", "acircles"):
            return f"{head}:{self.diameter_m:g}"
        if self.kind == "aprilgrid":
            return f"{head}:{self.spacing:g}"
        return head

    @property
    def description(self) -> str:
        """Human words, e.g. 'a 9x6 chessboard' (inner corners) or 'an 11x8 ChArUco board'."""
        names = {
            "charuco": "ChArUco board",
            "chessboard": "chessboard",
            "circles": "circle grid",
            "acircles": "asymmetric circle grid",
            "aprilgrid": "AprilGrid",
        }
        article = "an" if str(self.cols).startswith("8") or self.cols in (11, 18) else "a"
        return f"{article} {self.cols}x{self.rows} {names[self.kind]}"

    @property
    def is_partial_ok(self) -> bool:
        """ChArUco corners and AprilGrid tags carry ids, so a view showing part of the board
        still counts."""
        return self.kind in ("charuco", "aprilgrid")

    def object_points(self) -> np.ndarray:
        """(N, 3) float32 board-frame points in the order detection reports them."""
        s = self.size_m
        if self.kind == "aprilgrid":
            return self._aprilgrid_points()
        if self.kind in ("charuco", "chessboard"):
            inner_cols, inner_rows = self.inner_corners
            r, c = np.mgrid[0:inner_rows, 0:inner_cols]
            xy = np.column_stack([(c.ravel() + 1) * s, (r.ravel() + 1) * s])
        elif self.kind == "circles":
            r, c = np.mgrid[0 : self.rows, 0 : self.cols]
            xy = np.column_stack([(c.ravel() + 1) * s, (r.ravel() + 1) * s])
        else:  # acircles: OpenCV's (2c + r % 2, r) layout, shifted one pitch in
            r, c = np.mgrid[0 : self.rows, 0 : self.cols]
            xy = np.column_stack([(2 * c.ravel() + r.ravel() % 2 + 1) * s, (r.ravel() + 1) * s])
        return np.column_stack([xy, np.zeros(len(xy))]).astype(np.float32)

    def aprilgrid_target(self):
        """The AprilGrid as a ``positioning.target.Target`` (its tags, in Kalibr's frame)."""
        from cubeloc.positioning.target import make_aprilgrid

        return make_aprilgrid(self.rows, self.cols, self.size_m, self.spacing, APRILGRID_FAMILY)

    def _aprilgrid_points(self) -> np.ndarray:
        # Kalibr's frame has the tags facing +z; this one looks at the print along +z: x
        # mirrored and z reversed (a rotation by 180 degrees about y), shifted by one gap.
        target = self.aprilgrid_target()
        corners = target.corners_of(target.ids)
        gap = self.spacing * self.size_m
        tags_width = self.cols * self.size_m + (self.cols - 1) * gap
        xy = np.column_stack([gap + tags_width - corners[:, 0], gap + corners[:, 1]])
        return np.column_stack([xy, np.zeros(len(xy))]).astype(np.float32)

    @property
    def inner_corners(self) -> tuple[int, int]:
        """(cols, rows) of the detected point grid (corners or circle centres)."""
        if self.kind == "charuco":
            return (self.cols - 1, self.rows - 1)
        return (self.cols, self.rows)

    @property
    def extent_m(self) -> tuple[float, float]:
        """(width, height) of the printed pattern including its built-in white border."""
        s = self.size_m
        if self.kind == "chessboard":
            return ((self.cols + 1) * s, (self.rows + 1) * s)
        if self.kind == "charuco":
            return (self.cols * s, self.rows * s)
        if self.kind == "circles":
            return ((self.cols + 1) * s, (self.rows + 1) * s)
        if self.kind == "aprilgrid":  # tags, the gaps between them and the squares outside
            gap = self.spacing * s
            return (self.cols * s + (self.cols + 1) * gap, self.rows * s + (self.rows + 1) * gap)
        return ((2 * self.cols + 1) * s, (self.rows + 1) * s)

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.size_m, self.marker_m, dictionary)

    def with_counts(self, cols: int, rows: int) -> BoardSpec:
        return BoardSpec(self.kind, cols, rows, self.size_m, self.marker_m, self.dictionary, self.diameter_m,
                         self.spacing)


def _number(text: str, what: str, spec: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise BoardSpecError(f"board {spec!r}: {what} {text!r} is not a number (metres, e.g. 0.025)") from None
    if not 0.0 < value < 5.0:
        raise BoardSpecError(f"board {spec!r}: {what} {value:g} m is out of range (metres, e.g. 0.025)")
    if value > 0.5:
        raise BoardSpecError(f"board {spec!r}: {what} {value:g} m is huge: lengths are in metres (25 mm = 0.025)")
    return value


def make_board(
    kind: str, cols: int, rows: int, size_m: float, *, marker_m: float = 0.0,
    dictionary: str = "", diameter_m: float = 0.0, spacing: float = 0.0, spec: str = "",
) -> BoardSpec:
    """A validated BoardSpec; ``spec`` names the input in error messages."""
    spec = spec or f"{kind}:{cols}x{rows}"
    if kind not in KINDS:
        raise BoardSpecError(f"board {spec!r}: unknown kind {kind!r}; known kinds: {', '.join(KINDS)}")
    minimum = 3 if kind in ("charuco", "chessboard") else 1 if kind == "aprilgrid" else 2
    if cols < minimum or rows < minimum or cols * rows > 2500:
        raise BoardSpecError(f"board {spec!r}: {cols}x{rows} is not a usable {kind} size")
    if kind == "charuco":
        names = _dictionary_names()
        if dictionary not in names:
            raise BoardSpecError(
                f"board {spec!r}: unknown dictionary {dictionary!r}; known: {', '.join(names)}"
            )
        if not 0.0 < marker_m < size_m:
            raise BoardSpecError(f"board {spec!r}: the marker ({marker_m:g} m) must be smaller than the square ({size_m:g} m)")
        markers = cols * rows // 2
        dict_size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList.shape[0]
        if markers > dict_size:
            raise BoardSpecError(f"board {spec!r}: needs {markers} markers but {dictionary} has only {dict_size}")
    elif kind in ("circles", "acircles"):
        if diameter_m == 0.0:
            diameter_m = size_m * (0.5 if kind == "circles" else 0.8)
        nearest = size_m if kind == "circles" else size_m * np.sqrt(2.0)
        if diameter_m >= 0.9 * nearest:
            raise BoardSpecError(f"board {spec!r}: circles of {diameter_m:g} m touch at a spacing of {nearest:.4g} m")
    elif kind == "aprilgrid":
        if cols * rows < 2 or cols * rows > APRILGRID_TAGS:
            raise BoardSpecError(f"board {spec!r}: {cols}x{rows} tags; an AprilGrid holds 2 to {APRILGRID_TAGS} "
                                 f"({APRILGRID_FAMILY})")
        if not 0.0 < spacing <= 2.0:
            raise BoardSpecError(f"board {spec!r}: spacing {spacing:g} must be the gap as a fraction of the tag "
                                 "size, in (0, 2] (Kalibr's tagSpacing, e.g. 0.3)")
    return BoardSpec(kind, cols, rows, size_m, marker_m, dictionary, diameter_m, spacing)


def parse_board(spec: str) -> BoardSpec:
    """A board from a spec string or a YAML board file (see the module docstring)."""
    spec = spec.strip()
    if spec.lower().startswith("kalibr:"):
        return load_board_file(spec[len("kalibr:"):])
    if spec.endswith((".yaml", ".yml")) or (os.sep in spec and ":" not in spec):
        return load_board_file(spec)
    parts = spec.split(":")
    kind = parts[0].lower()
    if kind not in KINDS:
        raise BoardSpecError(
            f"board {spec!r}: unknown kind {parts[0]!r}; expected one of {', '.join(KINDS)} "
            f"(e.g. {DEFAULT_BOARD} or chessboard:9x6:0.025), kalibr:FILE.yaml or a .yaml board file"
        )
    expected = {"charuco": (5, 5), "chessboard": (3, 3), "circles": (3, 4), "acircles": (3, 4),
                "aprilgrid": (4, 4)}[kind]
    if not expected[0] <= len(parts) <= expected[1]:
        example = {
            "charuco": DEFAULT_BOARD, "chessboard": "chessboard:9x6:0.025",
            "circles": "circles:7x5:0.030", "acircles": "acircles:4x11:0.020",
            "aprilgrid": "aprilgrid:6x6:0.088:0.3",
        }[kind]
        raise BoardSpecError(f"board {spec!r}: wrong number of fields for {kind}; e.g. {example}")
    match = re.fullmatch(r"(\d+)[xX](\d+)", parts[1])
    if not match:
        raise BoardSpecError(f"board {spec!r}: size {parts[1]!r} must be COLSxROWS, e.g. 9x6")
    cols, rows = int(match.group(1)), int(match.group(2))
    size_m = _number(parts[2], "size", spec)
    if kind == "charuco":
        marker_m = _number(parts[3], "marker size", spec)
        return make_board(kind, cols, rows, size_m, marker_m=marker_m, dictionary=parts[4].upper(), spec=spec)
    if kind == "aprilgrid":
        try:
            spacing = float(parts[3])
        except ValueError:
            raise BoardSpecError(f"board {spec!r}: spacing {parts[3]!r} is not a number (a fraction of the tag "
                                 "size, e.g. 0.3)") from None
        return make_board(kind, cols, rows, size_m, spacing=spacing, spec=spec)
    diameter = _number(parts[3], "diameter", spec) if len(parts) == 4 else 0.0
    return make_board(kind, cols, rows, size_m, diameter_m=diameter, spec=spec)


def load_board_file(path: str | os.PathLike[str]) -> BoardSpec:
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise BoardSpecError(f"{path}: board file not found (or give a spec like {DEFAULT_BOARD})") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise BoardSpecError(f"{path}: cannot read board file ({str(exc).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise BoardSpecError(f"{path}: a board file is a YAML mapping with kind, cols, rows, size")
    if "target_type" in doc:
        return _kalibr_board(doc, path)
    missing = [k for k in ("kind", "cols", "rows", "size") if k not in doc]
    if missing:
        raise BoardSpecError(f"{path}: missing {', '.join(missing)} (see `cubeloc calibrate --help`)")
    try:
        return make_board(
            str(doc["kind"]).lower(), int(doc["cols"]), int(doc["rows"]), float(doc["size"]),
            marker_m=float(doc.get("marker_size", 0.0)), dictionary=str(doc.get("dictionary", "")).upper(),
            diameter_m=float(doc.get("diameter", 0.0)), spacing=float(doc.get("spacing", 0.0)), spec=str(path),
        )
    except (TypeError, ValueError) as exc:
        raise BoardSpecError(f"{path}: {exc}") from None


def _kalibr_board(doc: dict, path: Path) -> BoardSpec:
    """A Kalibr target file as a board: an ``aprilgrid`` (read by the same parser as the
    AprilGrid targets) or a ``checkerboard`` (Kalibr counts its inner corners too)."""
    kind = doc.get("target_type")
    if kind == "aprilgrid":
        from cubeloc.positioning.target import parse_target

        grid = parse_target(doc, str(path)).grid
        return make_board("aprilgrid", grid.cols, grid.rows, grid.tag_size_m, spacing=grid.spacing, spec=str(path))
    if kind == "checkerboard":
        keys = ("targetCols", "targetRows", "rowSpacingMeters", "colSpacingMeters")
        missing = [k for k in keys if k not in doc]
        if missing:
            raise BoardSpecError(f"{path}: a Kalibr checkerboard needs {', '.join(missing)}")
        try:
            cols, rows = int(doc["targetCols"]), int(doc["targetRows"])
            row_m, col_m = float(doc["rowSpacingMeters"]), float(doc["colSpacingMeters"])
        except (TypeError, ValueError) as exc:
            raise BoardSpecError(f"{path}: {exc}") from None
        if not np.isclose(row_m, col_m, rtol=1e-6):
            raise BoardSpecError(f"{path}: rowSpacingMeters {row_m:g} and colSpacingMeters {col_m:g} differ; "
                                 "cubeloc calibrates with square chessboards")
        return make_board("chessboard", cols, rows, _number(str(row_m), "rowSpacingMeters", str(path)),
                          spec=str(path))
    raise BoardSpecError(f"{path}: Kalibr target_type {kind!r} is not read; cubeloc reads 'aprilgrid' and "
                         "'checkerboard' (or give --board circles:... for a circle grid)")


def board_texture(board: BoardSpec, px_per_m: float, margin_m: float = 0.0) -> np.ndarray:
    """The board as printed: (H, W) float32 in [0, 1] (0 black), with ``margin_m`` of white.

    Texel (i, j) covers board coordinates [j, j + 1) / px_per_m - margin_m (x) and the same
    for y, so its centre sits at ((j + 0.5) / px_per_m - margin_m, ...). Edges are
    anti-aliased by exact area coverage for squares and a one-texel ramp for circles.
    """
    width_m, height_m = board.extent_m
    width = int(round((width_m + 2 * margin_m) * px_per_m))
    height = int(round((height_m + 2 * margin_m) * px_per_m))
    x = (np.arange(width) + 0.5) / px_per_m - margin_m
    y = (np.arange(height) + 0.5) / px_per_m - margin_m
    if board.kind == "chessboard":
        return _squares_texture(board, x, y, px_per_m)
    if board.kind == "charuco":
        return _charuco_texture(board, px_per_m, margin_m, (width, height))
    if board.kind == "aprilgrid":
        return _aprilgrid_texture(board, x, y, px_per_m)
    centres = board.object_points()[:, :2].astype(np.float64)
    texture = np.ones((height, width), np.float32)
    radius = board.diameter_m / 2.0
    reach = radius + 2.0 / px_per_m
    for cx, cy in centres:
        j0, j1 = np.searchsorted(x, [cx - reach, cx + reach])
        i0, i1 = np.searchsorted(y, [cy - reach, cy + reach])
        xx, yy = np.meshgrid(x[j0:j1] - cx, y[i0:i1] - cy)
        distance_px = (np.hypot(xx, yy) - radius) * px_per_m
        np.minimum(texture[i0:i1, j0:j1], np.clip(0.5 + distance_px, 0.0, 1.0), out=texture[i0:i1, j0:j1])
    return texture


def _squares_texture(board: BoardSpec, x: np.ndarray, y: np.ndarray, px_per_m: float) -> np.ndarray:
    """Chessboard with the top-left square black; area-exact edge texels."""
    s = board.size_m
    n_x, n_y = board.cols + 1, board.rows + 1

    def coverage(coord: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
        # per texel: fraction inside the pattern, and fraction in an "odd" square
        half = 0.5 / px_per_m
        lo, hi = coord - half, coord + half
        edges = np.arange(count + 1) * s
        inside = np.zeros_like(coord)
        odd = np.zeros_like(coord)
        for k in range(count):
            overlap = np.clip(np.minimum(hi, edges[k + 1]) - np.maximum(lo, edges[k]), 0, None) * px_per_m
            inside += overlap
            if k % 2:
                odd += overlap
        return inside, odd

    in_x, odd_x = coverage(x, n_x)
    in_y, odd_y = coverage(y, n_y)
    even_x, even_y = in_x - odd_x, in_y - odd_y
    # black where (col + row) is even: even*even + odd*odd
    black = np.outer(even_y, even_x) + np.outer(odd_y, odd_x)
    return (1.0 - black).astype(np.float32)


def _coverage(coord: np.ndarray, edges: np.ndarray, px_per_m: float) -> np.ndarray:
    """(texels, len(edges) - 1): the fraction of each texel (centres ``coord``, one texel
    wide) inside each interval between consecutive ``edges``."""
    half = 0.5 / px_per_m
    lo, hi = coord[:, None] - half, coord[:, None] + half
    return np.clip(np.minimum(hi, edges[None, 1:]) - np.maximum(lo, edges[None, :-1]), 0, None) * px_per_m


def _aprilgrid_texture(board: BoardSpec, x: np.ndarray, y: np.ndarray, px_per_m: float) -> np.ndarray:
    """An AprilGrid with area-exact edge texels: each tag's cells (two-cell border) where its
    corners put them, a black square of one gap at every corner of every tag."""
    from cubeloc.positioning.tag_bits import tag_cells

    points = board.object_points().astype(np.float64).reshape(-1, 4, 3)[:, :, :2]
    s, gap = board.size_m, board.spacing * board.size_m
    black = np.zeros((len(y), len(x)))
    for tag_id, (tl, tr, _, bl) in enumerate(points):
        cells = 1.0 - tag_cells(APRILGRID_FAMILY, tag_id, 2)  # 1 where black
        n = len(cells)
        # the tag's own axes (right, down) in this frame are signed unit axes: lay the
        # cells out in this frame's column / row order
        right, down = np.rint((tr - tl) / s).astype(int), np.rint((bl - tl) / s).astype(int)
        laid = cells.T if right[1] != 0 else cells  # laid[row along y, col along x]
        if (right if right[0] != 0 else down)[0] < 0:
            laid = laid[:, ::-1]
        if (down if down[1] != 0 else right)[1] < 0:
            laid = laid[::-1, :]
        x0, y0 = min(tl[0], tr[0], bl[0]), min(tl[1], tr[1], bl[1])
        cover_x = _coverage(x, x0 + np.arange(n + 1) * s / n, px_per_m)
        cover_y = _coverage(y, y0 + np.arange(n + 1) * s / n, px_per_m)
        black += cover_y @ laid @ cover_x.T
    pitch = s + gap  # the squares start every pitch from the pattern's edge, one gap wide
    for left in np.arange(board.cols + 1) * pitch:
        for top in np.arange(board.rows + 1) * pitch:
            black += np.outer(_coverage(y, np.array([top, top + gap]), px_per_m)[:, 0],
                              _coverage(x, np.array([left, left + gap]), px_per_m)[:, 0])
    return (1.0 - np.clip(black, 0.0, 1.0)).astype(np.float32)


def _charuco_texture(board: BoardSpec, px_per_m: float, margin_m: float, size: tuple[int, int]) -> np.ndarray:
    # OpenCV draws the board; whole pixels per square keep its edges exact, then the
    # image is resampled to the requested texel pitch.
    px_per_square = max(8, int(round(board.size_m * px_per_m)))
    drawn = board.charuco_board().generateImage((board.cols * px_per_square, board.rows * px_per_square), marginSize=0, borderBits=1)
    scale = px_per_square / board.size_m  # drawn texels per metre
    width, height = size
    # affine from output texel centre to drawn texel centre
    a = scale / px_per_m
    offset = (0.5 / px_per_m - margin_m) * scale - 0.5
    matrix = np.array([[a, 0.0, offset], [0.0, a, offset]])
    flags = cv2.INTER_AREA if a > 1.0 else cv2.INTER_LINEAR
    texture = cv2.warpAffine(
        drawn.astype(np.float32) / 255.0, matrix, (width, height),
        flags=flags | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=1.0,
    )
    return texture
