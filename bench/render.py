"""The synthetic camera: time per rendered frame, and how exactly the geometry lands.

Run with ``.venv/bin/python -m bench render``.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time

import numpy as np

from bench.common import markdown_table, median_seconds
from cubeloc.calib.camera_info import CameraCalibration, paper_camera
from cubeloc.fakes import make_trajectory, render_view
from cubeloc.fakes.accuracy import measure_tag_corners
from cubeloc.fakes.sequence import write_synthetic_sequence
from cubeloc.positioning.geometry import look_at
from cubeloc.positioning.target import make_cube

TITLE = "Synthetic camera: render time and corner accuracy (1280x1024)"
FRAMES_PER_TRAJECTORY = 12


def _render_times() -> list[list[object]]:
    rows = []
    for name in ("static", "orbit", "paper", "room_walk"):
        poses = make_trajectory(name)
        picks = [poses[i].T_world_camera for i in np.linspace(0, len(poses) - 1, FRAMES_PER_TRAJECTORY).astype(int)]
        wall, cpu = [], []
        for k, pose in enumerate(picks):
            wall.append(median_seconds(lambda pose=pose, k=k: render_view(pose, seed=k), repeats=3, warmup=1))
            started = time.process_time()  # CPU time: what the frame costs, whatever the load
            render_view(pose, seed=k)
            cpu.append(time.process_time() - started)
        median_ms = 1000 * float(np.median(wall))
        rows.append([
            name, f"{median_ms:.0f}", f"{1000 * float(np.median(cpu)):.0f}", f"{1000 * max(wall):.0f}",
            f"{300 * median_ms / 1000:.0f} s",
        ])
    return rows


def _sequence_time() -> str:
    out = tempfile.mkdtemp(prefix="bench-render-")
    try:
        started = time.perf_counter()
        summary = write_synthetic_sequence(f"{out}/seq", "paper", seconds=10, fps=10, seed=1)
        elapsed = time.perf_counter() - started
    finally:
        shutil.rmtree(out, ignore_errors=True)
    return (
        f"`write_synthetic_sequence` (render + PNG + CSV) of {summary.frames} frames of `paper`: "
        f"{elapsed:.1f} s, {1000 * elapsed / summary.frames:.0f} ms per frame "
        f"(a 300-frame sequence: ~{300 * elapsed / summary.frames:.0f} s)."
    )


def _corner_errors() -> list[list[object]]:
    paper = paper_camera()
    pinhole = CameraCalibration(paper.width, paper.height, paper.camera_matrix, np.zeros(5))
    cube = make_cube()
    rng = np.random.default_rng(2024)
    poses = []
    for _ in range(10):  # like tests/test_fakes.py: 0.9-1.7 m, tags anywhere in the image
        azimuth = np.radians(rng.uniform(-75, -15))
        distance = rng.uniform(0.9, 1.7)
        position = distance * np.array([np.cos(azimuth), np.sin(azimuth), 0.0]) + [0, 0, rng.uniform(0.35, 0.8)]
        poses.append(look_at(position, rng.uniform(-0.2, 0.2, 3)))
    rows = []
    for label, calibration in (("paper camera (barrel distortion)", paper), ("same, no distortion", pinhole)):
        for supersample in (None, 5):
            errors = np.concatenate([
                measure_tag_corners(
                    render_view(p, calibration=calibration, noise_sigma=0.0, supersample=supersample),
                    p, calibration, cube,
                ).errors_px
                for p in poses
            ])
            rows.append([
                label, "adaptive (3-5)" if supersample is None else supersample, errors.size,
                f"{errors.max():.4f}", f"{np.sqrt(np.mean(errors**2)):.4f}",
            ])
    return rows


def run() -> str:
    render_view(look_at(np.array([1.5, -1.5, 0.9]), np.zeros(3)))  # build the room and ray grid
    load = os.getloadavg()[0]
    times = markdown_table(
        ["trajectory", "median ms/frame", "median CPU ms/frame", "max ms/frame", "300 frames"], _render_times()
    )
    corners = markdown_table(
        ["camera", "samples per pixel side (edges)", "corners", "max error px", "RMS px"], _corner_errors()
    )
    return (
        "Render time of `fakes.render_view` (noise on, default room, median of 3 per pose, "
        f"{FRAMES_PER_TRAJECTORY} poses per trajectory; the load average at the start was "
        f"{load:.1f} on {os.cpu_count()} cores):\n\n{times}\n{_sequence_time()}\n\n"
        "Tag corners measured in noise-free renders (edge crossings by area coverage, lines "
        "fitted in undistorted coordinates; `fakes.accuracy`) against `fakes.optics.project` "
        "of the true 3-D corners, 10 poses at 0.9-1.7 m:\n\n" + corners
    )
