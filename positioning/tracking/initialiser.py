"""Map initialisation on the target: the paper's Algorithms 1 and 2.

Algorithm 1 picks a reference frame A: a trusted target pose (``min_planes`` faces) and at
least ``min_features`` feature tracks. Algorithm 2 then waits for a frame B with a trusted
target pose: the metric relative pose ``dT = T_B * T_A^-1`` comes from the two target
poses, the tracks common to A and B are triangulated with it, and the map is initialised
when more than ``min_points`` points pass cheirality, reprojection and parallax checks.

Unlike a five-point initialisation, nothing here estimates the relative pose from the
features, so a scene that is nearly planar or far away does not break it; the features
only need enough parallax for their depths. Every refusal says why (``InitStatus``); the
thresholds are the options' and are never relaxed.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from positioning.geometry import Transform
from positioning.tracking.options import InitOptions
from positioning.tracking.twoview import rotation_compensated_parallax_deg, triangulate


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


@dataclass(frozen=True)
class InitFrame:
    """What initialisation needs from one frame."""

    stamp_ns: int
    T_world_camera: Transform | None  # the trusted target pose, or None
    planes: int
    track_ids: np.ndarray  # (N,) int64
    xn: np.ndarray  # (N, 2) normalised coordinates


@dataclass(frozen=True)
class InitResult:
    status: InitStatus
    detail: str
    reference: InitFrame | None = None  # frame A when one is held
    track_ids: np.ndarray | None = None  # (M,) tracks that became points (INITIALISED)
    points_world: np.ndarray | None = None  # (M, 3)
    median_parallax_deg: float = 0.0


class Initialiser:
    """Holds the reference frame between calls; ``step`` once per frame until INITIALISED."""

    def __init__(self, options: InitOptions, fx: float) -> None:
        self.options = options
        self.fx = fx
        self.reference: InitFrame | None = None

    def reset(self) -> None:
        self.reference = None

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
        self.reference = frame
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
        a = self.reference
        common, ia, ib = np.intersect1d(a.track_ids, frame.track_ids, assume_unique=True, return_indices=True)
        if len(common) <= self.options.min_points:
            self.reference = None
            return InitResult(
                InitStatus.TOO_FEW_MATCHES,
                f"{len(common)} features survive from the reference, more than {self.options.min_points} needed",
            )
        xa, xb = a.xn[ia], frame.xn[ib]
        parallax = rotation_compensated_parallax_deg(a.T_world_camera, frame.T_world_camera, xa, xb)
        median = float(np.median(parallax))
        if median < self.options.min_parallax_deg:
            return InitResult(
                InitStatus.TOO_LITTLE_PARALLAX,
                f"median parallax {median:.2f} deg, {self.options.min_parallax_deg} deg needed",
                a, median_parallax_deg=median,
            )
        result = triangulate(
            a.T_world_camera, frame.T_world_camera, xa, xb, self.fx,
            self.options.max_reproj_px, self.options.min_point_parallax_deg,
        )
        survivors = int(result.good.sum())
        if survivors <= self.options.min_points:
            return InitResult(
                InitStatus.TOO_FEW_POINTS,
                f"{survivors} of {len(common)} points pass the checks, more than {self.options.min_points} needed",
                a, median_parallax_deg=median,
            )
        return InitResult(
            InitStatus.INITIALISED,
            f"{survivors} points from {len(common)} matches, median parallax {median:.2f} deg",
            a, common[result.good], result.points_world[result.good], median,
        )
