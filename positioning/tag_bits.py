"""The known edges inside a tag: every boundary between a black and a white cell.

A tag36h11 tag is an 8 x 8 grid of cells (a one-cell black border around 6 x 6 code bits)
on a white margin; with a two-cell border (a Kalibr AprilGrid) 10 x 10. Its 3-D corners fix every cell corner, so each boundary between cells
of different colour is a straight 3-D segment known as well as the corners are: tens of
extra edges per tag where the corners-only baseline uses four. The bit pattern is the
family's code, as OpenCV's ``aruco`` module generates it (the same drawing the printable
cube and the synthetic camera use: ``positioning/printable.py``, ``fakes/scene.py``).

Cells are indexed ``bits[row, col]``: row 0 at the top of the tag printed upright, col 0 on
the left, so cell (row, col) spans ``TL + col/N * (TR - TL) + row/N * (BL - TL)`` to one
cell further along both.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

ARUCO_DICTIONARIES = {
    "tag36h11": cv2.aruco.DICT_APRILTAG_36h11,
    "tag36h10": cv2.aruco.DICT_APRILTAG_36h10,
    "tag25h9": cv2.aruco.DICT_APRILTAG_25h9,
    "tag16h5": cv2.aruco.DICT_APRILTAG_16h5,
}


@functools.lru_cache(maxsize=128)
def tag_cells(family: str, tag_id: int, border_bits: int = 1) -> np.ndarray:
    """(N, N) uint8 cells of a tag including its black border of ``border_bits`` cells:
    1 white, 0 black."""
    dictionary = cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARIES[family])
    cells = dictionary.markerSize + 2 * border_bits
    image = cv2.aruco.generateImageMarker(dictionary, tag_id, cells, borderBits=border_bits)
    bits = (image > 127).astype(np.uint8)
    bits.setflags(write=False)
    return bits


@dataclass(frozen=True)
class TagEdges:
    """Straight black/white boundaries of one tag, in cell units of the tag's own grid.

    ``start`` and ``end`` (K, 2) are (col, row) grid coordinates (0..N) of each run of
    collinear cell edges with the same colours on each side; ``bright`` (K, 2) is the unit
    grid direction from its black side to its white side. ``outer`` marks the four
    border edges (black border against the white margin).
    """

    cells: int
    start: np.ndarray
    end: np.ndarray
    bright: np.ndarray
    outer: np.ndarray


@functools.lru_cache(maxsize=128)
def tag_edges(family: str, tag_id: int, border_bits: int = 1) -> TagEdges:
    bits = tag_cells(family, tag_id, border_bits)
    n = bits.shape[0]
    padded = np.ones((n + 2, n + 2), np.uint8)  # the white margin all round
    padded[1:-1, 1:-1] = bits
    starts, ends, brights, outer = [], [], [], []
    # Vertical lines col = j (between padded columns j and j+1), runs along rows.
    for j in range(n + 1):
        run_start, run_key = None, None
        for row in range(n + 1):
            key = None
            if row < n:
                left, right = padded[row + 1, j], padded[row + 1, j + 1]
                key = (left, right) if left != right else None
            if key != run_key:
                if run_key is not None:
                    starts.append((j, run_start))
                    ends.append((j, row))
                    brights.append((1.0, 0.0) if run_key[1] == 1 else (-1.0, 0.0))
                    outer.append(j in (0, n))
                run_start, run_key = row, key
    # Horizontal lines row = i, runs along columns.
    for i in range(n + 1):
        run_start, run_key = None, None
        for col in range(n + 1):
            key = None
            if col < n:
                above, below = padded[i, col + 1], padded[i + 1, col + 1]
                key = (above, below) if above != below else None
            if key != run_key:
                if run_key is not None:
                    starts.append((run_start, i))
                    ends.append((col, i))
                    brights.append((0.0, 1.0) if run_key[1] == 1 else (0.0, -1.0))
                    outer.append(i in (0, n))
                run_start, run_key = col, key
    edges = TagEdges(n, np.array(starts, np.float64), np.array(ends, np.float64), np.array(brights),
                     np.array(outer, bool))
    for array in (edges.start, edges.end, edges.bright, edges.outer):
        array.setflags(write=False)
    return edges


def grid_to_world(corners: np.ndarray, cells: int, grid: np.ndarray) -> np.ndarray:
    """World points (K, 3) of grid coordinates (K, 2) = (col, row) on a tag with corners
    (4, 3) TL TR BR BL (a planar square: bilinear is exact)."""
    u, v = grid[:, 0:1] / cells, grid[:, 1:2] / cells
    tl, tr, br, bl = corners
    return (1 - u) * (1 - v) * tl + u * (1 - v) * tr + u * v * br + (1 - u) * v * bl
