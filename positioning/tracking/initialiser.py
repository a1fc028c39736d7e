"""Map initialisation on the target: the paper's Algorithms 1 and 2.

Algorithm 1 picks a reference frame A: a trusted target pose (``min_planes`` faces) and at
least ``min_features`` feature tracks. Algorithm 2 then waits for a frame B with a trusted
target pose: the metric relative pose ``dT = T_B * T_A^-1`` comes from the two target
poses, the tracks common to A and B are triangulated with it, and the map is initialised
when more than ``min_points`` points pass cheirality, reprojection and parallax checks.

When the target leaves the view before the median parallax is reached (backing off the
cube in a hall whose walls are 10-30 m away, the cube small at the image's edge), or the
reference's tracks run out, the baseline will grow no longer: of the frames B Algorithm 2
weighed, the one whose matches have the most parallax of their own is the longest metric
baseline the target gave. ``on_departure`` initialises on it with the median test left
out: each match's own rotation-compensated parallax must reach ``min_point_parallax_deg``
instead, besides the points' reprojection and cheirality checks, and more than
``min_points`` of them are needed.

Unlike a five-point initialisation, nothing here estimates the relative pose from the
features, so a scene that is nearly planar or far away does not break it; the features
only need enough parallax for their depths. Every refusal says why (``InitStatus``); the
thresholds are the options' and are never relaxed.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, replace

import numpy as np

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.camera_model import project
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking.options import InitOptions
from cubeloc.positioning.tracking.twoview import (
    baseline_scale_var,
    rotation_compensated_parallax_deg,
    triangulate,
)


class InitStatus(str, enum.Enum):
    INITIALISED = "initialised"
    REFERENCE_SET = "reference_set"  # frame A accepted; waiting for B (not a failure)
    NO_TARGET_POSE = "no_target_pose"  # the frame has no trusted target pose
    TOO_FEW_PLANES = "too_few_planes"  # the target pose rests on fewer faces than required
    UNCERTAIN_TARGET_POSE = "uncertain_target_pose"  # fits or covariance too poor to anchor the map
    TOO_FEW_FEATURES = "too_few_features"  # the reference candidate has < min_features tracks
    TOO_FEW_MATCHES = "too_few_matches"  # fewer than min_points tracks survive from A to B
    TOO_LITTLE_PARALLAX = "too_little_parallax"  # median parallax A<->B below the minimum
    TOO_FEW_POINTS = "too_few_points"  # triangulation left min_points or fewer good points
    UNCERTAIN_BASELINE = "uncertain_baseline"  # the two target poses measure their baseline too poorly


@dataclass(frozen=True)
class InitFrame:
    """What initialisation needs from one frame."""

    stamp_ns: int
    T_world_camera: Transform | None  # the trusted target pose, or None
    planes: int
    track_ids: np.ndarray  # (N,) int64
    xn: np.ndarray  # (N, 2) normalised coordinates
    position_covariance: np.ndarray | None = None  # (3, 3) of the target pose, None: unknown


@dataclass(frozen=True)
class InitResult:
    status: InitStatus
    detail: str
    reference: InitFrame | None = None  # frame A when one is held
    track_ids: np.ndarray | None = None  # (M,) tracks that became points (INITIALISED)
    points_world: np.ndarray | None = None  # (M, 3)
    median_parallax_deg: float = 0.0
    frame: InitFrame | None = None  # frame B (INITIALISED)


class Initialiser:
    """Holds the reference frame between calls; ``step`` once per frame until INITIALISED."""

    def __init__(self, options: InitOptions, fx: float) -> None:
        self.options = options
        self.fx = fx
        self.reference: InitFrame | None = None
        # of the frames B weighed against the reference, the one whose matches have the
        # most parallax of their own (and how many): the target's longest baseline so far
        self.best: InitFrame | None = None
        self._best_usable = 0

    def reset(self) -> None:
        self.reference, self.best, self._best_usable = None, None, 0

    def _trusted(self, frame: InitFrame) -> InitResult | None:
        if frame.T_world_camera is None:
            return InitResult(InitStatus.NO_TARGET_POSE, "no target pose in this frame", self.reference)
        if frame.planes < self.options.min_planes:
            return InitResult(
                InitStatus.TOO_FEW_PLANES,
                f"target pose from {frame.planes} face(s), initialisation needs {self.options.min_planes}",
                self.reference,
            )
        return None

    def try_reference(self, frame: InitFrame) -> InitResult:
        """Algorithm 1: make ``frame`` the reference A if it qualifies."""
        refusal = self._trusted(frame)
        if refusal is not None:
            return refusal
        if len(frame.track_ids) < self.options.min_features:
            return InitResult(
                InitStatus.TOO_FEW_FEATURES,
                f"{len(frame.track_ids)} features, the reference needs {self.options.min_features}",
                self.reference,
            )
        self.reference, self.best, self._best_usable = frame, None, 0
        return InitResult(InitStatus.REFERENCE_SET, f"reference frame with {len(frame.track_ids)} features", frame)

    def step(self, frame: InitFrame) -> InitResult:
        """Algorithm 2 against the held reference (setting one first when there is none).

        On TOO_FEW_MATCHES the reference is dropped (its tracks are gone; the caller makes
        a new one from a frame with fresh features).
        """
        if self.reference is None:
            return self.try_reference(frame)
        refusal = self._trusted(frame)
        if refusal is not None:
            return refusal
        return self._pair(frame, median_test=True)

    def on_departure(self) -> InitResult:
        """The target has left the view before Algorithm 2 initialised: Algorithm 2 on the
        reference and ``best`` (the frame weighed whose matches have the most parallax of
        their own), without the median parallax test; ``step`` does the same when the
        reference's tracks run out. Each ``best`` is tried once."""
        if self.reference is None or self.best is None:
            return InitResult(InitStatus.NO_TARGET_POSE, "no target pose in this frame", self.reference)
        best, self.best = self.best, None  # tried once
        return self._pair(best, median_test=False)

    def _pair(self, frame: InitFrame, median_test: bool) -> InitResult:
        a = self.reference
        common, ia, ib = np.intersect1d(a.track_ids, frame.track_ids, assume_unique=True, return_indices=True)
        if len(common) <= self.options.min_points:
            detail = f"{len(common)} features survive from the reference, more than {self.options.min_points} needed"
            if median_test and self.best is not None:
                # the reference's tracks run out: its baseline will grow no longer
                result = self.on_departure()
                if result.status is InitStatus.INITIALISED:
                    return result
                detail += f"; on the longest baseline, {result.detail}"
            self.reference, self.best = None, None
            return InitResult(InitStatus.TOO_FEW_MATCHES, detail)
        scale_std = baseline_scale_std(a, frame)
        if scale_std > self.options.max_scale_std:
            return InitResult(
                InitStatus.UNCERTAIN_BASELINE,
                f"the baseline known to {100 * scale_std:.0f} %, {100 * self.options.max_scale_std:.0f} % needed",
                a)
        xa, xb = a.xn[ia], frame.xn[ib]
        parallax = rotation_compensated_parallax_deg(a.T_world_camera, frame.T_world_camera, xa, xb)
        median = float(np.median(parallax))
        if median_test:
            usable = int(np.count_nonzero(parallax >= self.options.min_point_parallax_deg))
            if self.best is None or usable >= self._best_usable:
                self.best, self._best_usable = frame, usable
        if median_test and median < self.options.min_parallax_deg:
            return InitResult(
                InitStatus.TOO_LITTLE_PARALLAX,
                f"median parallax {median:.2f} deg, {self.options.min_parallax_deg} deg needed",
                a, median_parallax_deg=median,
            )
        result = triangulate(
            a.T_world_camera, frame.T_world_camera, xa, xb, self.fx,
            self.options.max_reproj_px, self.options.min_point_parallax_deg,
        )
        good = result.good
        if not median_test:
            # the median test stood for the baseline; without it each match's own
            # rotation-compensated parallax must (a pure rotation triangulates noise)
            good = good & (parallax >= self.options.min_point_parallax_deg)
        result = replace(result, good=good)
        survivors = int(good.sum())
        if survivors <= self.options.min_points:
            return InitResult(
                InitStatus.TOO_FEW_POINTS,
                f"{survivors} of {len(common)} points pass the checks, more than {self.options.min_points} needed",
                a, median_parallax_deg=median,
            )
        self.best = None  # done
        return InitResult(
            InitStatus.INITIALISED,
            f"{survivors} points from {len(common)} matches, median parallax {median:.2f} deg"
            + ("" if median_test else " (the target's longest baseline)"),
            a, common[result.good], result.points_world[result.good], median, frame,
        )


def baseline_scale_std(a: InitFrame, b: InitFrame) -> float:
    """The relative standard deviation of the baseline between two target poses (the scale
    a map begun on them has, ``twoview.baseline_scale_var``); 0 when either covariance is
    unknown."""
    if a.position_covariance is None or b.position_covariance is None:
        return 0.0
    baseline = b.T_world_camera.translation - a.T_world_camera.translation
    return float(np.sqrt(baseline_scale_var(baseline, a.position_covariance, b.position_covariance)))


def out_of_view(pose: Transform, points_world: np.ndarray, calibration: CameraCalibration) -> bool:
    """Does none of ``points_world`` (the target's corners) lie in the image seen from
    ``pose``? The target has left the view, rather than been missed in a frame that shows it."""
    camera = pose.inverse().apply(points_world)
    front = camera[:, 2] > 1e-3
    if not front.any():
        return True
    pixels = project(camera[front], calibration)
    return not np.any((pixels[:, 0] >= 0) & (pixels[:, 0] < calibration.width) & (pixels[:, 1] >= 0)
                      & (pixels[:, 1] < calibration.height))
