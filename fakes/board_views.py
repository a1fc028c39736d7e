"""Synthetic views of calibration boards, rendered with a known camera.

Each output pixel is the mean of s x s samples; each sample looks along the exact
undistorted ray of ``fakes.optics.ray_grid`` (the inverse of OpenCV's projection), the
ray meets the board plane, and the board's printed texture is read there. A board point
therefore lands where ``cv2.projectPoints`` puts it with the true intrinsics, which is
what lets tests check that calibration recovers them.

A chessboard is not read from a texture but computed at each sample (``_chessboard``):
its edges are exact, anti-aliased over one sample. Reading the 60-texel-per-square
texture bilinearly put its corners off by 0.03-0.05 px RMS, in a pattern that depended
on the texel size (at 640x512 a corner-exact detector then saw the principal point
0.9 px off; computed, 0.001 px and 0.01 px).

``board_views(board, camera, count=20, seed=1)`` is the one-call helper; ``random_poses``
picks poses that keep the whole board in view at varied distances, places and tilts.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cubeloc.calib.boards import BoardSpec, board_texture
from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.fakes.optics import project, ray_grid

WHITE, BLACK, BACKGROUND = 215.0, 35.0, 110.0  # grey levels of paper, ink and the room
LENS_BLUR_PX = 0.5


@dataclass(frozen=True)
class BoardView:
    image: np.ndarray  # (H, W) uint8
    rotation: np.ndarray  # (3, 3) R_cam_board
    translation: np.ndarray  # (3,) t_cam_board, metres
    corrupted: str = ""  # "" for a good view, else what was done to it


@functools.lru_cache(maxsize=4)
def _texture(board: BoardSpec, px_per_m: float, margin_m: float) -> np.ndarray:
    return board_texture(board, px_per_m, margin_m)


def render_view(
    board: BoardSpec,
    camera: CameraCalibration,
    rotation: np.ndarray,
    translation: np.ndarray,
    *,
    supersample: int = 3,
    noise_sigma: float = 1.5,
    blur_sigma: float = 0.0,
    rng: np.random.Generator | None = None,
    stretch_x: float = 1.0,
) -> np.ndarray:
    """One (H, W) uint8 image of ``board`` at pose ``T_cam_board = (rotation, translation)``.

    ``stretch_x`` scales the printed board along x (a badly printed board: a corrupted view).
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    rays = ray_grid(camera, supersample)  # (H*s, W*s, 2)
    r = np.asarray(rotation, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    normal = r[:, 2]
    # ray (x, y, 1) * lam meets the plane n . (p - t) = 0
    denominator = rays[..., 0] * normal[0] + rays[..., 1] * normal[1] + normal[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = float(normal @ t) / denominator
    px = rays[..., 0] * lam - t[0]
    py = rays[..., 1] * lam - t[1]
    pz = lam - t[2]
    bx = (r[0, 0] * px + r[1, 0] * py + r[2, 0] * pz) / stretch_x
    by = r[0, 1] * px + r[1, 1] * py + r[2, 1] * pz
    behind = ~(lam > 0) | ~np.isfinite(bx) | ~np.isfinite(by)  # or along the board's plane
    if board.kind == "chessboard":
        bx[behind], by[behind] = -1e3, -1e3  # off the paper, finite
        sampled = _chessboard(board, bx, by)
        sampled[behind] = -1.0
    else:
        margin_m = board.size_m  # white paper around the pattern
        # 60 texels per square, 20 per cell of an AprilGrid's tag: finer than the samples
        px_per_m = (200.0 if board.kind == "aprilgrid" else 60.0) / board.size_m
        texture = _texture(board, px_per_m, margin_m)
        map_x = ((bx + margin_m) * px_per_m - 0.5).astype(np.float32)
        map_y = ((by + margin_m) * px_per_m - 0.5).astype(np.float32)
        map_x[behind] = -10.0
        sampled = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0)
    paper = sampled >= 0.0
    shade = np.where(paper, BLACK + (WHITE - BLACK) * sampled, BACKGROUND)
    s = supersample
    height, width = camera.height, camera.width
    # The lens' point spread (sigma 0.5 px) before pixel integration: without it an edge
    # ramps over about one sample, and s x s samples place it only to ~1/(2s) px.
    shade = cv2.GaussianBlur(shade.astype(np.float32), (0, 0), LENS_BLUR_PX * s)
    image = shade.reshape(height, s, width, s).mean(axis=(1, 3), dtype=np.float64)
    if blur_sigma > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur_sigma)
    image = image + rng.normal(0.0, noise_sigma, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _square_wave(u: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Along one board axis, ``u`` (float32) in squares at each sample: +1 in even squares
    and -1 in odd ones, box-filtered one sample wide across the edges between squares (a
    linear ramp); and the fraction of the sample inside the pattern [0, count]."""
    gradient_rows, gradient_cols = np.gradient(u)
    step = np.hypot(gradient_rows, gradient_cols)  # squares per sample, across the edge
    np.maximum(step, np.float32(1e-9), out=step)
    edge = np.rint(u)
    # |u - nearest edge| in samples, doubled: the ramp runs from -1 to 1 over one sample
    ramp = np.abs(u - edge)
    ramp *= 2.0
    ramp /= step
    np.minimum(ramp, np.float32(1.0), out=ramp)
    ramp[(edge <= 0) | (edge >= count)] = 1.0  # the pattern's outer edge: see ``inside``
    odd = (np.floor(u).astype(np.int32) & 1).astype(bool)
    np.negative(ramp, out=ramp, where=odd)
    inside = np.minimum(u, count - u)
    inside /= step
    inside += 0.5
    np.clip(inside, 0.0, 1.0, out=inside)
    return ramp, inside


def _chessboard(board: BoardSpec, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
    """The printed chessboard (1 white, 0 black, top-left square black, one square of white
    paper around it, -1 off the paper) at board points (bx, by), as ``board_texture`` has
    it, but exact: each axis is a one-sample box-filtered square wave, and their product
    is the black fraction (the box filters are separable where the grid is locally affine)."""
    u = (bx / board.size_m).astype(np.float32)
    v = (by / board.size_m).astype(np.float32)
    columns, rows = board.cols + 1, board.rows + 1  # squares
    wave_x, inside_x = _square_wave(u, columns)
    wave_y, inside_y = _square_wave(v, rows)
    white = 1.0 - 0.5 * (1.0 + wave_x * wave_y) * inside_x * inside_y
    paper = (u >= -1) & (u <= columns + 1) & (v >= -1) & (v <= rows + 1)
    return np.where(paper, white, -1.0).astype(np.float32)


def _rotation(axis_angle: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis_angle, dtype=np.float64).reshape(3, 1))[0]


def random_poses(
    board: BoardSpec, camera: CameraCalibration, count: int, rng: np.random.Generator,
    *, max_tilt_deg: float = 50.0, border_px: float = 12.0,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Poses (R_cam_board, t_cam_board) as a careful technician takes them: the whole
    pattern in view, the board's centre aimed in turn at the nine cells of a 3 x 3 grid
    (pushed into the image corners as far as the board fits), filling 30-65 % of the
    image width, tilted 20 to ``max_tilt_deg`` degrees about an axis in the board plane
    (tilt is what pins down focal length and principal point)."""
    width_m, height_m = board.extent_m
    centre = np.array([width_m / 2, height_m / 2, 0.0])
    outline = np.array([[0, 0, 0], [width_m, 0, 0], [width_m, height_m, 0], [0, height_m, 0]], dtype=np.float64)
    targets = [(fu, fv) for fv in (0.1, 0.5, 0.9) for fu in (0.1, 0.5, 0.9)]
    order = rng.permutation(len(targets))
    poses: list[tuple[np.ndarray, np.ndarray]] = []
    attempts = 0
    while len(poses) < count:
        attempts += 1
        if attempts > 200 * count:
            raise RuntimeError(f"cannot place {count} views of {board.text} in a {camera.width}x{camera.height} image")
        fill = rng.uniform(0.45, 0.8)
        distance = camera.fx * width_m / (fill * camera.width)
        tilt_axis = rng.uniform(0, np.pi)
        tilt = np.radians(rng.uniform(20.0, max_tilt_deg))
        axis = np.array([np.cos(tilt_axis), np.sin(tilt_axis), 0.0])
        roll = rng.uniform(-0.5, 0.5)
        rotation = _rotation(axis * tilt) @ _rotation(np.array([0.0, 0.0, roll]))
        fu, fv = targets[order[len(poses) % len(targets)]]
        for pull in np.linspace(0.0, 1.0, 11):  # from the cell's extreme towards the centre
            u = (fu + (0.5 - fu) * pull) * camera.width
            v = (fv + (0.5 - fv) * pull) * camera.height
            ray = np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
            translation = ray * distance - rotation @ centre
            corners_cam = outline @ rotation.T + translation
            if np.any(corners_cam[:, 2] < 0.05):
                continue
            uv = project(corners_cam, camera)
            inside = (
                (uv[:, 0] > border_px) & (uv[:, 0] < camera.width - 1 - border_px)
                & (uv[:, 1] > border_px) & (uv[:, 1] < camera.height - 1 - border_px)
            )
            if inside.all():
                poses.append((rotation, translation))
                break
    return poses


def board_views(
    board: BoardSpec,
    camera: CameraCalibration,
    count: int = 20,
    seed: int = 1,
    *,
    corrupt: int = 0,
    wrong_board: BoardSpec | None = None,
    supersample: int = 3,
    noise_sigma: float = 1.5,
) -> list[BoardView]:
    """``count`` views of ``board``; the last ``corrupt`` of them are spoiled in turn by a
    wrong board (``wrong_board``, or the same board stretched 8 % along x when None),
    heavy blur, and a board printed stretched 5 %."""
    rng = np.random.default_rng(seed)
    poses = random_poses(board, camera, count, rng)
    views = []
    for index, (rotation, translation) in enumerate(poses):
        kind = ""
        if index >= count - corrupt:
            kind = ("wrong board", "heavy blur", "stretched print")[(index - (count - corrupt)) % 3]
        if kind == "wrong board" and wrong_board is not None:
            image = render_view(wrong_board, camera, rotation, translation, supersample=supersample, noise_sigma=noise_sigma, rng=rng)
        elif kind == "heavy blur":
            image = render_view(board, camera, rotation, translation, supersample=supersample, noise_sigma=noise_sigma, blur_sigma=4.0, rng=rng)
        elif kind:
            stretch = 1.08 if kind == "wrong board" else 1.05
            image = render_view(board, camera, rotation, translation, supersample=supersample, noise_sigma=noise_sigma, rng=rng, stretch_x=stretch)
        else:
            image = render_view(board, camera, rotation, translation, supersample=supersample, noise_sigma=noise_sigma, rng=rng)
        views.append(BoardView(image, rotation, translation, kind))
    return views


def synthetic_board_camera(width: int = 640, height: int = 512) -> CameraCalibration:
    """A camera like the paper's (same field of view) at a smaller size, with a principal
    point off the centre and a little tangential distortion, so nothing is trivially right."""
    scale = width / 1280.0
    f = 8.0e-3 / 4.8e-6 * scale
    k = np.array([[f * 1.002, 0.0, (width - 1) / 2 + 4.3], [0.0, f, (height - 1) / 2 - 3.1], [0.0, 0.0, 1.0]])
    d = np.array([-0.12, 0.09, 4e-4, -3e-4, 0.0])
    return CameraCalibration(width, height, k, d, "plumb_bob", "synthetic-board-camera")


def write_board_images(
    directory: str | os.PathLike[str], board: BoardSpec, camera: CameraCalibration, count: int = 20,
    seed: int = 1, *, corrupt: int = 0, prefix: str = "img",
) -> list[Path]:
    """Render ``board_views`` into ``directory`` as ``<prefix>_NN.png``; return the paths."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for index, view in enumerate(board_views(board, camera, count, seed, corrupt=corrupt)):
        path = directory / f"{prefix}_{index:02d}.png"
        cv2.imwrite(str(path), view.image)
        paths.append(path)
    return paths


def write_board_sequence(
    root: str | os.PathLike[str], board: BoardSpec, camera: CameraCalibration, count: int = 20,
    seed: int = 1, *, repeats: int = 2, blank_every: int = 4,
) -> int:
    """A recorded sequence (EuRoC layout) of a technician waving the board: each view
    held for ``repeats`` frames, and an empty frame (board out of view) every
    ``blank_every`` views. Returns the number of frames written."""
    from cubeloc.drivers.sequence import SequenceWriter

    blank = np.full((camera.height, camera.width), int(BACKGROUND), np.uint8)
    stamp_ns = 1_700_000_000_000_000_000
    with SequenceWriter(root) as writer:
        for index, view in enumerate(board_views(board, camera, count, seed)):
            frames = [view.image] * repeats + ([blank] if blank_every and index % blank_every == 0 else [])
            for image in frames:
                stamp_ns += 100_000_000  # 10 fps
                writer.write(stamp_ns, image)
        return writer.frames
