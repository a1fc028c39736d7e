"""Flat textured rectangles (quads) and how a ray meets one: the renderer's building block.

A quad is a rectangle in the world: its top-left corner ``origin``, unit axes ``axis_u``
("right") and ``axis_v`` ("down") as seen from its front, and its size. Its outward normal
is ``axis_v x axis_u`` (as the camera's -z is y x x). Rays are OpenCV camera rays
``(x, y, 1)``, so the ray parameter of a hit is the depth z of the hit point.

Exactness: a hit's quad coordinates (metres from ``origin``) come from the plane equation
in closed form; texture lookups use the texel that contains the hit (nearest, for the tag
cells) or bilinear between texel centres (for the room), so an edge in a texture lands
exactly where the geometry puts it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from cubeloc.positioning.geometry import Transform


class Shader(Protocol):
    def __call__(self, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
        """Radiance (float32, 0 = black, 1 = paper white) at quad coordinates in metres."""

    def labels(self, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
        """Integer id of the uniform patch (a tag cell) at each point, 0 where the shader
        is smooth: the renderer supersamples pixels where ids change (edges)."""


@dataclass(frozen=True, eq=False)
class TextureShader:
    """A uint8 texture with square texels of ``texel_m``; bilinear between texel centres."""

    texture: np.ndarray  # (H, W) uint8
    texel_m: float

    def __call__(self, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
        map_x = (u_m / self.texel_m - 0.5).astype(np.float32).reshape(-1, 1)
        map_y = (v_m / self.texel_m - 0.5).astype(np.float32).reshape(-1, 1)
        if map_x.shape[0] >= 32000:  # cv2.remap takes maps under SHRT_MAX on each side
            side = int(np.ceil(np.sqrt(map_x.shape[0])))
            pad = side * side - map_x.shape[0]
            map_x = np.pad(map_x.ravel(), (0, pad)).reshape(side, side)
            map_y = np.pad(map_y.ravel(), (0, pad)).reshape(side, side)
        out = cv2.remap(self.texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out.ravel()[: u_m.size].astype(np.float32) / np.float32(255.0)

    def labels(self, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
        return np.zeros(u_m.shape, np.int32)


@dataclass(frozen=True, eq=False)
class TagShader:
    """An AprilTag on plain paper: ``bits`` (N, N) cells, 1 = white, outer ring black.

    ``tag_u_m``, ``tag_v_m`` place the tag's top-left corner in quad coordinates; cells are
    ``cell_m`` wide. Nearest lookup: the hit's cell decides, so cell edges are exact.
    """

    bits: np.ndarray  # (N, N) float32 in {0, 1}
    tag_u_m: float
    tag_v_m: float
    cell_m: float
    paper: float = 0.9
    ink: float = 0.06
    corner_squares_m: float = 0.0  # black squares this wide touching the tag's corners diagonally

    def _cells(self, u_m: np.ndarray, v_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = self.bits.shape[0]
        col = np.floor((u_m - self.tag_u_m) / self.cell_m).astype(np.int32)
        row = np.floor((v_m - self.tag_v_m) / self.cell_m).astype(np.int32)
        return row, col, (col >= 0) & (col < n) & (row >= 0) & (row < n)

    def _square(self, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
        """Where a corner square is: 1-4 (TL, TR, BR, BL), else 0."""
        if self.corner_squares_m <= 0:
            return np.zeros(u_m.shape, np.int32)
        side = self.bits.shape[0] * self.cell_m
        du, dv = u_m - self.tag_u_m, v_m - self.tag_v_m
        left, right = (du < 0) & (du >= -self.corner_squares_m), (du >= side) & (du < side + self.corner_squares_m)
        top, bottom = (dv < 0) & (dv >= -self.corner_squares_m), (dv >= side) & (dv < side + self.corner_squares_m)
        return (1 * (left & top) + 2 * (right & top) + 3 * (right & bottom) + 4 * (left & bottom)).astype(np.int32)

    def __call__(self, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
        row, col, inside = self._cells(u_m, v_m)
        white = np.ones(u_m.shape, np.float32)
        white[inside] = self.bits[row[inside], col[inside]]
        white[self._square(u_m, v_m) > 0] = 0.0
        return np.float32(self.ink) + white * np.float32(self.paper - self.ink)

    def labels(self, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
        """1 + the cell index inside the tag, a label of its own on each corner square, 0
        on the margin."""
        row, col, inside = self._cells(u_m, v_m)
        n2 = self.bits.shape[0] ** 2
        square = self._square(u_m, v_m)
        return np.where(inside, 1 + row * self.bits.shape[0] + col, np.where(square > 0, n2 + square, 0)).astype(np.int32)


@dataclass(frozen=True, eq=False)
class PlainShader:
    """Uniform paint (a face whose tag is hidden)."""

    value: float = 0.9

    def __call__(self, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
        return np.full(u_m.shape, self.value, np.float32)

    def labels(self, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
        return np.zeros(u_m.shape, np.int32)


@dataclass(frozen=True, eq=False)
class Quad:
    """A front-facing rectangle; ``brightness`` scales its shader (lighting), ``glare`` adds
    a bright specular spot (radiance at its centre) that over-exposes the quad."""

    origin: np.ndarray  # (3,) world, top-left corner seen from the front
    axis_u: np.ndarray  # (3,) unit, "right"
    axis_v: np.ndarray  # (3,) unit, "down"
    size_u: float  # metres
    size_v: float  # metres
    shader: Shader
    brightness: float = 1.0
    glare: float = 0.0

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.axis_v, self.axis_u)

    def corners(self) -> np.ndarray:
        """(4, 3) world corners TL, TR, BR, BL."""
        u = np.asarray(self.axis_u) * self.size_u
        v = np.asarray(self.axis_v) * self.size_v
        o = np.asarray(self.origin, dtype=np.float64)
        return np.array([o, o + u, o + u + v, o + v])


@dataclass(frozen=True)
class QuadInCamera:
    """A quad's plane and axes in a camera frame, for tracing many rays at once."""

    quad: Quad
    origin: np.ndarray  # (3,)
    axis_u: np.ndarray  # (3,)
    axis_v: np.ndarray  # (3,)
    normal: np.ndarray  # (3,)

    @staticmethod
    def facing(quad: Quad, T_camera_world: Transform) -> QuadInCamera | None:
        """The quad in the camera frame, or None when the camera sees its back (or its edge)."""
        r = T_camera_world.rotation
        origin = T_camera_world.apply(np.asarray(quad.origin, dtype=np.float64)[None])[0]
        normal = r @ quad.normal
        if normal @ origin >= -1e-12:  # camera on or behind the plane: back faces never drawn
            return None
        return QuadInCamera(quad, origin, r @ quad.axis_u, r @ quad.axis_v, normal)

    def intersect(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Depth (inf where missed), u_m, v_m, hit mask for rays (x, y, 1) of any shape."""
        n, a, b, o = self.normal, self.axis_u, self.axis_v, self.origin
        f32 = np.float32
        denominator = f32(n[0]) * x + f32(n[1]) * y + f32(n[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = f32(n @ o) / denominator
        # local coordinates, relative to the quad origin: u = (t r - o) . a
        u_m = depth * (f32(a[0]) * x + f32(a[1]) * y + f32(a[2])) - f32(a @ o)
        v_m = depth * (f32(b[0]) * x + f32(b[1]) * y + f32(b[2])) - f32(b @ o)
        hit = (depth > 0) & (u_m >= 0) & (u_m < self.quad.size_u) & (v_m >= 0) & (v_m < self.quad.size_v)
        return np.where(hit, depth, np.float32(np.inf)), u_m, v_m, hit

    def labels(self, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
        return self.quad.shader.labels(u_m, v_m)

    def shade(self, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
        quad = self.quad
        value = quad.shader(u_m, v_m) * np.float32(quad.brightness)
        if quad.glare > 0:
            du = u_m - np.float32(quad.size_u / 2)
            dv = v_m - np.float32(quad.size_v / 2)
            sigma = 0.45 * max(quad.size_u, quad.size_v)
            value = value + np.float32(quad.glare) * np.exp(-(du * du + dv * dv) / np.float32(2 * sigma * sigma))
        return value.astype(np.float32)
