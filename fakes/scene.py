"""What stands in the room: the target's faces as quads, lit, with tags drawn or hidden.

For a cube target each face is one quad of the cube's side with its tag centred on it (a
white margin around the black border, as printed). For a Kalibr AprilGrid each tag is a
plate half a gap wider all round, with black squares touching its corners. For any other
target each tag is a plate: the tag with a one-cell white margin. Tag cells are tag36h11
(or the target's family) bit patterns from ``cv2.aruco.generateImageMarker``, so the tag's
3-D corners TL, TR, BR, BL fall exactly on the outer corners of the marker image's black
border.
"""

from __future__ import annotations

import functools

import numpy as np

from cubeloc.fakes.surfaces import PlainShader, Quad, TagShader
from cubeloc.positioning.tag_bits import tag_cells
from cubeloc.positioning.target import Tag, Target

# One light from above and to the side, so the faces of the cube differ in brightness
# the way they do under a ceiling lamp; ``AMBIENT`` keeps the darkest face readable.
LIGHT_DIRECTION = np.array([0.35, -0.45, 1.0]) / np.linalg.norm([0.35, -0.45, 1.0])
AMBIENT = 0.5
PAPER_WHITE = 0.9
INK_BLACK = 0.06


@functools.lru_cache(maxsize=64)
def tag_bits(family: str, tag_id: int, border_bits: int = 1) -> np.ndarray:
    """(N, N) float32 cells of a tag including its black border: 1 white, 0 black (the
    drawing ``positioning.tag_bits`` models the edges of)."""
    bits = tag_cells(family, tag_id, border_bits).astype(np.float32)
    bits.setflags(write=False)
    return bits


def face_brightness(normal: np.ndarray) -> float:
    return AMBIENT + (1.0 - AMBIENT) * max(0.0, float(np.asarray(normal) @ LIGHT_DIRECTION))


def _tag_frame(tag: Tag) -> tuple[np.ndarray, np.ndarray]:
    """Unit "right" (TL->TR) and "down" (TL->BL) of a tag as printed upright."""
    c = tag.corners
    right = (c[1] - c[0]) / np.linalg.norm(c[1] - c[0])
    down = (c[3] - c[0]) / np.linalg.norm(c[3] - c[0])
    return right, down


def target_quads(
    target: Target,
    *,
    hidden_tags: tuple[int, ...] | frozenset[int] = (),
    glare_tag: int | None = None,
    glare_strength: float = 3.0,
) -> tuple[Quad, ...]:
    """The quads that draw ``target``: cube faces, or one plate per tag (an AprilGrid's
    plates reach half the gap beyond each tag, so they tile the board, and each carries a
    quarter of the four black squares at its tag's corners)."""
    hidden = set(hidden_tags)
    quads = []
    for tag in target.tags:
        right, down = _tag_frame(tag)
        size = tag.size_m
        bits = tag_bits(target.family, tag.tag_id, target.border_bits)
        cell = size / bits.shape[0]
        squares = 0.0
        if target.cube is not None:
            margin = (target.cube.side_m - size) / 2.0
        elif target.grid is not None:
            margin = squares = target.grid.gap_m / 2.0
        else:
            margin = cell
        origin = tag.corners[0] - margin * (right + down)
        if tag.tag_id in hidden:
            shader = PlainShader(PAPER_WHITE)
        else:
            shader = TagShader(bits, margin, margin, cell, PAPER_WHITE, INK_BLACK, squares)
        quads.append(
            Quad(
                origin,
                right,
                down,
                size + 2 * margin,
                size + 2 * margin,
                shader,
                brightness=face_brightness(np.cross(down, right)),
                glare=glare_strength if tag.tag_id == glare_tag else 0.0,
            )
        )
    return tuple(quads)
