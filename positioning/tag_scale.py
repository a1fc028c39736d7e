"""Does the target file's tag size match the printed tags? One scale factor on every tag's
size about its centre, fitted with the pose (needs two planes: on one, size and distance
trade off). A cube whose tags are printed 5 % too large, or a tag_size given as the inner
white square, shows as a scale far from 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.camera_model import project_pose
from cubeloc.positioning.corner_pose import TargetPose
from cubeloc.positioning.detection import TagDetection
from cubeloc.positioning.target import Target

# The tag-size consistency check warns beyond this relative disagreement.
SCALE_WARNING_FRACTION = 0.02


@dataclass(frozen=True)
class ScaleCheck:
    """Tag size against the layout, as the detections see it.

    ``tag_scale`` is the factor on every tag's size (about its centre) that fits the image
    best; 1 when the configured tag size matches the printed one. For a cube,
    ``implied_side_m`` is the cube edge that the detections imply if the tag size is right.
    """

    tag_scale: float
    implied_side_m: float | None
    configured_side_m: float | None
    agrees: bool
    configured_tag_m: float | None = None

    def message(self) -> str:
        if self.implied_side_m is not None:
            tag_mm = self.configured_tag_m * self.tag_scale * 1000
            return (
                f"the tags look {self.tag_scale:.3f} times the configured size: printed tags of "
                f"{tag_mm:.1f} mm if the {self.configured_side_m * 1000:.1f} mm cube edge is right, or a "
                f"{self.implied_side_m * 1000:.1f} mm cube edge if the {self.configured_tag_m * 1000:.1f} mm "
                "tag size is: tag_size is the outer edge of the black border"
            )
        return (
            f"the tags look {self.tag_scale:.3f} times the configured size relative to their "
            "layout: check the tag size (outer edge of the black border)"
        )


def check_tag_scale(
    detections: list[TagDetection], target: Target, calibration: CameraCalibration, pose: TargetPose
) -> ScaleCheck | None:
    """Fit one scale factor on the tags' sizes about their centres, with the pose.

    Needs two planes or more (on one plane, tag size and distance trade off). A cube whose
    tags are printed 5 % too large, or a tag_size given as the inner white square, shows
    here as a scale far from 1.
    """
    ours = [d for d in detections if d.tag_id in pose.tag_ids]
    if pose.planes < 2 or not ours:
        return None
    tag_ids = tuple(d.tag_id for d in ours)
    corners = target.corners_of(tag_ids).reshape(-1, 4, 3)
    centers = corners.mean(axis=1, keepdims=True)
    offsets = (corners - centers).reshape(-1, 3)
    centers = np.repeat(centers.reshape(-1, 3), 4, axis=0)
    pixels = np.concatenate([d.corners for d in ours]).astype(np.float64)
    T_camera_world = pose.T_world_camera.inverse()

    def residuals(x: np.ndarray) -> np.ndarray:
        points = centers + x[6] * offsets
        return (project_pose(points, x[:3], x[3:6], calibration) - pixels).ravel()

    start = np.concatenate([T_camera_world.rvec(), T_camera_world.translation, [1.0]])
    fit = least_squares(residuals, start, method="lm", x_scale=np.concatenate([np.full(6, 0.01), [0.01]]))
    scale = float(fit.x[6])
    configured = target.cube.side_m if target.cube is not None else None
    implied = configured / scale if configured is not None else None
    tag_m = target.cube.tag_size_m if target.cube is not None else None
    return ScaleCheck(scale, implied, configured, abs(scale - 1.0) <= SCALE_WARNING_FRACTION, tag_m)
