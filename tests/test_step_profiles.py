"""The step-profile kernel under the corner refinement and the edge alignment."""

from __future__ import annotations

import os
import subprocess
import sys

import cv2
import numba
import numpy as np
import pytest

from cubeloc.positioning import step_profiles
from cubeloc.positioning.detection import _fit_lines
from cubeloc.positioning.step_profiles import step_positions

DARK, BRIGHT = 30.0, 210.0


def _edge_image(normal_deg: float, offset: float, size: int = 40) -> np.ndarray:
    """A straight dark-to-bright edge through (20, 20) + offset * normal, each pixel the
    mean over its area (16x16 supersampled), as a camera sees it."""
    normal = np.array([np.cos(np.radians(normal_deg)), np.sin(np.radians(normal_deg))])
    sub = (np.arange(16) + 0.5) / 16 - 0.5
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float64)
    x = xs[:, :, None, None] + sub[None, None, None, :]
    y = ys[:, :, None, None] + sub[None, None, :, None]
    bright = ((x - 20) * normal[0] + (y - 20) * normal[1] - offset) > 0
    return np.round(DARK + (BRIGHT - DARK) * bright.mean(axis=(2, 3))).astype(np.uint8)


@pytest.mark.parametrize("normal_deg", [0.0, 90.0, 33.0, 200.0])
@pytest.mark.parametrize("offset", [-0.37, 0.0, 0.25, 0.61])
def test_a_step_is_found_where_it_is_to_a_hundredth_of_a_pixel(normal_deg, offset):
    image = _edge_image(normal_deg, offset)
    normal = np.array([np.cos(np.radians(normal_deg)), np.sin(np.radians(normal_deg))])
    along = np.array([-normal[1], normal[0]])
    # 9 profiles along the edge, each from 3 px on the dark side to 3 px on the bright one
    centres = np.array([20.0, 20.0]) + np.linspace(-6, 6, 9)[:, None] * along
    starts = centres - 3.0 * normal
    deltas = np.tile(0.25 * normal, (9, 1))
    position, clean, per_group = step_positions(image, starts, deltas, 25, np.zeros(9, int), 1, 25.0)
    assert clean.all() and per_group.tolist() == [9]
    found = position * 0.25 - 3.0  # along the normal from the profile's centre
    # Axis-aligned, one grey level of rounding is ~0.006 px of a 180-level step; oblique,
    # bilinear sampling across the pixel grid adds up to ~0.06 px a profile, which the
    # line fit or the pose averages out along the edge (mean within 0.01 px).
    axis_aligned = normal_deg % 90.0 == 0.0
    assert np.abs(found - offset).max() < (0.01 if axis_aligned else 0.08), found
    assert abs(found.mean() - offset) < 0.01, found


def test_profiles_that_are_not_one_clean_step_are_left_out():
    image = _edge_image(0.0, 0.0)
    image[:, 14:16] = BRIGHT  # a bright stripe on the dark side, crossed twice more
    starts = np.array([[17.0, 10.0], [12.0, 30.0], [17.0, 30.0]])
    deltas = np.tile([0.25, 0.0], (3, 1))
    low = image.copy()
    low[25:35] = (DARK + 10.0 * (image[25:35] > 100)).astype(np.uint8)  # 10 grey levels of step
    position, clean, per_group = step_positions(image, starts[:2], deltas[:2], 25, np.array([0, 1]), 2, 25.0)
    assert clean.tolist() == [True, False] and per_group.tolist() == [1, 0]
    _, clean, _ = step_positions(low, starts[2:], deltas[2:], 25, np.zeros(1, int), 1, 25.0)
    assert not clean[0]


def test_the_plateau_levels_are_pooled_over_a_group():
    """A profile that starts on a brighter patch of the dark side is pulled to its group's
    dark level, so the patch moves its step less than it moves a profile on its own."""
    image = _edge_image(0.0, 0.0)
    image[20:24, :18] += 20  # brighter dark side under the second profile only
    starts = np.array([[17.0, 10.0], [17.0, 21.5], [17.0, 30.0]])
    deltas = np.tile([0.25, 0.0], (3, 1))
    alone, _, _ = step_positions(image, starts, deltas, 25, np.array([0, 1, 2]), 3, 25.0)
    pooled, _, _ = step_positions(image, starts, deltas, 25, np.zeros(3, int), 1, 25.0)
    assert abs(alone[0] - pooled[0]) > 0.05 and abs(alone[0] - alone[2]) < 1e-9
    assert pooled[1] != alone[1]


def test_it_runs_where_no_compiled_kernel_can_be_cached(tmp_path):
    """A read-only install without NUMBA_CACHE_DIR: compiled in the process, with a warning."""
    env = dict(os.environ, NUMBA_CACHE_LOCATOR_CLASSES="ZipCacheLocator")  # finds no folder
    code = ("import warnings, numpy as np; warnings.simplefilter('always')\n"
            "from cubeloc.positioning.step_profiles import step_positions\n"
            "img = np.zeros((20, 20), np.uint8); img[:, 10:] = 200\n"
            "p, c, _ = step_positions(img, [[6.0, 5.0]], [[0.25, 0.0]], 33, [0], 1, 25.0)\n"
            "print(float(p[0]) * 0.25 + 6.0, bool(c[0]))\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["9.5", "True"]
    assert "without a disk cache" in result.stderr and "NUMBA_CACHE_DIR" in result.stderr


def test_read_only_and_writable_frames_share_one_compiled_kernel():
    """Camera buffers arrive read-only, synthetic frames writable: numba types them apart,
    and a second compilation on a live frame held the GIL ~2.5 s."""
    writable = _edge_image(0.0, 0.0).astype(np.uint8)
    read_only = np.frombuffer(writable.tobytes(), np.uint8).reshape(writable.shape)
    assert not read_only.flags.writeable
    starts, deltas = np.array([[17.0, 10.0]]), np.array([[0.25, 0.0]])
    a = step_positions(writable, starts, deltas, 25, np.zeros(1, int), 1, 25.0)
    b = step_positions(read_only, starts, deltas, 25, np.zeros(1, int), 1, 25.0)
    assert a[0][0] == b[0][0] and a[1][0] and writable.flags.writeable
    uint8_kernels = [s for s in step_profiles._compiled().signatures if s[0].dtype == numba.uint8]
    assert len(uint8_kernels) == 1, uint8_kernels


def test_a_target_observer_has_every_kernel_ready_before_its_first_frame():
    """Each kernel compiled once when the observer is built, with the argument types of
    real use: frames of both kinds (camera buffers read-only, renders writable), the full
    search with the corner refinement and the edge alignment, compile nothing more."""
    code = ("import numpy as np\n"
            "from cubeloc.calib.camera_info import paper_camera\n"
            "from cubeloc.fakes import render_view\n"
            "from cubeloc.positioning import jit\n"
            "from cubeloc.positioning.observer import TargetObserver\n"
            "from cubeloc.positioning.range_map import camera_on_sphere\n"
            "from cubeloc.positioning.target import make_cube\n"
            "assert len(jit.KERNELS) >= 5 and all(k.cache_info().currsize == 0 for k, _ in jit.KERNELS)\n"
            "observer = TargetObserver(make_cube(), paper_camera())\n"
            "ready = [len(k().signatures) for k, _ in jit.KERNELS]\n"
            "image = render_view(camera_on_sphere(40.0, 30.0, 2.0), seed=3)\n"
            "frozen = np.frombuffer(image.tobytes(), np.uint8).reshape(image.shape)\n"
            "poses = [observer.observe(frame, None, 0).pose for frame in (image, frozen)]\n"
            "assert all(p is not None and p.reproj_rms_px < 0.1 for p in poses), poses\n"
            "print(ready, [len(k().signatures) for k, _ in jit.KERNELS])\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    ready, after = result.stdout.strip().split("] [")
    assert ready.strip("[") == after.strip("]"), result.stdout
    assert set(ready.strip("[").split(", ")) == {"1"}, result.stdout


def test_the_edge_line_fit_is_total_least_squares_after_one_outlier_pass():
    """``detection._fit_lines`` (compiled): each edge's line through its points, the
    direction of their largest spread, a point ~3 sigma off left out; None below
    MIN_EDGE_SAMPLES points on an edge."""
    rng = np.random.default_rng(4)
    along = np.linspace(0.0, 60.0, 40)
    angles = np.radians([10.0, 100.0, 190.0, 280.0])
    points = np.stack([[200.0, 300.0] + along[:, None] * [np.cos(a), np.sin(a)] for a in angles])
    normals = np.stack([[-np.sin(a), np.cos(a)] for a in angles])
    # bounded noise: within 1.9x its mean distance, so only the planted outlier goes
    points += rng.uniform(-0.03, 0.03, (4, 40, 1)) * normals[:, None, :]
    points[1, 7] += 1.5 * normals[1]  # one step found on the wrong edge
    use = np.ones((4, 40), bool)
    centre, direction = _fit_lines(points, use)
    for e in range(4):
        kept = np.arange(40) != 7 if e == 1 else np.ones(40, bool)
        expected = points[e, kept].mean(axis=0)
        _, _, vt = np.linalg.svd(points[e, kept] - expected)
        assert np.allclose(centre[e], expected, atol=1e-9)
        assert abs(abs(direction[e] @ vt[0]) - 1.0) < 1e-12
    assert abs(abs(direction[1] @ [np.cos(angles[1]), np.sin(angles[1])]) - 1.0) < 1e-5
    use[2, 5:] = False  # 5 points left on one edge
    assert _fit_lines(points, use) is None


def test_with_rising_only_a_profile_may_run_on_into_something_dark():
    """The corner refinement's profiles cross a tag's white margin and, on a steep face,
    run on into what lies beyond it: its step still counts (rising_only); the edge
    alignment's profiles, across a cell edge, must cross once either way."""
    image = _edge_image(0.0, 0.0)
    image[:, 23:] = DARK  # dark again 3 px past the edge
    starts, deltas = np.array([[17.0, 10.0], [17.0, 30.0]]), np.tile([0.25, 0.0], (2, 1))
    strict = step_positions(image, starts, deltas, 25, np.zeros(2, int), 1, 25.0)
    rising = step_positions(image, starts, deltas, 25, np.zeros(2, int), 1, 25.0, rising_only=True)
    assert not strict[1].any()
    assert rising[1].all()


@pytest.mark.parametrize("sigma", [0.0, 0.8, 1.2])
def test_a_steps_spread_is_its_blur(sigma):
    """The spread (the profile's second moment about its step, ``spread=True``) pooled over
    profiles is the blur's variance: a sharp edge's is the pixels' own (0.5 px here, box and
    bilinear sampling), a defocused one's adds in quadrature (measured 0.52, 0.96, 1.25 px)."""
    rng = np.random.default_rng(3)
    image = _edge_image(0.0, 0.17).astype(np.float64)
    if sigma:
        image = cv2.GaussianBlur(image, (0, 0), sigma)
    image = np.clip(np.rint(image + rng.normal(0.0, 2.0, image.shape)), 0, 255).astype(np.uint8)
    centres = np.column_stack([np.full(30, 20.0), np.linspace(8.0, 32.0, 30)])
    starts, deltas = centres - [5.0, 0.0], np.tile([0.5, 0.0], (30, 1))
    _, clean, _, spread = step_positions(image, starts, deltas, 21, np.zeros(30, int), 1, 25.0, spread=True)
    assert clean.all()
    blur = np.sqrt(np.mean(spread) * 0.25)  # samples of 0.5 px
    assert abs(blur - np.hypot(0.5, sigma)) < 0.12, blur
