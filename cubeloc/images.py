"""Images as positioning takes them: (H, W) uint8 grey, whatever the file or camera gave."""

from __future__ import annotations

import cv2
import numpy as np


def to_mono8(image: np.ndarray, bits: int | None = None) -> np.ndarray:
    """An 8-bit grey image from a decoded one: colour to grey; 16-bit data (Mono10/12/16, in
    the low or the high bits of its container) brought to its top 8 bits. ``bits``: the
    data's depth where the source states it (a camera's pixel format); else the bits it
    really uses, the highest bit set in any pixel (an image file does not say), so that a
    12-bit image's 4095 and a 16-bit one's 65535 both become 255. ValueError for a type
    that is neither."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if image.dtype == np.uint16:
        used = bits if bits is not None else max(8, int(np.bitwise_or.reduce(image, axis=None)).bit_length())
        image = (image >> (used - 8)).astype(np.uint8)
    if image.dtype != np.uint8 or image.ndim != 2:
        raise ValueError(f"expected an 8- or 16-bit grey or colour image, got {image.dtype} {image.shape}")
    return np.ascontiguousarray(image)
