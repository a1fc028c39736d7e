"""Render a Mono8 frame of the target in its room, by exact inverse mapping.

For every pixel sample we take its ray from the exact inverse-distortion grid
(``fakes.optics``), intersect the room's walls and every front-facing quad (target faces,
obstacle boxes), let the nearest hit win, and look up its texture. Two passes keep a
1280x1024 frame fast:

* the room at one sample per pixel (one ``cv2.remap`` of the wall atlas), then
* each object (the target, every obstacle box) again in the pixel box around its
  projection: one ray per pixel, then the pixels on an edge (between quads, tag cells,
  or a quad and the room) again at ``s x s`` samples in an n-rooks pattern, averaged:
  anti-aliased edges exactly where the geometry puts them (see ``subpixel_offsets``,
  ``pixel_rays`` and ``_shade_region``).

Then the physical effects, in the order light meets them: glare (a bright spot on one
face, part of the radiance), optical blur (defocus, motion), exposure gain, sensor noise,
and clipping to 8 bits. All randomness comes from ``seed``: same seed, same frame.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from cubeloc.calib.camera_info import CameraCalibration, paper_camera
from cubeloc.fakes.optics import ray_grid
from cubeloc.fakes.room import Room, box_quads, default_room, room_atlas
from cubeloc.fakes.scene import target_quads
from cubeloc.fakes.surfaces import Quad, QuadInCamera
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.jit import compiled
from cubeloc.positioning.target import Target, make_cube

SAMPLE_BUDGET = 1_500_000  # sub-pixel samples of edge pixels per object, when supersample is None
MIN_SUPERSAMPLE, MAX_SUPERSAMPLE = 3, 5  # 5: the best edge accuracy measured (bench render)
REGION_MARGIN_PX = 2
BACKGROUND = 0.5  # radiance where there is no room (room=False)
Z_NEAR = 1e-4  # metres; geometry nearer than this to the camera plane is clipped


@dataclass(frozen=True)
class PixelBox:
    """Pixels [u0, u1) x [v0, v1)."""

    u0: int
    v0: int
    u1: int
    v1: int

    def union(self, other: PixelBox) -> PixelBox:
        return PixelBox(min(self.u0, other.u0), min(self.v0, other.v0), max(self.u1, other.u1), max(self.v1, other.v1))

    def overlaps(self, other: PixelBox) -> bool:
        return self.u0 < other.u1 and other.u0 < self.u1 and self.v0 < other.v1 and other.v0 < self.v1


@functools.lru_cache(maxsize=4)
def _padded_grid_cached(key: tuple) -> np.ndarray:
    width, height, k_bytes, d_bytes, model = key
    calibration = CameraCalibration(width, height, np.frombuffer(k_bytes).reshape(3, 3), np.frombuffer(d_bytes), model)
    grid = ray_grid(calibration, 1)
    padded = np.empty((grid.shape[0] + 2, grid.shape[1] + 2, 2), np.float64)
    padded[1:-1, 1:-1] = grid
    padded[0, 1:-1] = 2 * grid[0] - grid[1]
    padded[-1, 1:-1] = 2 * grid[-1] - grid[-2]
    padded[:, 0] = 2 * padded[:, 1] - padded[:, 2]
    padded[:, -1] = 2 * padded[:, -2] - padded[:, -3]
    padded = padded.astype(np.float32)
    padded.setflags(write=False)
    return padded


def padded_grid(calibration: CameraCalibration) -> np.ndarray:
    """(H+2, W+2, 2) float32 ray grid with one pixel of linear extrapolation all round
    (cached per calibration), so sub-pixel samples of border pixels interpolate too."""
    key = (calibration.width, calibration.height, calibration.camera_matrix.tobytes(),
           calibration.distortion.tobytes(), calibration.distortion_model)
    return _padded_grid_cached(key)


def subpixel_offsets(s: int) -> tuple[np.ndarray, np.ndarray]:
    """(s, s) x and y offsets from the pixel centre of the samples (sub-row i, sub-column j).

    An "n-rooks" pattern: the s*s samples all have distinct x and distinct y offsets, so a
    near-vertical or near-horizontal edge is resolved to 1/s^2 px, where a regular s x s
    grid would snap it to 1/s px. The offsets average to zero: the pixel's centre.
    """
    i, j = np.meshgrid(np.arange(s), np.arange(s), indexing="ij")
    ox = (j * s + i + 0.5) / (s * s) - 0.5
    oy = (i * s + j + 0.5) / (s * s) - 0.5
    return ox.astype(np.float32), oy.astype(np.float32)


def sample_rays(calibration: CameraCalibration, box: PixelBox) -> tuple[np.ndarray, np.ndarray]:
    """Exact rays (x, y), each (h, w) float32, of the pixel centres in ``box``."""
    centre = padded_grid(calibration)[box.v0 + 1 : box.v1 + 1, box.u0 + 1 : box.u1 + 1]
    return np.ascontiguousarray(centre[..., 0]), np.ascontiguousarray(centre[..., 1])


def shade_room(room: Room, T_world_camera: Transform, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Radiance of the room's walls along rays (x, y, 1) ((H, W) float32 each); the camera
    is inside the room.

    The camera is inside a convex box, so every ray leaves through exactly one wall: the
    one with the smallest exit distance along the ray. Its wall coordinates come from one
    compiled pass over the rays (``_room_coordinates``), the radiance from one ``cv2.remap``
    of the wall atlas: this is most of the time of a frame.
    """
    atlas = room_atlas(room)
    c = T_world_camera.translation
    f32 = np.float32
    # per axis: the distances to its upper and lower wall, and the camera's coordinate
    walls = np.array([[room.upper[k] - c[k], room.lower[k] - c[k], c[k]] for k in range(3)]).astype(f32)
    x, y = np.ascontiguousarray(x, f32), np.ascontiguousarray(y, f32)
    u, v = _compiled_room()(x, y, T_world_camera.rotation.astype(f32), walls, f32(1.0 / atlas.texel_m),
                            atlas.offset_x, atlas.offset_y)
    return _remap_any_shape(atlas.image, u, v)


def _room_coordinates(x, y, r, walls, inv_texel, offset_x, offset_y):
    """Atlas coordinates (u, v) of the wall each ray (x, y, 1) of the camera rotated by ``r``
    meets first, float32 throughout in the order numpy would take it.

    Per axis k the ray's exit distance is the positive one of (wall - c[k]) / d[k] over
    its two walls (+inf for d[k] = 0); the smallest over the axes is the wall it meets.
    Wall coordinates: x walls (y, z), y walls (x, z), z walls (x, y); wall index
    2 * axis + (1 on the upper wall), as in fakes.room.
    """
    height, width = x.shape
    u = np.empty((height, width), np.float32)
    v = np.empty((height, width), np.float32)
    one, zero = np.float32(1.0), np.float32(0.0)
    for i in range(height):
        for j in range(width):
            xx, yy = x[i, j], y[i, j]
            d0 = r[0, 0] * xx + r[0, 1] * yy + r[0, 2]
            d1 = r[1, 0] * xx + r[1, 1] * yy + r[1, 2]
            d2 = r[2, 0] * xx + r[2, 1] * yy + r[2, 2]
            # numpy's maximum and minimum, where nan wins
            a, b = one / d0 * walls[0, 0], one / d0 * walls[0, 1]
            e0 = a if a != a or a >= b else b
            a, b = one / d1 * walls[1, 0], one / d1 * walls[1, 1]
            e1 = a if a != a or a >= b else b
            a, b = one / d2 * walls[2, 0], one / d2 * walls[2, 1]
            e2 = a if a != a or a >= b else b
            depth = e0 if e0 != e0 or e0 <= e1 else e1
            depth = depth if depth != depth or depth <= e2 else e2
            on_x = e0 == depth
            on_z = e2 == depth and not on_x
            if on_x:
                uu, upper = d1 * depth + walls[1, 2], d0 > zero
            else:
                uu, upper = d0 * depth + walls[0, 2], (d2 if on_z else d1) > zero
            vv = d1 * depth + walls[1, 2] if on_z else d2 * depth + walls[2, 2]
            wall = (4 if on_z else (0 if on_x else 2)) + (1 if upper else 0)
            u[i, j] = uu * inv_texel + offset_x[wall]
            v[i, j] = vv * inv_texel + offset_y[wall]
    return u, v


def _warm_up_room() -> None:
    f32 = np.float32
    _compiled_room()(np.zeros((1, 1), f32), np.zeros((1, 1), f32), np.eye(3, dtype=f32), np.ones((3, 3), f32),
                     f32(1.0), np.zeros(6, f32), np.zeros(6, f32))


_compiled_room = compiled(_room_coordinates, _warm_up_room, exact=True)  # see positioning/jit.py


def _remap_any_shape(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """cv2.remap (bilinear) for maps of any 2-D shape, as float32 radiance in [0, 1]."""
    shape = map_x.shape
    mx, my = map_x.astype(np.float32), map_y.astype(np.float32)
    if max(shape) >= 32000:  # cv2.remap needs both sides under SHRT_MAX
        side = int(np.ceil(np.sqrt(mx.size)))
        pad = side * side - mx.size
        mx = np.pad(mx.ravel(), (0, pad)).reshape(side, side)
        my = np.pad(my.ravel(), (0, pad)).reshape(side, side)
    out = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[: map_x.size].reshape(shape).astype(np.float32) * np.float32(1 / 255)


def quad_pixel_box(quad: QuadInCamera, calibration: CameraCalibration) -> PixelBox | None:
    """Pixels the quad may cover (its outline clipped to the view, distorted, plus a
    margin), or None when no part of it is in view."""
    from cubeloc.fakes.optics import project

    polygon = np.array([quad.origin, quad.origin + quad.axis_u * quad.quad.size_u,
                        quad.origin + quad.axis_u * quad.quad.size_u + quad.axis_v * quad.quad.size_v,
                        quad.origin + quad.axis_v * quad.quad.size_v])
    # clip to the viewing frustum (a little wider than the image's rays), so that parts
    # outside the view never stretch the box, and the lens model is only used where valid
    grid = padded_grid(calibration)
    x_reach = 1.02 * float(np.abs(grid[..., 0]).max())
    y_reach = 1.02 * float(np.abs(grid[..., 1]).max())
    for plane in ((0.0, 0.0, 1.0, -Z_NEAR), (-1.0, 0.0, x_reach, 0.0), (1.0, 0.0, x_reach, 0.0),
                  (0.0, -1.0, y_reach, 0.0), (0.0, 1.0, y_reach, 0.0)):
        polygon = _clip(polygon, np.array(plane[:3]), plane[3])
        if len(polygon) < 3:
            return None
    # points along the edges: distortion bends straight edges, so corners alone do not bound
    steps = np.linspace(0.0, 1.0, 17)[:-1, None]
    points = np.concatenate([a + steps * (b - a) for a, b in zip(polygon, np.roll(polygon, -1, axis=0), strict=True)])
    pixels = project(points, calibration)
    box = PixelBox(
        max(0, int(np.floor(pixels[:, 0].min())) - REGION_MARGIN_PX),
        max(0, int(np.floor(pixels[:, 1].min())) - REGION_MARGIN_PX),
        min(calibration.width, int(np.ceil(pixels[:, 0].max())) + REGION_MARGIN_PX + 1),
        min(calibration.height, int(np.ceil(pixels[:, 1].max())) + REGION_MARGIN_PX + 1),
    )
    return box if box.u1 > box.u0 and box.v1 > box.v0 else None


def _clip(polygon: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """Sutherland-Hodgman: the part of a convex polygon (N, 3) where normal . p + offset >= 0."""
    out = []
    count = len(polygon)
    side = polygon @ normal + offset
    for i in range(count):
        j = (i + 1) % count
        if side[i] >= 0:
            out.append(polygon[i])
        if (side[i] >= 0) != (side[j] >= 0):
            t = side[i] / (side[i] - side[j])
            out.append(polygon[i] + t * (polygon[j] - polygon[i]))
    return np.array(out).reshape(-1, 3)


def _choose_supersample(edge_pixels: int, supersample: int | None) -> int:
    if supersample is not None:
        return int(supersample)
    s = int(np.sqrt(SAMPLE_BUDGET / max(edge_pixels, 1)))
    return int(np.clip(s, MIN_SUPERSAMPLE, MAX_SUPERSAMPLE))


def pixel_rays(calibration: CameraCalibration, us: np.ndarray, vs: np.ndarray, s: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays (x, y), each (N, s*s) float32, of the samples of the pixels (us, vs) (N,):
    the pixel centre's exact ray plus the local Jacobian times the sample offset (the
    inverse distortion bends so little over half a pixel that this is exact to ~1e-4 px)."""
    padded = padded_grid(calibration)
    pu, pv = us + 1, vs + 1  # padded indices
    centre = padded[pv, pu]
    d_du = (padded[pv, pu + 1] - padded[pv, pu - 1]) * np.float32(0.5)
    d_dv = (padded[pv + 1, pu] - padded[pv - 1, pu]) * np.float32(0.5)
    ox, oy = (o.ravel()[None, :] for o in subpixel_offsets(s))
    x = centre[:, 0:1] + d_du[:, 0:1] * ox + d_dv[:, 0:1] * oy
    y = centre[:, 1:2] + d_du[:, 1:2] * ox + d_dv[:, 1:2] * oy
    return x, y


def _trace_quads(
    quads: list[tuple[QuadInCamera, PixelBox]],
    x: np.ndarray,
    y: np.ndarray,
    radiance: np.ndarray,
    labels: np.ndarray | None = None,
) -> None:
    """Draw the quads over ``radiance`` (in place) along rays (x, y), nearest hit winning.
    Every quad is inside the room, so any hit is nearer than the room behind it."""
    depth = np.full(x.shape, np.inf, np.float32)
    for index, (quad, _) in enumerate(quads):
        t, u_m, v_m, hit = quad.intersect(x, y)
        nearer = hit & (t < depth)
        if not nearer.any():
            continue
        radiance[nearer] = quad.shade(u_m[nearer], v_m[nearer])
        depth[nearer] = t[nearer]
        if labels is not None:
            labels[nearer] = (index + 1) * 4096 + quad.labels(u_m[nearer], v_m[nearer])


def _shade_region(
    background: np.ndarray,
    quads: list[tuple[QuadInCamera, PixelBox]],
    calibration: CameraCalibration,
    box: PixelBox,
    supersample: int | None,
) -> np.ndarray:
    """The objects over ``background`` (the region's 1x room) in the pixel box ``box``.

    First one ray per pixel, which also labels each pixel with the quad and tag cell it
    sees; a pixel whose 3x3 neighbourhood holds one label lies inside one uniform patch
    (or shows only the room), so that sample is its exact value. The other pixels, the
    edges, are traced again at s x s samples and averaged: anti-aliasing where it matters.
    """
    quads = [q for q in quads if q[1].overlaps(box)]
    x, y = sample_rays(calibration, box)
    radiance = background.copy()
    labels = np.zeros(background.shape, np.float32)  # 0: the room
    _trace_quads(quads, x, y, radiance, labels)
    kernel = np.ones((3, 3), np.uint8)
    edges = cv2.dilate(labels, kernel) != cv2.erode(labels, kernel)
    vs, us = np.nonzero(edges)
    if len(vs) == 0:
        return radiance
    s = _choose_supersample(len(vs), supersample)
    xs, ys = pixel_rays(calibration, us + box.u0, vs + box.v0, s)
    samples = np.repeat(background[vs, us][:, None], xs.shape[1], axis=1)
    _trace_quads(quads, xs, ys, samples)
    radiance[vs, us] = samples.mean(axis=1)
    return radiance


@functools.lru_cache(maxsize=1)
def _default_cube() -> Target:
    return make_cube()


def render_radiance(
    T_world_camera: Transform,
    calibration: CameraCalibration,
    room: Room | None,
    quads_world: tuple[Quad, ...],
    objects: tuple[tuple[int, ...], ...],
    supersample: int | None,
) -> np.ndarray:
    """(H, W) float32 radiance: the room at 1x, then each object's region supersampled.

    ``objects`` groups indices into ``quads_world``: one region is rendered per group.
    """
    if room is not None and not room.contains(T_world_camera.translation):
        raise ValueError(f"camera at {np.round(T_world_camera.translation, 3).tolist()} is outside the room")
    T_camera_world = T_world_camera.inverse()
    full = PixelBox(0, 0, calibration.width, calibration.height)
    facing: dict[int, tuple[QuadInCamera, PixelBox]] = {}
    for index, quad in enumerate(quads_world):
        in_camera = QuadInCamera.facing(quad, T_camera_world)
        if in_camera is None:
            continue
        box = quad_pixel_box(in_camera, calibration)
        if box is not None:
            facing[index] = (in_camera, box)
    if room is not None:
        x, y = sample_rays(calibration, full)
        room_only = shade_room(room, T_world_camera, x, y)
    else:
        room_only = np.full((calibration.height, calibration.width), BACKGROUND, np.float32)
    radiance = room_only.copy()
    visible = list(facing.values())
    for group in objects:
        boxes = [facing[i][1] for i in group if i in facing]
        if not boxes:
            continue
        region = boxes[0]
        for b in boxes[1:]:
            region = region.union(b)
        # each region draws every quad in it over the bare room, so where the regions of
        # two objects overlap, either result is the whole truth
        rows, cols = slice(region.v0, region.v1), slice(region.u0, region.u1)
        radiance[rows, cols] = _shade_region(room_only[rows, cols], visible, calibration, region, supersample)
    return radiance


def apply_sensor(
    radiance: np.ndarray,
    *,
    noise_sigma: float,
    seed: int,
    blur_sigma_px: float = 0.0,
    motion_blur_px: float = 0.0,
    motion_blur_angle_deg: float = 0.0,
    exposure_gain: float = 1.0,
    response_gamma: float = 1.0,
) -> np.ndarray:
    """Optics blur, exposure, Gaussian read noise (DN), the response curve
    ``255 (DN / 255) ** response_gamma`` (1: linear, as a machine-vision camera's default;
    otherwise a blurred edge is found off its true place: below 1 the white side grows,
    0.11 of the blur's sigma at 0.8) and 8-bit clipping -> Mono8."""
    image = radiance
    if blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur_sigma_px)
    if motion_blur_px > 0:
        image = cv2.filter2D(image, -1, motion_kernel(motion_blur_px, motion_blur_angle_deg))
    image = image * np.float32(255.0 * exposure_gain)
    if noise_sigma > 0:
        # OpenCV's generator is 4x faster than numpy's here; it is per thread, so seeding
        # it right before drawing makes the noise a function of ``seed`` alone
        noise = np.empty(image.shape, np.float32)
        cv2.setRNGSeed(int(np.random.SeedSequence(seed).generate_state(1)[0] >> 1))
        cv2.randn(noise, 0.0, float(noise_sigma))
        image = image + noise
    if response_gamma != 1.0:
        image = np.float32(255.0) * (np.clip(image, 0.0, 255.0) / np.float32(255.0)) ** np.float32(response_gamma)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def motion_kernel(length_px: float, angle_deg: float) -> np.ndarray:
    """A normalised line kernel of ``length_px`` at ``angle_deg`` (image x right, y down)."""
    half = int(np.ceil(length_px / 2)) + 1
    kernel = np.zeros((2 * half + 1, 2 * half + 1), np.float32)
    angle = np.radians(angle_deg)
    for step in np.linspace(-length_px / 2, length_px / 2, max(2, int(np.ceil(length_px * 4)))):
        u, v = half + step * np.cos(angle), half + step * np.sin(angle)
        iu, iv = int(np.floor(u)), int(np.floor(v))
        fu, fv = u - iu, v - iv
        # bilinear splat: a smooth line at any angle and sub-pixel length
        kernel[iv, iu] += (1 - fu) * (1 - fv)
        kernel[iv, iu + 1] += fu * (1 - fv)
        kernel[iv + 1, iu] += (1 - fu) * fv
        kernel[iv + 1, iu + 1] += fu * fv
    return kernel / kernel.sum()


def render_view(
    T_world_camera: Transform,
    *,
    calibration: CameraCalibration | None = None,
    target: Target | None = None,
    room: bool | Room = True,
    noise_sigma: float = 2.0,
    seed: int = 0,
    hidden_tags: tuple[int, ...] = (),
    glare_tag: int | None = None,
    blur_sigma_px: float = 0.0,
    supersample: int | None = None,
    exposure_gain: float = 1.0,
    glare_strength: float = 3.0,
    motion_blur_px: float = 0.0,
    motion_blur_angle_deg: float = 0.0,
    extra_objects: tuple[tuple[Quad, ...], ...] = (),
    exposure_poses: tuple[Transform, ...] = (),
    response_gamma: float = 1.0,
) -> np.ndarray:
    """A (H, W) uint8 Mono8 frame of ``target`` seen from ``T_world_camera``.

    ``calibration`` defaults to the paper's camera, ``target`` to the 18 cm cube (ids 0-5),
    ``room`` to the default textured room (``False``: a plain grey background; a ``Room``:
    that room and its obstacle boxes). ``hidden_tags`` are painted over (plain faces),
    ``glare_tag`` gets a specular spot of ``glare_strength`` (radiance; 1 is paper white)
    that over-exposes its face. ``supersample`` s fixes the s x s samples of each pixel on
    an object's edges (default: 5, fewer when an object fills much of the view; 5 puts tag
    corners within ~0.03 px). ``exposure_gain`` scales brightness before clipping,
    ``blur_sigma_px`` is defocus, ``motion_blur_px`` a linear smear at
    ``motion_blur_angle_deg``. ``noise_sigma`` is Gaussian read noise in DN drawn from
    ``seed``. ``extra_objects`` are more objects in the room (each a group of quads:
    a passer-by, a painted panel). ``exposure_poses``, when given, are camera poses spread
    over the exposure time: the frame is the mean of their renders, the motion blur of a
    moving camera integrated over its exposure (``motion_blur_px`` is a fixed smear
    instead). ``response_gamma``: the camera's response curve (``apply_sensor``). Raises
    ValueError if the camera is outside the room.
    """
    calibration = calibration or paper_camera()
    target = target or _default_cube()
    room_obj: Room | None = default_room() if room is True else (room or None)
    quads = list(target_quads(target, hidden_tags=tuple(hidden_tags), glare_tag=glare_tag,
                              glare_strength=glare_strength))
    objects = [tuple(range(len(quads)))]
    boxes = [box_quads(box, room_obj.texel_m) for box in room_obj.boxes] if room_obj is not None else []
    for group in [*boxes, *extra_objects]:  # one region each: the room's boxes, passers-by, panels
        start = len(quads)
        quads.extend(group)
        objects.append(tuple(range(start, len(quads))))
    radiance = render_radiance(
        T_world_camera, calibration, room_obj, tuple(quads), tuple(objects), supersample
    ) if not exposure_poses else np.mean([
        render_radiance(pose, calibration, room_obj, tuple(quads), tuple(objects), supersample)
        for pose in exposure_poses], axis=0, dtype=np.float32)
    return apply_sensor(
        radiance,
        noise_sigma=noise_sigma,
        seed=seed,
        blur_sigma_px=blur_sigma_px,
        motion_blur_px=motion_blur_px,
        motion_blur_angle_deg=motion_blur_angle_deg,
        exposure_gain=exposure_gain,
        response_gamma=response_gamma,
    )
