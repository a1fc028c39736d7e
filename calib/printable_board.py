"""A calibration board as a printable page at true scale, with its spec printed on it.

The page is the smallest ISO A size (portrait or landscape) that holds the board with
margins; below the board go the spec to type into ``cubeloc calibrate --board``, a
100 mm bar to check the print scale, and the square size to measure. The page is
black and white only (1 bit per pixel when saved), so no printer or PDF viewer
smooths the edges, and the PDF is written at the page's resolution, so printing at
"actual size" gives the board's true dimensions.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import cv2
import numpy as np

from cubeloc.calib.boards import BoardSpec, BoardSpecError, board_texture

PAGES_M = {"A4": (0.210, 0.297), "A3": (0.297, 0.420), "A2": (0.420, 0.594), "A1": (0.594, 0.841), "A0": (0.841, 1.189)}
MARGIN_M = 0.010  # printers cannot print to the edge
TEXT_BAND_M = 0.030  # room under the board for the spec and the scale bar
M_PER_INCH = 0.0254


@dataclass(frozen=True)
class BoardSheet:
    image: np.ndarray  # (H, W) uint8, 0 or 255
    page: str  # e.g. "A4 landscape"
    dpi: float


def choose_page(board: BoardSpec) -> tuple[str, tuple[float, float]]:
    """The smallest A page (name, (width, height) m) holding the board, margins and text."""
    width_m, height_m = board.extent_m
    need_w, need_h = width_m + 2 * MARGIN_M, height_m + 2 * MARGIN_M + TEXT_BAND_M
    for name, (short, long) in PAGES_M.items():
        for orientation, size in (("portrait", (short, long)), ("landscape", (long, short))):
            if need_w <= size[0] and need_h <= size[1]:
                return f"{name} {orientation}", size
    raise BoardSpecError(
        f"board {board.text}: {width_m * 1000:.0f} x {height_m * 1000:.0f} mm does not fit on A0; "
        "use fewer or smaller squares"
    )


def board_sheet(board: BoardSpec, dpi: float = 300.0) -> BoardSheet:
    """The page image: the board centred at true scale, the spec and a 100 mm bar below."""
    page_name, (page_w, page_h) = choose_page(board)
    px_per_m = dpi / M_PER_INCH
    width, height = int(round(page_w * px_per_m)), int(round(page_h * px_per_m))
    page = np.full((height, width), 255, np.uint8)
    texture = board_texture(board, px_per_m)
    pattern = np.where(texture >= 0.5, 255, 0).astype(np.uint8)
    ph, pw = pattern.shape
    left = (width - pw) // 2
    top = max(int(round(MARGIN_M * px_per_m)), (height - ph - int(TEXT_BAND_M * px_per_m)) // 2)
    page[top : top + ph, left : left + pw] = pattern

    # text and scale bar, in the band under the board
    line_height = int(round(0.004 * px_per_m))
    scale = line_height / 22.0  # Hershey simplex capitals are about 22 px tall at scale 1
    thickness = max(1, int(round(scale * 1.5)))
    y = top + ph + int(round(0.004 * px_per_m))
    pitch = {"charuco": "square", "chessboard": "square", "aprilgrid": "tag"}.get(board.kind, "spacing")
    lines = [
        f"--board {board.text}",
        f"{board.description}, {pitch} {board.size_m * 1000:.1f} mm",
        "print at 100 % (actual size) and glue flat; the bar below must be 100 mm",
    ]
    for text in lines:
        y += line_height
        cv2.putText(page, text, (left, y), cv2.FONT_HERSHEY_SIMPLEX, scale, 0, thickness, cv2.LINE_8)
        y += line_height // 2
    mm = px_per_m / 1000.0
    bar_top = y + int(round(4 * mm))
    bar_height = max(2, int(round(1 * mm)))
    page[bar_top : bar_top + bar_height, left : left + int(round(100 * mm))] = 0
    for tick_mm in range(0, 101, 10):
        x = left + int(round(tick_mm * mm))
        tick = int(round((3 if tick_mm % 50 == 0 else 2) * mm))
        page[bar_top - tick : bar_top + bar_height, max(x - thickness // 2, 0) : x + thickness // 2 + 1] = 0
    page = np.where(page >= 128, 255, 0).astype(np.uint8)  # strictly black and white
    return BoardSheet(page, page_name, dpi)


def sheet_bytes(sheet: BoardSheet, file_format: str) -> bytes:
    """The sheet as a PDF (true scale at ``sheet.dpi``) or a PNG (with its DPI)."""
    from PIL import Image

    image = Image.fromarray(sheet.image).convert("1", dither=Image.Dither.NONE)
    buffer = io.BytesIO()
    if file_format == "pdf":
        image.save(buffer, format="PDF", resolution=sheet.dpi)
    else:
        image.save(buffer, format="PNG", dpi=(sheet.dpi, sheet.dpi))
    return buffer.getvalue()
