"""Printable cube faces and the pictures that explain the target (Pillow images, no files).

A technician builds the cube the target file describes from these: one page per face at
true physical scale (the tag, its id, which edge is up, cut marks, a 100 mm check bar),
and, when the whole cube fits on an A3 sheet, its unfolded net with fold lines. The
``cubeloc generate cube`` verb writes them; docs/target.md shows the layout picture.

Tags are drawn from OpenCV's AprilTag dictionaries, cell by cell: ``generateImageMarker``
is the definition of "upright" and of the corner order in interfaces.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from cubeloc.positioning.detection import FAMILY_CELLS
from cubeloc.positioning.target import CUBE_FACES, Target

MM_PER_INCH = 25.4
PAGE_SIZES_MM = {"A4": (210.0, 297.0), "A3": (297.0, 420.0)}
PAGE_MARGIN_MM = 28.0  # above a face: room for the "UP" line and cut marks
PAGE_SIDE_MARGIN_MM = 14.0  # beside a face: cut marks only (so 18 cm faces fit on A4)
LEGEND_MM = 60.0  # below a face: the legend and the check bar
CUT_MARK_MM, CUT_GAP_MM = 8.0, 2.0
ARUCO_DICTS = {
    "tag36h11": cv2.aruco.DICT_APRILTAG_36h11,
    "tag36h10": cv2.aruco.DICT_APRILTAG_36h10,
    "tag25h9": cv2.aruco.DICT_APRILTAG_25h9,
    "tag16h5": cv2.aruco.DICT_APRILTAG_16h5,
}
# Where each face sits in the unfolded net (column, row), rows downwards; see target.py.
NET_CELLS = {"+x": (0, 1), "+y": (1, 1), "-x": (2, 1), "-y": (3, 1), "+z": (0, 0), "-z": (0, 2)}
# The world direction of each face's "up", for the legend.
UP_WORDS = {"+x": "world +z", "+y": "world +z", "-x": "world +z", "-y": "world +z", "+z": "world -x", "-z": "world +x"}


@dataclass(frozen=True)
class FaceSheet:
    """One printable page: a cube face at true scale."""

    tag_id: int
    face: str  # cube face name (+x, +y, -x, -y, +z, -z)
    page: Image.Image  # mode "L", ``dpi`` in its info
    face_image: Image.Image  # the face square alone (side x side), same dpi
    page_name: str  # A4, A3 or "custom"


def mm_to_px(mm: float, dpi: float) -> int:
    return int(round(mm / MM_PER_INCH * dpi))


def font(size_px: int) -> ImageFont.ImageFont:
    return ImageFont.load_default(size=max(8, size_px))


def tag_image(family: str, tag_id: int, size_px: int) -> Image.Image:
    """The tag (outer black border included, no white quiet zone), upright, ``size_px``
    square, sharp cells (nearest neighbour)."""
    dictionary = cv2.aruco.getPredefinedDictionary(ARUCO_DICTS[family])
    cells = FAMILY_CELLS[family]
    marker = cv2.aruco.generateImageMarker(dictionary, tag_id, cells)
    return Image.fromarray(marker).resize((size_px, size_px), Image.NEAREST)


def face_image(target: Target, tag_id: int, dpi: float) -> Image.Image:
    """A face of the cube: white square of the cube's side with the tag centred."""
    cube = target.cube
    side_px = mm_to_px(cube.side_m * 1000, dpi)
    tag_px = mm_to_px(cube.tag_size_m * 1000, dpi)
    face = Image.new("L", (side_px, side_px), 255)
    offset = (side_px - tag_px) // 2
    face.paste(tag_image(target.family, tag_id, tag_px), (offset, offset))
    face.info["dpi"] = (dpi, dpi)
    return face


def _page_size(side_mm: float) -> tuple[str, tuple[float, float]]:
    need_w, need_h = side_mm + 2 * PAGE_SIDE_MARGIN_MM, side_mm + PAGE_MARGIN_MM + LEGEND_MM
    for name, (width, height) in PAGE_SIZES_MM.items():
        if need_w <= width and need_h <= height:
            return name, (width, height)
    return "custom", (need_w, need_h)


def _cut_marks(draw: ImageDraw.ImageDraw, box: tuple[int, int, int, int], dpi: float) -> None:
    """Short lines outside each corner on the extensions of the face's edges."""
    x0, y0, x1, y1 = box
    gap, length = mm_to_px(CUT_GAP_MM, dpi), mm_to_px(CUT_MARK_MM, dpi)
    width = max(1, mm_to_px(0.2, dpi))
    for x, sx in ((x0, -1), (x1, 1)):
        for y, sy in ((y0, -1), (y1, 1)):
            draw.line([(x + sx * gap, y), (x + sx * (gap + length), y)], fill=0, width=width)
            draw.line([(x, y + sy * gap), (x, y + sy * (gap + length))], fill=0, width=width)


def _scale_bar(draw: ImageDraw.ImageDraw, origin: tuple[int, int], dpi: float, text_px: int) -> None:
    x, y = origin
    length = mm_to_px(100.0, dpi)
    tick = mm_to_px(2.0, dpi)
    width = max(1, mm_to_px(0.3, dpi))
    draw.line([(x, y), (x + length, y)], fill=0, width=width)
    for end in (x, x + length):
        draw.line([(end, y - tick), (end, y + tick)], fill=0, width=width)
    draw.text((x + length + tick * 2, y - text_px // 2), "100 mm: measure after printing", fill=0, font=font(text_px))


def face_sheets(target: Target, dpi: float = 300.0) -> list[FaceSheet]:
    """One page per cube face at true scale, in the order of ``cube.ids``."""
    if target.cube is None:
        raise ValueError("face sheets need a cube target (the 'cube:' shorthand)")
    cube = target.cube
    side_mm = cube.side_m * 1000
    page_name, (page_w_mm, page_h_mm) = _page_size(side_mm)
    text_px = mm_to_px(3.5, dpi)
    sheets = []
    for tag_id, (face_name, _, _) in zip(cube.ids, CUBE_FACES, strict=True):
        face = face_image(target, tag_id, dpi)
        page = Image.new("L", (mm_to_px(page_w_mm, dpi), mm_to_px(page_h_mm, dpi)), 255)
        x0 = (page.width - face.width) // 2
        y0 = mm_to_px(PAGE_MARGIN_MM, dpi)
        page.paste(face, (x0, y0))
        draw = ImageDraw.Draw(page)
        _cut_marks(draw, (x0, y0, x0 + face.width, y0 + face.height), dpi)
        up_text = f"UP ({UP_WORDS[face_name]})"
        draw.text((page.width // 2, y0 - mm_to_px(6, dpi)), up_text, fill=0, font=font(text_px), anchor="ms")
        lines = [
            f"{target.family} id {tag_id}  -  cube face {face_name}  -  this edge up: {UP_WORDS[face_name]}",
            f"face {side_mm:.1f} mm (cut at the marks), tag {cube.tag_size_m * 1000:.1f} mm "
            "(outer edge of the black border)",
            "print at 100 % / actual size, no fit-to-page; glue flat, edges on the cube's edges",
        ]
        y = y0 + face.height + mm_to_px(14, dpi)
        for line in lines:
            draw.text((x0, y), line, fill=0, font=font(text_px))
            y += int(text_px * 1.5)
        _scale_bar(draw, (x0, y + text_px), dpi, text_px)
        page.info["dpi"] = (dpi, dpi)
        sheets.append(FaceSheet(tag_id, face_name, page, face, page_name))
    return sheets


def _dashed(draw: ImageDraw.ImageDraw, a: tuple[int, int], b: tuple[int, int], dash: int, width: int) -> None:
    (xa, ya), (xb, yb) = a, b
    length = max(abs(xb - xa), abs(yb - ya))
    for start in range(0, length, 2 * dash):
        end = min(start + dash, length)
        draw.line([(xa + (xb - xa) * start // length, ya + (yb - ya) * start // length),
                   (xa + (xb - xa) * end // length, ya + (yb - ya) * end // length)], fill=0, width=width)


def _net_edges(face_px: int, origin: tuple[int, int]) -> tuple[list, list]:
    """(cut edges, fold edges) of the net: an edge shared by two faces is a fold."""
    ox, oy = origin
    counts: dict[tuple, int] = {}
    for column, row in NET_CELLS.values():
        x, y = ox + column * face_px, oy + row * face_px
        corners = [(x, y), (x + face_px, y), (x + face_px, y + face_px), (x, y + face_px)]
        for k in range(4):
            edge = tuple(sorted((corners[k], corners[(k + 1) % 4])))
            counts[edge] = counts.get(edge, 0) + 1
    cuts = [e for e, n in counts.items() if n == 1]
    folds = [e for e, n in counts.items() if n == 2]
    return cuts, folds


def net_sheet(target: Target, dpi: float = 300.0) -> Image.Image | None:
    """The whole cube unfolded on one A3 landscape page at true scale, with solid cut lines
    and dashed fold lines; None when the cube is too big for A3."""
    cube = target.cube
    if cube is None:
        return None
    side_mm = cube.side_m * 1000
    page_w_mm, page_h_mm = PAGE_SIZES_MM["A3"][1], PAGE_SIZES_MM["A3"][0]
    if 4 * side_mm + 20 > page_w_mm or 3 * side_mm + 30 > page_h_mm:
        return None
    page = Image.new("L", (mm_to_px(page_w_mm, dpi), mm_to_px(page_h_mm, dpi)), 255)
    face_px = mm_to_px(side_mm, dpi)
    origin = ((page.width - 4 * face_px) // 2, mm_to_px(10, dpi))
    for tag_id, (face_name, _, _) in zip(cube.ids, CUBE_FACES, strict=True):
        column, row = NET_CELLS[face_name]
        page.paste(face_image(target, tag_id, dpi), (origin[0] + column * face_px, origin[1] + row * face_px))
    draw = ImageDraw.Draw(page)
    width = max(1, mm_to_px(0.2, dpi))
    cuts, folds = _net_edges(face_px, origin)
    for a, b in cuts:
        draw.line([a, b], fill=0, width=width)
    for a, b in folds:
        _dashed(draw, a, b, mm_to_px(3, dpi), width)
    text_px = mm_to_px(3.5, dpi)
    legend = (f"{target.family} cube, face {side_mm:.1f} mm, tag {cube.tag_size_m * 1000:.1f} mm: "
              "cut along solid lines, fold along dashed lines, print at 100 %")
    draw.text((origin[0], origin[1] + 3 * face_px + mm_to_px(6, dpi)), legend, fill=0, font=font(text_px))
    page.info["dpi"] = (dpi, dpi)
    return page


def _arrow(draw: ImageDraw.ImageDraw, start, end, colour, width: int) -> None:
    draw.line([start, end], fill=colour, width=width)
    direction = np.subtract(end, start, dtype=float)
    direction /= np.linalg.norm(direction)
    normal = np.array([-direction[1], direction[0]])
    head = 4 * width
    tip = np.array(end, dtype=float)
    draw.polygon([tuple(tip), tuple(tip - head * direction + head * 0.6 * normal),
                  tuple(tip - head * direction - head * 0.6 * normal)], fill=colour)


def cube_layout_picture(target: Target, face_px: int = 220) -> Image.Image:
    """The unfolded cube for docs/target.md: ids, face names, which way is up, world axes and
    the origin, drawn from the same tags the printer gets."""
    cube = target.cube
    if cube is None:
        raise ValueError("the layout picture needs a cube target")
    pad = 40
    canvas = Image.new("RGB", (4 * face_px + 2 * pad, 3 * face_px + 2 * pad + 70), "white")
    draw = ImageDraw.Draw(canvas)
    label_font, small_font = font(face_px // 9), font(face_px // 13)
    for tag_id, (face_name, _, _) in zip(cube.ids, CUBE_FACES, strict=True):
        column, row = NET_CELLS[face_name]
        x, y = pad + column * face_px, pad + row * face_px
        side_px = face_px
        tag_px = int(round(face_px * cube.tag_size_m / cube.side_m))
        off = (side_px - tag_px) // 2
        canvas.paste(tag_image(target.family, tag_id, tag_px).convert("RGB"), (x + off, y + off))
        draw.rectangle([x, y, x + face_px, y + face_px], outline=(90, 90, 90), width=2)
        draw.rectangle([x + face_px // 2 - 62, y + face_px // 2 - 24, x + face_px // 2 + 62, y + face_px // 2 + 24],
                       fill=(255, 255, 255))
        draw.text((x + face_px // 2, y + face_px // 2), f"id {tag_id}  {face_name}", fill=(200, 0, 0),
                  font=label_font, anchor="mm")
        draw.text((x + face_px // 2, y + 3), f"up: {UP_WORDS[face_name]}", fill=(0, 0, 160), font=small_font, anchor="mt")
    # World axes on the +x face as seen from outside: y to the right, z up, x out of the page.
    cx, cy = pad + face_px // 2, pad + face_px + face_px // 2
    axes_origin = (pad + 12, pad + 2 * face_px - 12)
    _arrow(draw, axes_origin, (axes_origin[0] + face_px // 3, axes_origin[1]), (0, 150, 0), 3)
    _arrow(draw, axes_origin, (axes_origin[0], axes_origin[1] - face_px // 3), (0, 0, 220), 3)
    draw.ellipse([axes_origin[0] - 7, axes_origin[1] - 7, axes_origin[0] + 7, axes_origin[1] + 7], outline=(220, 0, 0), width=3)
    draw.ellipse([axes_origin[0] - 2, axes_origin[1] - 2, axes_origin[0] + 2, axes_origin[1] + 2], fill=(220, 0, 0))
    draw.text((axes_origin[0] + face_px // 3 + 4, axes_origin[1]), "y", fill=(0, 150, 0), font=small_font, anchor="lm")
    draw.text((axes_origin[0], axes_origin[1] - face_px // 3 - 4), "z", fill=(0, 0, 220), font=small_font, anchor="mb")
    draw.text((axes_origin[0] + 10, axes_origin[1] - 10), "x (out)", fill=(220, 0, 0), font=small_font, anchor="lb")
    del cx, cy
    legend = [
        f"{target.family}, cube {cube.side_m * 1000:.0f} mm, tags {cube.tag_size_m * 1000:.0f} mm, seen from outside, "
        "fold the side strip into a ring, +z on top, -z below.",
        "World frame: origin at the cube centre, z up; every tag is printed upright in this net "
        "(corners TL, TR, BR, BL as printed).",
    ]
    for k, line in enumerate(legend):
        draw.text((pad, pad + 3 * face_px + 14 + k * (face_px // 8)), line, fill=(0, 0, 0), font=small_font)
    return canvas


def tag_size_picture(family: str = "tag36h11", tag_id: int = 0, size_px: int = 400) -> Image.Image:
    """What "tag size" means: the outer edge of the black border, not the white margin
    and not the inner data area."""
    cells = FAMILY_CELLS[family]
    cell = size_px // cells
    size_px = cell * cells
    pad = 3 * cell
    canvas = Image.new("RGB", (size_px + 2 * pad + 260, size_px + 2 * pad + 60), "white")
    draw = ImageDraw.Draw(canvas)
    # The white quiet zone around the tag (shown as a light frame), then the tag.
    draw.rectangle([pad - cell, pad - cell, pad + size_px + cell, pad + size_px + cell], outline=(170, 170, 170), width=2)
    canvas.paste(tag_image(family, tag_id, size_px).convert("RGB"), (pad, pad))
    text = font(22)
    y_good = pad + size_px + cell + 26
    _arrow(draw, (pad + size_px // 2, y_good), (pad, y_good), (0, 140, 0), 3)
    _arrow(draw, (pad + size_px // 2, y_good), (pad + size_px, y_good), (0, 140, 0), 3)
    for x in (pad, pad + size_px):
        draw.line([(x, pad + size_px + 4), (x, y_good + 8)], fill=(0, 140, 0), width=2)
    draw.text((pad + size_px // 2, y_good + 6), "tag size = outer edge of the black border", fill=(0, 140, 0),
              font=text, anchor="mt")
    x_text = pad + size_px + cell + 20
    draw.text((x_text, pad), "NOT the white margin\n(grey frame)", fill=(170, 0, 0), font=text)
    draw.text((x_text, pad + size_px // 2), f"NOT the inner data\narea ({cells - 2} of {cells} cells)", fill=(170, 0, 0),
              font=text)
    inner0, inner1 = pad + cell, pad + size_px - cell
    draw.rectangle([inner0, inner0, inner1, inner1], outline=(200, 0, 0), width=2)
    return canvas


@dataclass(frozen=True)
class CubeFiles:
    """A cube's printables, in memory: ``files`` maps a file name to its bytes."""

    files: dict[str, bytes]
    faces: int
    page_name: str  # the faces' page size
    with_net: bool  # the unfolded net is the PDF's last page (the cube fits on A3)


def cube_files(target: Target, dpi: float = 300.0) -> CubeFiles:
    """What ``cubeloc generate cube`` writes for a cube target: ``cube.pdf`` (one page per
    face at true scale, then the unfolded net when it fits on A3), ``face_<n>_id<id>.png``
    (each face, with ``dpi`` in the file) and ``cube_layout.png`` (which tag goes where)."""
    import io

    def png(image: Image.Image, resolution: float) -> bytes:
        buffer = io.BytesIO()
        image.save(buffer, format="PNG", dpi=(resolution, resolution))
        return buffer.getvalue()

    sheets = face_sheets(target, dpi)
    net = net_sheet(target, dpi)
    pages = [sheet.page for sheet in sheets] + ([net] if net is not None else [])
    pdf = io.BytesIO()
    pages[0].save(pdf, format="PDF", save_all=True, append_images=pages[1:], resolution=dpi)
    files = {"cube.pdf": pdf.getvalue()}
    for index, sheet in enumerate(sheets):
        files[f"face_{index}_id{sheet.tag_id}.png"] = png(sheet.face_image, dpi)
    files["cube_layout.png"] = png(cube_layout_picture(target), 96)
    return CubeFiles(files, len(sheets), sheets[0].page_name, net is not None)
