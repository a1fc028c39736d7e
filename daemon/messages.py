"""The wire payloads: ``cubeloc.pose/3`` (world -> camera), ``cubeloc.pose/4`` (map ->
base_link, with ``[frames]``), ``cubeloc.map_odom/1`` (map -> odom, with ``[odometry]``)
and ``cubeloc.status/1`` (JSON, UTF-8).

/3 and /4 are /1 and /2 with two more fields: ``source`` (what measured the pose:
``positioning.estimator.PoseSource``) and ``latency_ns`` (publish time minus the capture
stamp, both on the host's CLOCK_REALTIME; null where the pose is not published live).

The pose schema is a user-facing contract (docs: interfaces.md). A pose is checked before
it is encoded: a NaN, an infinity or a non-unit quaternion never reaches the wire; such a
frame raises ``UnpublishablePose`` and publishes nothing.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from cubeloc.positioning.estimator import PoseEstimate
from cubeloc.positioning.frames import RobotFrames
from cubeloc.positioning.geometry import Transform

POSE_SCHEMA = "cubeloc.pose/3"  # world -> camera: /1's fields, source and latency_ns
BASE_POSE_SCHEMA = "cubeloc.pose/4"  # map -> base_link: /3's fields and camera_frame_id (/2 + the same two)
MAP_ODOM_SCHEMA = "cubeloc.map_odom/1"  # map -> odom (REP 105): /4's fields but camera_frame_id
STATUS_SCHEMA = "cubeloc.status/1"

# A camera further than this from the world origin is a solver failure, not a pose.
MAX_POSITION_M = 1.0e4
MAX_MAP_POSITION_M = 1.0e5  # a facility map's origin may be far from the target
QUATERNION_NORM_TOLERANCE = 1e-6


class UnpublishablePose(ValueError):
    """A pose that must not be published (non-finite, non-unit quaternion, absurd)."""


def _finite_list(values: np.ndarray, what: str) -> list[float]:
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(array)):
        raise UnpublishablePose(f"{what} is not finite: {array.tolist()}")
    return [float(v) for v in array]


def pose_payload(seq: int, stamp_ns: int, estimate: PoseEstimate, published_ns: int | None = None
                 ) -> dict[str, Any]:
    """The ``cubeloc.pose/3`` document for one frame (world -> camera), validated;
    ``published_ns`` is the host's CLOCK_REALTIME as it goes out (None: not live)."""
    return _pose_document(POSE_SCHEMA, seq, stamp_ns, estimate, estimate.T_world_camera, estimate.covariance,
                          "world", "camera", published_ns)


def base_pose_payload(seq: int, stamp_ns: int, estimate: PoseEstimate, frames: RobotFrames,
                      published_ns: int | None = None) -> dict[str, Any]:
    """The ``cubeloc.pose/4`` document: the robot's base in the map (``map`` -> ``base_link``
    under ``frames``' names), the same ``seq`` and ``stamp_ns`` as the camera's pose, and
    ``camera_frame_id`` naming the frame the vision measured. Validated as /3."""
    transform, covariance = frames.base_in_map(estimate.T_world_camera, estimate.covariance)
    document = _pose_document(BASE_POSE_SCHEMA, seq, stamp_ns, estimate, transform, covariance,
                              frames.map_frame, frames.base_frame, published_ns, max_position_m=MAX_MAP_POSITION_M)
    document["camera_frame_id"] = frames.camera_frame
    return document


def map_odom_payload(seq: int, stamp_ns: int, estimate: PoseEstimate, frames: RobotFrames, transform: Transform,
                     covariance: np.ndarray | None, spread: Transform | None = None,
                     published_ns: int | None = None) -> dict[str, Any]:
    """The ``cubeloc.map_odom/1`` document: ``map`` -> ``odom`` (``transform`` and its
    ``covariance``, as ``frames.odom_in_map`` gives them for this frame's pose), the same
    ``seq`` and ``stamp_ns``, ``state`` and ``source`` as the camera's pose, validated as /3;
    and ``spread_position``, ``spread_orientation``: the value ``tf`` carries, with its
    steps spread over time (``positioning.frames.SpreadCorrection``; ``spread`` None: the same)."""
    document = _pose_document(MAP_ODOM_SCHEMA, seq, stamp_ns, estimate, transform, covariance, frames.map_frame,
                              frames.odom_frame, published_ns, max_position_m=MAX_MAP_POSITION_M)
    spread = transform if spread is None else spread
    document["spread_position"] = _finite_list(spread.translation, "spread position")
    document["spread_orientation"] = _finite_list(spread.quaternion(), "spread orientation")
    return document


def pose_label(state: str, source: str | None) -> str:
    """A pose's state for people: with its source where that says more (``tracking (held)``;
    a ``cubeloc.pose/1`` document has none)."""
    return state if source in (None, state) else f"{state} ({source})"


def _pose_document(schema: str, seq: int, stamp_ns: int, estimate: PoseEstimate, transform: Transform,
                   covariance: np.ndarray | None, frame_id: str, child_frame_id: str, published_ns: int | None,
                   max_position_m: float = MAX_POSITION_M) -> dict[str, Any]:
    if stamp_ns <= 0:
        raise UnpublishablePose(f"stamp_ns {stamp_ns} is not a capture time")
    position = _finite_list(transform.translation, "position")
    if math.hypot(*position) > max_position_m:
        raise UnpublishablePose(f"position {position} is more than {max_position_m:g} m from the origin")
    rotation = np.asarray(transform.rotation)
    if not np.all(np.isfinite(rotation)):
        raise UnpublishablePose("rotation is not finite")
    # Transform.quaternion() normalises; a rotation matrix that is not a rotation would be
    # hidden by that, so check orthonormality first.
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6) or np.linalg.det(rotation) < 0:
        raise UnpublishablePose("rotation matrix is not a proper rotation")
    orientation = _finite_list(transform.quaternion(), "orientation")
    norm = math.sqrt(sum(q * q for q in orientation))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE or orientation[3] < 0:
        raise UnpublishablePose(f"orientation {orientation} is not a unit quaternion with w >= 0")
    rms = float(estimate.reproj_rms_px)
    if not math.isfinite(rms) or rms < 0:
        raise UnpublishablePose(f"reproj_rms_px {rms} is not a finite non-negative number")
    values = None
    if covariance is not None:
        cov = np.asarray(covariance, dtype=np.float64)
        if cov.shape != (6, 6):
            raise UnpublishablePose(f"covariance has shape {cov.shape}, expected (6, 6)")
        values = _finite_list(cov, "covariance")
    return {
        "schema": schema,
        "seq": int(seq),
        "stamp_ns": int(stamp_ns),
        "frame_id": frame_id,
        "child_frame_id": child_frame_id,
        "position": position,
        "orientation": orientation,
        "state": estimate.state.value,
        "source": estimate.source.value,
        "planes": int(estimate.planes),
        "reproj_rms_px": round(rms, 4),
        "covariance": values,
        "latency_ns": None if published_ns is None else int(published_ns) - int(stamp_ns),
    }


def encode(document: dict[str, Any]) -> bytes:
    # allow_nan=False: a NaN that slipped past the checks fails here rather than on the wire.
    return json.dumps(document, allow_nan=False, separators=(",", ":")).encode("utf-8")


def pose_message(seq: int, stamp_ns: int, estimate: PoseEstimate, published_ns: int | None = None) -> bytes:
    return encode(pose_payload(seq, stamp_ns, estimate, published_ns))


def base_pose_message(seq: int, stamp_ns: int, estimate: PoseEstimate, frames: RobotFrames,
                      published_ns: int | None = None) -> bytes:
    return encode(base_pose_payload(seq, stamp_ns, estimate, frames, published_ns))


def map_odom_message(seq: int, stamp_ns: int, estimate: PoseEstimate, frames: RobotFrames, transform: Transform,
                     covariance: np.ndarray | None, spread: Transform | None = None,
                     published_ns: int | None = None) -> bytes:
    return encode(map_odom_payload(seq, stamp_ns, estimate, frames, transform, covariance, spread, published_ns))


@dataclass(frozen=True)
class CameraStatus:
    source: str
    state: str  # connecting | streaming | reconnecting | ended | stopped
    detail: str = ""
    model: str = ""
    serial: str = ""
    reconnects: int = 0
    dropped: int = 0  # frames the camera backend dropped (bad buffers, gaps, timestamps)


@dataclass(frozen=True)
class StatusReport:
    """What ``cubeloc/<name>/status`` carries once a second."""

    name: str
    state: str  # one word: the camera's state, else the positioning status of the last frame
    detail: str
    stamp_ns: int  # host time of this report
    fps: float  # frames processed per second, over the last few seconds
    frames: int  # frames processed since start
    poses: int  # poses published since start
    dropped_frames: int  # frames overwritten in the queue (processing slower than the camera)
    rejected_poses: int  # poses that failed the wire checks (NaN, non-unit quaternion)
    latency_ms: dict[str, float | None]  # p50, p99: frame leaves the camera driver -> published
    camera: CameraStatus
    uptime_s: float
    version: str
    tags_seen: tuple[int, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)


def status_message(report: StatusReport) -> bytes:
    document = {"schema": STATUS_SCHEMA, **asdict(report)}
    document["tags_seen"] = list(report.tags_seen)
    document["fps"] = round(report.fps, 2)
    document["uptime_s"] = round(report.uptime_s, 1)
    return encode(document)
