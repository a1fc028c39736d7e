"""Where a dark-to-bright step lies along short straight intensity profiles.

The one measurement under the corner refinement (``detection.refine_corners``: profiles
across a tag's four outer edges) and the edge alignment (``edge_alignment``: profiles
across every cell edge). Each profile has the same number of samples, from its own start
point in its own steps (pixels, bilinear, the border replicated). A profile is a clean
step when its two end quarters differ by at least ``min_contrast`` grey levels and it
crosses their mid-level exactly once (not noise, not a second edge, not glare or an
occluder); with ``rising_only`` (the corner refinement) only its dark-to-bright crossings
are counted, so that a profile running on past the white margin into something dark
still counts (steep faces: such an edge of a tag seen at 70 deg had no clean profile
left, and the range map lost two of its two-face poses when both counted every crossing).
The step's position comes from its area, not from where it crosses 50 %: pixels average
light over their area, which keeps the area of a step (blurred or not) but pulls the 50 %
crossing towards pixel centres by up to 0.08 px. The plateau levels are per group (an
edge, or a run of cell edges: means over its clean profiles), so their noise does not
enter each profile. On request each clean profile's spread (its second moment about the
step: the blur's variance) comes too; the edge alignment sizes the covariance's systematic
share by it.

Compiled with numba (``positioning/jit.py``, whose ``warm_up`` compiles it before the first
frame). The arrays always reach the kernel as read-only views (``jit.read_only``): numba
compiles a read-only and a writable array apart, and camera frames come both ways. The profiles are
a few thousand short loops of arithmetic; in numpy they were some thirty array operations
of 20-100 us each, which made this measurement most of the corner refinement's and the
edge alignment's time; compiled, 1188 profiles of 15 samples take ~0.2 ms.
"""

from __future__ import annotations

import numpy as np

from cubeloc.positioning.jit import compiled, read_only


def _steps(image, starts, deltas, samples, groups, group_count, min_contrast, rising_only, with_spread):
    """(position (K,) in samples from each start, clean (K,), clean profiles a group, spread (K,):
    the blur's variance in samples^2 of each clean profile when ``with_spread``, else 0)."""
    height, width = image.shape
    count = starts.shape[0]
    quarter = max(2, samples // 4)
    profile = np.empty(samples)
    dark = np.empty(count)
    bright = np.empty(count)
    total = np.empty(count)
    spread = np.zeros(count)
    clean = np.zeros(count, np.bool_)
    for k in range(count):
        for s in range(samples):
            x = min(max(starts[k, 0] + s * deltas[k, 0], 0.0), width - 1.0)
            y = min(max(starts[k, 1] + s * deltas[k, 1], 0.0), height - 1.0)
            col, row = min(int(x), width - 2), min(int(y), height - 2)
            fx, fy = x - col, y - row
            v00, v01 = np.float64(image[row, col]), np.float64(image[row, col + 1])
            v10, v11 = np.float64(image[row + 1, col]), np.float64(image[row + 1, col + 1])
            top = v00 + (v01 - v00) * fx
            profile[s] = top + (v10 + (v11 - v10) * fx - top) * fy
        lo = 0.0
        hi = 0.0
        for s in range(quarter):
            lo += profile[s]
            hi += profile[samples - 1 - s]
        lo /= quarter
        hi /= quarter
        middle = (lo + hi) / 2.0
        crossings = 0
        area = profile[0]
        for s in range(1, samples):
            before, after = profile[s - 1] >= middle, profile[s] >= middle
            crossings += (after and not before) if rising_only else before != after
            area += profile[s]
        dark[k], bright[k] = lo, hi
        total[k] = area - 0.5 * (profile[0] + profile[samples - 1])  # trapezoids
        clean[k] = hi - lo >= min_contrast and crossings == 1
        if with_spread and clean[k]:
            # the step's spread: for a step blurred by a Gaussian of variance v (samples^2),
            # the integral of (profile - ideal step) times the distance from the step is -v / 2
            # (zero-mean noise stays zero-mean in it); the step and its levels are the profile's own
            at = (samples - 1) - (total[k] - lo * (samples - 1)) / (hi - lo)
            moment = 0.0
            for s in range(samples):
                ideal = 1.0 if s > at else 0.0
                moment += ((profile[s] - lo) / (hi - lo) - ideal) * (s - at)
            spread[k] = -2.0 * moment
    per_group = np.zeros(group_count, np.int64)
    dark_sum = np.zeros(group_count)
    bright_sum = np.zeros(group_count)
    for k in range(count):
        if clean[k]:
            per_group[groups[k]] += 1
            dark_sum[groups[k]] += dark[k]
            bright_sum[groups[k]] += bright[k]
    position = np.empty(count)
    for k in range(count):
        g = groups[k]
        n = max(per_group[g], 1)
        dark_level = dark_sum[g] / n
        contrast = max(bright_sum[g] / n - dark_level, 1e-6)
        # the profile's area above the dark level, in samples of full contrast
        position[k] = (samples - 1) - (total[k] - dark_level * (samples - 1)) / contrast
    return position, clean, per_group, spread


def _warm_up() -> None:  # Mono8, the cameras' and the renderer's
    step_positions(np.zeros((4, 4), np.uint8), np.zeros((1, 2)), np.full((1, 2), 0.5), 4, np.zeros(1, np.int64), 1, 1.0)


_compiled = compiled(_steps, _warm_up)  # see positioning/jit.py


def step_positions(image: np.ndarray, starts: np.ndarray, deltas: np.ndarray, samples: int,
                   groups: np.ndarray, group_count: int, min_contrast: float, rising_only: bool = False,
                   spread: bool = False) -> tuple[np.ndarray, ...]:
    """Steps along K profiles of ``samples`` samples: sample s of profile k is at
    ``starts[k] + s * deltas[k]`` (pixels) in ``image`` (2-D, any real type). ``groups``
    (K,) in ``range(group_count)`` pool the plateau levels.

    Returns (position (K,): the step, in samples from the start; clean (K,); clean profiles
    in each group (group_count,)), and with ``spread`` the step's blur (K,): its variance
    in samples^2, as a Gaussian blur's (noisy a profile: pool many). A position or a spread
    is meaningful for clean profiles only."""
    if samples < 4:
        raise ValueError(f"a profile needs at least 4 samples, not {samples}")
    image = read_only(image)  # one compiled signature per pixel type (see the module's docstring)
    found = _compiled()(image, read_only(starts, np.float64), read_only(deltas, np.float64), int(samples),
                        read_only(groups, np.int64), int(group_count), float(min_contrast), bool(rising_only),
                        bool(spread))
    return found if spread else found[:3]
