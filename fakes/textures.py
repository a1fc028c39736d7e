"""Procedural, seeded textures for the synthetic room: rich, non-repeating, trackable.

A visual tracker needs corners and blobs at many scales that never repeat, so a texture
is multi-scale value noise (smooth shading, like stains and light falloff) with random
shapes drawn over it at several sizes: rectangles, discs, polygons, lines and letters
(posters, tiles, cables, labels). Everything comes from one ``numpy`` generator, so the
same seed gives the same texture bit for bit.
"""

from __future__ import annotations

import string

import cv2
import numpy as np

_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX)


def value_noise(height: int, width: int, rng: np.random.Generator, octaves: int = 6) -> np.ndarray:
    """(H, W) float32 noise in [0, 1]: random grids upsampled bicubically, 1/f amplitudes."""
    total = np.zeros((height, width), np.float32)
    amplitude_sum = 0.0
    for octave in range(octaves):
        cells = 2 ** (octave + 2)
        small = rng.random((max(2, height * cells // max(height, width)), cells), dtype=np.float32)
        total += cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC) / (octave + 1)
        amplitude_sum += 1.0 / (octave + 1)
    total /= amplitude_sum
    low, high = np.percentile(total, (1, 99))
    return np.clip((total - low) / max(high - low, 1e-6), 0.0, 1.0)


def procedural_texture(
    height: int,
    width: int,
    rng: np.random.Generator,
    *,
    mean: float = 0.55,
    contrast: float = 0.35,
    shapes_per_mpx: float = 2500.0,
) -> np.ndarray:
    """(H, W) uint8 texture: noise background plus random shapes at all scales."""
    base = mean + contrast * (value_noise(height, width, rng) - 0.5)
    image = np.clip(base * 255.0, 0, 255).astype(np.uint8)
    count = int(shapes_per_mpx * height * width / 1e6)
    # sizes log-uniform from a few texels to ~80 (a few centimetres to ~30 cm at 4 mm
    # texels), plus a few large posters: features at every range, background still shows
    largest = max(4.0, min(80.0, max(height, width) / 4.0))
    sizes = np.exp(rng.uniform(np.log(3.0), np.log(largest), count))
    poster_size = max(largest, max(height, width) / 8.0)
    posters = np.exp(rng.uniform(np.log(largest), np.log(poster_size), max(1, count // 100)))
    for size in np.concatenate([posters, sizes]):
        _draw_shape(image, rng, float(size), mean, contrast)
    return image


def _draw_shape(image: np.ndarray, rng: np.random.Generator, size: float, mean: float, contrast: float) -> None:
    height, width = image.shape
    x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
    # greys around the surface's mean, sometimes far off it (dark and bright marks)
    grey = int(np.clip(255 * (mean + rng.normal(0.0, 1.2 * contrast)), 0, 255))
    kind = int(rng.integers(0, 5))
    s = max(2, int(size))
    if kind == 0:
        angle = rng.uniform(0, np.pi)
        box = cv2.boxPoints(((x, y), (s, s * rng.uniform(0.3, 1.0)), np.degrees(angle)))
        cv2.fillPoly(image, [box.astype(np.int32)], grey, cv2.LINE_AA)
    elif kind == 1:
        cv2.circle(image, (x, y), s // 2, grey, -1 if rng.random() < 0.7 else max(1, s // 8), cv2.LINE_AA)
    elif kind == 2:
        count = int(rng.integers(3, 7))
        angles = np.sort(rng.uniform(0, 2 * np.pi, count))
        radii = rng.uniform(0.3, 1.0, count) * s / 2
        points = np.column_stack([x + radii * np.cos(angles), y + radii * np.sin(angles)])
        cv2.fillPoly(image, [points.astype(np.int32)], grey, cv2.LINE_AA)
    elif kind == 3:
        angle = rng.uniform(0, 2 * np.pi)
        end = (int(x + s * np.cos(angle)), int(y + s * np.sin(angle)))
        cv2.line(image, (x, y), end, grey, max(1, s // 12), cv2.LINE_AA)
    else:
        letters = "".join(rng.choice(list(string.ascii_uppercase + string.digits), int(rng.integers(1, 6))))
        scale = max(0.3, s / 30.0)
        font = _FONTS[int(rng.integers(0, len(_FONTS)))]
        cv2.putText(image, letters, (x, y), font, scale, grey, max(1, int(scale * 2)), cv2.LINE_AA)
