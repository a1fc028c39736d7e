"""A hand-built target: the nominal tags each moved and turned a little, as glued.

For the target calibration (``positioning.target_calibration``): render the perturbed
target (the renderer takes any Target) and check that calibrating it against the
nominal file finds the perturbation.
"""

from __future__ import annotations

import cv2
import numpy as np

from cubeloc.positioning.target import Tag, Target


def perturbed_target(target: Target, seed: int, max_shift_m: float = 0.003, max_rotation_deg: float = 2.0,
                     fixed: tuple[int, ...] = ()) -> Target:
    """``target`` with every tag not in ``fixed`` rotated about its centre by up to
    ``max_rotation_deg`` (random axis) and moved by up to ``max_shift_m`` (random
    direction), drawn from ``seed``. An explicit-tag target (no cube shorthand)."""
    rng = np.random.default_rng(seed)
    tags = []
    for tag in target.tags:
        corners = tag.corners
        if tag.tag_id not in fixed:
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            angle = np.radians(rng.uniform(0.5, 1.0) * max_rotation_deg)
            rotation = cv2.Rodrigues(axis * angle)[0]
            shift = rng.normal(size=3)
            shift *= rng.uniform(0.5, 1.0) * max_shift_m / np.linalg.norm(shift)
            corners = (corners - tag.center) @ rotation.T + tag.center + shift
        tags.append(Tag(tag.tag_id, corners, tag.face))
    return Target(target.family, tuple(tags), None, f"{target.source or 'target'} perturbed (seed {seed})")


def explicit(target: Target) -> Target:
    """The same tags without the cube shorthand (rendered as plates, like a perturbed one)."""
    return Target(target.family, target.tags, None, target.source)
