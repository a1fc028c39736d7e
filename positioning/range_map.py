"""The effective range of the single-frame pose (the paper's Fig. 8), as data.

A sweep puts the camera around the target (azimuths at one elevation, distances 0.5-5 m),
aims it at the target's centre, and records for each view how many faces gave the pose
and its position error. A second sweep turns one face away from the camera degree by
degree to find the critical angle beyond which its tag no longer decodes (paper: 77 deg).

Pure: images come from a caller-supplied ``render(T_world_camera, seed) -> image``, so
this module knows nothing of the synthetic camera; ``bench/pose.py`` runs it and draws.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.geometry import Transform, look_at
from cubeloc.positioning.single_frame import TargetPoseProcessor
from cubeloc.positioning.target import Target

Render = Callable[[Transform, int], np.ndarray]


@dataclass(frozen=True)
class RangeCell:
    """One view of the sweep."""

    azimuth_deg: float
    distance_m: float
    planes: int  # faces used by the pose; 0 when there is none
    tags_seen: int
    error_mm: float | None  # camera position error, None without a pose
    status: str


@dataclass(frozen=True)
class FaceAngleSample:
    angle_deg: float  # between the face normal and the line of sight to the camera
    distance_m: float
    decoded: bool


def camera_on_sphere(azimuth_deg: float, elevation_deg: float, distance_m: float) -> Transform:
    """T_world_camera at that direction and distance from the origin, looking at it."""
    azimuth, elevation = np.radians(azimuth_deg), np.radians(elevation_deg)
    direction = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                          np.sin(elevation)])
    return look_at(direction * distance_m, np.zeros(3))


def range_sweep(target: Target, calibration: CameraCalibration, render: Render,
                azimuths_deg: Sequence[float], distances_m: Sequence[float], elevation_deg: float,
                edge_alignment: bool = True) -> list[RangeCell]:
    """One view per (distance, azimuth); ``edge_alignment`` False is the corners-only pose."""
    processor = TargetPoseProcessor(target, calibration, edge_alignment=edge_alignment)
    cells = []
    for i, distance in enumerate(distances_m):
        for j, azimuth in enumerate(azimuths_deg):
            truth = camera_on_sphere(azimuth, elevation_deg, distance)
            processor.reset()
            result = processor.process(render(truth, 1000 * i + j), 0, 0)
            estimate = result.estimate
            error = None
            if estimate is not None:
                error = float(np.linalg.norm(estimate.T_world_camera.translation - truth.translation)) * 1000
            cells.append(RangeCell(float(azimuth), float(distance), estimate.planes if estimate else 0,
                                   len(result.tags_seen), error, result.status))
    return cells


def face_angle_sweep(target: Target, calibration: CameraCalibration, render: Render, tag_id: int,
                     angles_deg: Sequence[float], distances_m: Sequence[float]) -> list[FaceAngleSample]:
    """Move the camera about the world z axis (at the target's height) so that its line of
    sight makes ``angle`` with the normal of side-face tag ``tag_id``; record whether that
    tag decodes."""
    tag = target.tag(tag_id)
    base_azimuth = np.degrees(np.arctan2(tag.normal[1], tag.normal[0]))
    processor = TargetPoseProcessor(target, calibration)
    samples = []
    for i, distance in enumerate(distances_m):
        for j, angle in enumerate(angles_deg):
            truth = camera_on_sphere(base_azimuth + angle, 0.0, distance)
            processor.reset()
            result = processor.process(render(truth, 5000 + 1000 * i + j), 0, 0)
            samples.append(FaceAngleSample(float(angle), float(distance), tag_id in result.tags_seen))
    return samples


def critical_angle(samples: list[FaceAngleSample], distance_m: float) -> float | None:
    """The largest angle up to which the face decodes without a gap at ``distance_m``."""
    at = sorted((s for s in samples if s.distance_m == distance_m), key=lambda s: s.angle_deg)
    last = None
    for sample in at:
        if not sample.decoded:
            break
        last = sample.angle_deg
    return last


def summary_rows(cells: list[RangeCell]) -> list[dict]:
    """Per distance: share of views by faces used, and median errors."""
    rows = []
    for distance in sorted({c.distance_m for c in cells}):
        at = [c for c in cells if c.distance_m == distance]
        three = [c.error_mm for c in at if c.planes == 3]
        two = [c.error_mm for c in at if c.planes == 2]
        rows.append({
            "distance_m": distance,
            "views": len(at),
            "three": sum(c.planes == 3 for c in at),
            "two": sum(c.planes == 2 for c in at),
            "none": sum(c.planes == 0 for c in at),
            "one_face_only": sum(c.planes == 0 and c.tags_seen == 1 for c in at),
            "reasons": sorted({c.status for c in at if c.planes == 0}),
            "median_3_mm": float(np.median(three)) if three else None,
            "median_2_mm": float(np.median(two)) if two else None,
            "max_mm": max((c.error_mm for c in at if c.error_mm is not None), default=None),
        })
    return rows
