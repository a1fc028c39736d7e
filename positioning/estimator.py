"""The one interface between the daemon loop and positioning.

The daemon hands every frame to a ``FrameProcessor`` and publishes what comes back. The
single-frame target pose is one processor; the tracker (initialisation on the target,
then visual tracking) is another. Both see the target through one
``positioning.observer.TargetObserver`` (search, edge-aligned pose, checks), take arrays
and return frozen
dataclasses: no cameras, Zenoh, logging configuration or printing in here.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from cubeloc.positioning.geometry import Transform


class PoseState(str, enum.Enum):
    """How a published pose stands to the ones before it (the ``state`` field of the pose
    messages); what measured it is its ``PoseSource``."""

    TARGET = "target"  # from the target alone, this frame
    TRACKING = "tracking"  # from the tracker, the target not (fully) in view
    RELOCALISED = "relocalised"  # the first pose after a visible correction (a jump)


class PoseSource(str, enum.Enum):
    """What measured a published pose (the ``source`` field of ``cubeloc.pose/3`` and
    ``/4``): a fusion filter weighs a held or odometry pose differently from a measured one,
    though its covariance already says how far it may be off."""

    TARGET = "target"  # the target's pose in this frame (with the map's points in view when fused)
    MAP = "map"  # the map's points in view (PnP), with the wheels' motion when there is odometry
    # too few map points in view: the orientation from the tracks' rays, the position from
    # the points left, the wheels or the motion model (for at most hold.max_s; nothing in
    # view: the motion model alone for at most motion.max_coast_s)
    HELD = "held"
    ODOMETRY = "odometry"  # lost: the wheels' motion since the last camera pose ("bridged")
    RELOCALISED = "relocalised"  # this image matched to the map's keyframes


# The source a pose has when its maker names none: what its state implies.
_SOURCE_OF_STATE = {PoseState.TARGET: PoseSource.TARGET, PoseState.TRACKING: PoseSource.MAP,
                    PoseState.RELOCALISED: PoseSource.RELOCALISED}


@dataclass(frozen=True)
class PoseEstimate:
    """A trustworthy camera pose for one frame.

    ``covariance`` is 6x6 over (x, y, z, rotation about X, rotation about Y, rotation about
    Z) of the camera in the world frame (ROS ``PoseWithCovariance`` order), or None.
    """

    T_world_camera: Transform
    state: PoseState
    planes: int  # target faces used (0 when the target played no part)
    tag_ids: tuple[int, ...]
    reproj_rms_px: float
    covariance: np.ndarray | None = None  # (6, 6)
    source: PoseSource | None = None  # None: the one ``state`` implies (target, map, relocalised)

    def __post_init__(self) -> None:
        if self.source is None:
            object.__setattr__(self, "source", _SOURCE_OF_STATE[self.state])


class FeatureState(enum.IntEnum):
    """What a tracked feature is to the tracker in a frame (``FrameView.feature_states``)."""

    MAPPED = 0  # has a 3-D map point that agreed with this frame's pose
    CANDIDATE = 1  # followed, no map point yet (it gets one when a keyframe triangulates it)
    OUTLIER = 2  # its map point disagreed with this frame's pose: dropped


@dataclass(frozen=True)
class FrameView:
    """What the processor saw in the frame, in pixels, for a viewer (``cubeloc run
    --foxglove``, MCAP): the target's tags decoded (id, (4, 2) corners) and the tracked
    features (N, 2) with their ``FeatureState``."""

    tags: tuple[tuple[int, np.ndarray], ...] = ()
    features: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 2)))
    feature_states: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.uint8))


@dataclass(frozen=True)
class FrameResult:
    """What positioning made of one frame: a pose, or the reason there is none.

    ``status`` is a short machine-readable word shown on the daemon's ``status``
    (``"ok"``, ``"no_target"``, ``"one_face"``, ``"reprojection"``, ``"initialising"``,
    ``"lost"``...); ``detail`` is for humans.
    """

    estimate: PoseEstimate | None
    status: str
    detail: str = ""
    tags_seen: tuple[int, ...] = ()
    view: FrameView | None = None


class FrameProcessor(Protocol):
    """Turns frames into poses. Implementations keep state between frames (the last pose,
    a map) and must never raise for a bad image: they return a FrameResult saying why."""

    def process(self, image: np.ndarray, stamp_ns: int, seq: int) -> FrameResult: ...

    def reset(self) -> None:
        """Forget all state and re-initialise on the target (the ``reset`` queryable)."""
