"""The room around the target: an axis-aligned box seen from inside, and obstacle boxes.

The standard cube stands on the floor at the world origin, so the floor is at
``z = -0.09``. Walls, floor and ceiling carry procedural textures (``fakes.textures``)
packed into one atlas, so a whole frame of room is one ``cv2.remap``. Obstacles are
axis-aligned boxes on the floor, drawn like any other textured quad (``fakes.surfaces``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from cubeloc.fakes.surfaces import Quad, TextureShader
from cubeloc.fakes.textures import procedural_texture

ATLAS_PADDING = 4  # texels of replicated border around each wall, so bilinear never bleeds
MAX_ATLAS_SIDE = 32000  # cv2.remap takes sources under SHRT_MAX on each side


@dataclass(frozen=True)
class Box:
    """An obstacle: an axis-aligned box, ``center`` and ``size`` (x, y, z) in metres."""

    center: tuple[float, float, float]
    size: tuple[float, float, float]
    seed: int = 0


@dataclass(frozen=True)
class Room:
    """Bounds in metres (world frame), texel size of the wall textures, texture seed."""

    x_range: tuple[float, float] = (-5.0, 5.0)
    y_range: tuple[float, float] = (-4.0, 4.0)
    z_range: tuple[float, float] = (-0.09, 2.91)
    texel_m: float = 0.004
    seed: int = 0
    boxes: tuple[Box, ...] = ()
    # walls (atlas order, below) given another texture, the others kept: a room changed in part
    retextured: tuple[int, ...] = ()
    # per wall (atlas order), the share of its width that is plain paint (one span, a few
    # scuffs): rich to sparse walls. Empty: every wall textured all over.
    plain: tuple[float, ...] = ()

    @property
    def lower(self) -> np.ndarray:
        return np.array([self.x_range[0], self.y_range[0], self.z_range[0]])

    @property
    def upper(self) -> np.ndarray:
        return np.array([self.x_range[1], self.y_range[1], self.z_range[1]])

    def contains(self, point: np.ndarray, margin: float = 0.0) -> bool:
        p = np.asarray(point, dtype=np.float64)
        return bool(np.all(p > self.lower + margin) and np.all(p < self.upper - margin))


def default_room(seed: int = 0) -> Room:
    return Room(seed=seed)


# Walls in atlas order: index = 2 * axis + (1 if the wall is at the upper bound).
# The texture of a wall spans its two other world axes (u, v): x walls (y, z),
# y walls (x, z), z walls (x, y).
WALL_AXES = {0: (1, 2), 1: (0, 2), 2: (0, 1)}


@dataclass(frozen=True)
class RoomAtlas:
    """All six wall textures in one image, with the affine map from wall (u, v) to atlas."""

    image: np.ndarray  # (H, W) uint8
    offset_x: np.ndarray  # (6,) atlas column of u = 0 per wall, in texels
    offset_y: np.ndarray  # (6,) atlas row of v = 0 per wall, in texels
    texel_m: float


@functools.lru_cache(maxsize=4)
def room_atlas(room: Room) -> RoomAtlas:
    """The texture atlas of a room (cached: building one takes about a second)."""
    lower, upper = room.lower, room.upper
    rng = np.random.default_rng([room.seed, 7])
    blocks, offsets_x, offsets_y = [], [], []
    row = 0
    width = 0
    for wall in range(6):
        axis, upper_side = divmod(wall, 2)
        u_axis, v_axis = WALL_AXES[axis]
        w = int(np.ceil((upper[u_axis] - lower[u_axis]) / room.texel_m))
        h = int(np.ceil((upper[v_axis] - lower[v_axis]) / room.texel_m))
        # floor darker and ceiling lighter, as lit rooms are
        mean = {4: 0.42, 5: 0.7}.get(wall, 0.55)
        texture = procedural_texture(h, w, rng, mean=mean)
        if wall in room.retextured:  # drawn after the original, so the other walls stay as they were
            texture = procedural_texture(h, w, np.random.default_rng([room.seed, 7, 100 + wall]), mean=mean)
        span = plain_span(room, wall)
        if span is not None:  # texel j covers [j, j + 1) texels from the wall's lower corner
            j0, j1 = (int(round((m - lower[u_axis]) / room.texel_m)) for m in span)
            if j1 > j0:
                texture = texture.copy()
                texture[:, j0:j1] = plain_paint(h, j1 - j0, np.random.default_rng([room.seed, 7, 300 + wall]),
                                                mean + 0.1)
        texture = np.pad(texture, ATLAS_PADDING, mode="edge")
        blocks.append(texture)
        # texel j covers [j, j + 1) * texel from the wall's lower corner; its centre is at
        # remap coordinate j, hence the half-texel shift
        offsets_x.append(ATLAS_PADDING - lower[u_axis] / room.texel_m - 0.5)
        offsets_y.append(row + ATLAS_PADDING - lower[v_axis] / room.texel_m - 0.5)
        row += texture.shape[0]
        width = max(width, texture.shape[1])
    if row >= MAX_ATLAS_SIDE or width >= MAX_ATLAS_SIDE:
        raise ValueError(f"room too large for texel {room.texel_m} m: atlas {width}x{row}; use a larger texel_m")
    image = np.zeros((row, width), np.uint8)
    row = 0
    for block in blocks:
        image[row : row + block.shape[0], : block.shape[1]] = block
        row += block.shape[0]
    image.setflags(write=False)
    return RoomAtlas(image, np.array(offsets_x, np.float32), np.array(offsets_y, np.float32), room.texel_m)


def plain_paint(height: int, width: int, rng: np.random.Generator, mean: float = 0.72) -> np.ndarray:
    """Fresh paint: flat, faint roller marks and a few scuffs per square metre at 4 mm texels."""
    return procedural_texture(height, width, rng, mean=mean, contrast=0.03, shapes_per_mpx=40.0)


def plain_span(room: Room, wall: int) -> tuple[float, float] | None:
    """Where wall ``wall`` (atlas order) is plain paint: (start, end) along its u axis, world
    metres, one span of ``room.plain[wall]`` of its width; None where it is textured all over."""
    share = float(np.clip(room.plain[wall], 0.0, 1.0)) if room.plain else 0.0
    if share <= 0.0:
        return None
    u_axis = WALL_AXES[wall // 2][0]
    low, high = float(room.lower[u_axis]), float(room.upper[u_axis])
    width = (high - low) * share
    start = low + float(np.random.default_rng([room.seed, 7, 200 + wall]).uniform(0.0, high - low - width))
    return start, start + width


@functools.lru_cache(maxsize=32)
def box_quads(box: Box, texel_m: float = 0.004) -> tuple[Quad, ...]:
    """The five visible faces of an obstacle box (no bottom), textured like cardboard."""
    center = np.asarray(box.center, dtype=np.float64)
    half = np.asarray(box.size, dtype=np.float64) / 2.0
    rng = np.random.default_rng([box.seed, 11])
    quads = []
    up = np.array([0.0, 0.0, 1.0])
    for normal in (np.eye(3)[0], -np.eye(3)[0], np.eye(3)[1], -np.eye(3)[1], np.eye(3)[2]):
        # texture "right" and "down" seen from outside, so the normal points at the viewer
        down = -up if abs(normal[2]) < 0.5 else np.array([-1.0, 0.0, 0.0]) * normal[2]
        right = np.cross(normal, down)  # so that normal = down x right
        size_u = 2.0 * float(np.abs(right) @ half)
        size_v = 2.0 * float(np.abs(down) @ half)
        origin = center + normal * (np.abs(normal) @ half) - right * size_u / 2 - down * size_v / 2
        h = max(2, int(np.ceil(size_v / texel_m)))
        w = max(2, int(np.ceil(size_u / texel_m)))
        texture = procedural_texture(h, w, rng, mean=0.5, contrast=0.25, shapes_per_mpx=400.0)
        quads.append(Quad(origin, right, down, size_u, size_v, TextureShader(texture, texel_m)))
    return tuple(quads)
