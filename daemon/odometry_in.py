"""Wheel odometry into the daemon: a Zenoh subscriber that fills the tracker's buffer.

``[odometry] source = "ros2"``: ``nav_msgs/msg/Odometry`` in CDR as rmw_zenoh_cpp publishes
it, on ``<domain>/<topic>/nav_msgs::msg::dds_::Odometry_/*`` (any type hash: a Humble
robot's ``TypeHashNotSupported`` too; the layout is the same in every distribution).
``"json"``: ``cubeloc.odometry/1`` documents on ``cubeloc/<name>/odometry``::

    {"schema": "cubeloc.odometry/1", "stamp_ns": 1790000000000000000,
     "frame_id": "odom", "child_frame_id": "base_link",
     "position": [x, y, z], "orientation": [qx, qy, qz, qw]}

(the base's pose in the robot's odom frame, metres, stamped when it was measured). A
sample that cannot be read is dropped and counted (``malformed``), as the buffer counts the
stale, out-of-order and non-finite ones; ``status`` shows them under ``extra.odometry``.
"""

from __future__ import annotations

import json
import time

import structlog

from daemon.ros2 import ODOMETRY_TYPE, dds_type_name, typestore
from positioning.tracking.odometry import OdometryBuffer

log = structlog.get_logger()
ODOMETRY_SCHEMA = "cubeloc.odometry/1"


def odometry_key(config) -> str:
    """The key the configured odometry arrives on."""
    if config.odometry.source == "json":
        return f"cubeloc/{config.name}/odometry"
    name = config.ros2.topic(config.odometry.topic)
    return f"{config.ros2.domain_id}/{name.strip('/')}/{dds_type_name(ODOMETRY_TYPE)}/*"


def parse_odometry(doc) -> tuple[int, list[float], list[float]]:
    """(stamp_ns, position, orientation) of a ``cubeloc.odometry/1`` document (a dict);
    ValueError, KeyError or TypeError when it is not one. Also ``cubeloc track --odometry``'s."""
    if not isinstance(doc, dict) or doc.get("schema", ODOMETRY_SCHEMA) != ODOMETRY_SCHEMA:
        raise ValueError(f"not a {ODOMETRY_SCHEMA} document")
    return int(doc["stamp_ns"]), [float(v) for v in doc["position"]], [float(v) for v in doc["orientation"]]


class OdometryInput:
    def __init__(self, session, config, buffer: OdometryBuffer) -> None:
        self.buffer = buffer
        self.key = odometry_key(config)
        self._types = typestore(config.ros2.distro) if config.odometry.source == "ros2" else None
        self._subscriber = session.declare_subscriber(self.key, self._on_sample)
        log.info("odometry in", key=self.key, source=config.odometry.source)

    def _read(self, payload: bytes) -> tuple[int, list[float], list[float]]:
        if self._types is None:
            return parse_odometry(json.loads(payload))
        message = self._types.deserialize_cdr(payload, ODOMETRY_TYPE)
        stamp = int(message.header.stamp.sec) * 1_000_000_000 + int(message.header.stamp.nanosec)
        p, q = message.pose.pose.position, message.pose.pose.orientation
        return stamp, [p.x, p.y, p.z], [q.x, q.y, q.z, q.w]

    def _on_sample(self, sample) -> None:  # a Zenoh thread: never raises
        try:
            stamp, position, orientation = self._read(sample.payload.to_bytes())
        except Exception as exc:  # noqa: BLE001 - whatever a peer sends
            self.buffer.reject("malformed")
            log.debug("odometry sample unreadable", error=str(exc)[:200])
            return
        self.buffer.add(stamp, position, orientation, now_ns=time.time_ns())

    def close(self) -> None:
        try:
            self._subscriber.undeclare()
        except Exception as exc:  # noqa: BLE001 - the session may be closing
            log.debug("undeclare failed", error=str(exc))
