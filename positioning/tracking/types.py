"""What the tracker takes in per frame and gives back: frozen, array-valued records."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cubeloc.positioning.estimator import FrameResult
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking.initialiser import InitStatus
from cubeloc.positioning.tracking.map import Keyframe


@dataclass(frozen=True)
class Tracks:
    """Feature tracks in one frame: ids persist from frame to frame while a track lives."""

    ids: np.ndarray  # (N,) int64
    pixels: np.ndarray  # (N, 2) float64, OpenCV pixel convention

    @staticmethod
    def empty() -> Tracks:
        return Tracks(np.zeros(0, np.int64), np.zeros((0, 2)))


@dataclass(frozen=True)
class TargetObservation:
    """A trusted single-frame target pose and the corners it came from."""

    T_world_camera: Transform
    planes: int
    tag_ids: tuple[int, ...]
    reproj_rms_px: float
    corners_px: np.ndarray  # (M, 2) detected corners
    corners_world: np.ndarray  # (M, 3) the same corners on the target (world frame)
    # (6, 6), ROS order as in PoseEstimate: this frame's own (the noise of what it was fitted
    # to), which weighs it against the map and the frames around it; and the share it has
    # in common with them (``TargetPose.systematic_covariance``), which moves them all alike
    covariance: np.ndarray | None = None
    systematic: np.ndarray | None = None

    @property
    def position_covariance(self) -> np.ndarray | None:
        """This frame's own position covariance (3, 3), None without one."""
        return None if self.covariance is None else np.asarray(self.covariance)[:3, :3].copy()

    @property
    def published_covariance(self) -> np.ndarray | None:
        """What the pose's error against the truth may be: the two shares together."""
        if self.covariance is None or self.systematic is None:
            return self.covariance
        return self.covariance + self.systematic


@dataclass(frozen=True)
class TrackedFrame:
    """One frame on its way through the tracker: what came in, and what the tracker made
    of it. ``Tracker.step`` returns it (``TrackerOutput.frame``); ``add_tracks``,
    ``relocalised`` and ``close_loop`` take it and return it as they leave it."""

    stamp_ns: int
    tracks: Tracks  # every track of the frame, the fresh corners added to it included
    xn: np.ndarray  # (N, 2) the tracks' normalised (undistorted) coordinates
    target: TargetObservation | None  # the target as observed in it (trusted or not)
    pose: Transform | None = None  # the tracker's pose of it (None: no pose, or the target's alone)
    keyframe: Keyframe | None = None  # the keyframe it became


@dataclass(frozen=True)
class TrackerOutput:
    """The frame's result, and what the tracker asks of the feature front end."""

    result: FrameResult
    want_features: bool  # detect fresh corners in this image and hand them to add_tracks()
    drop_ids: np.ndarray  # (K,) tracks rejected as outliers: stop following them
    init_status: InitStatus | None = None  # while initialising: why not yet
    frame: TrackedFrame | None = None  # always set by Tracker.step: what add_tracks takes next

    @property
    def keyframe(self) -> bool:
        """The step made this frame a keyframe."""
        return self.frame is not None and self.frame.keyframe is not None
