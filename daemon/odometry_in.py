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

from cubeloc.daemon.ros2 import ODOMETRY_TYPE, dds_type_name, typestore
from cubeloc.positioning.tracking.odometry import OdometryBuffer

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


def read_odometry_file(path) -> list[tuple[int, int, list[float], list[float]]]:
    """The samples of a file of ``cubeloc.odometry/1`` documents, one per line, in the
    order they arrived: (arrival_ns, stamp_ns, position, orientation), the arrival being
    the row's ``arrival_ns`` or else its stamp. InputFileError naming the line otherwise."""
    from cubeloc.jsonlines import read_json_lines

    def parse(row: dict) -> tuple[int, int, list[float], list[float]]:
        stamp, position, orientation = parse_odometry(row)
        return int(row.get("arrival_ns", stamp)), stamp, position, orientation

    return read_json_lines(path, parse, ODOMETRY_SCHEMA)


class OdometryLog(OdometryBuffer):
    """A buffer that also keeps every sample it accepts as a ``cubeloc.odometry/1`` row
    with its ``arrival_ns`` (``cubeloc record --odometry``): what ``cubeloc track
    --odometry`` and ``cubeloc calibrate-mount`` read back."""

    def __init__(self, odom_frame: str = "odom", base_frame: str = "base_link", **kwargs) -> None:
        super().__init__(**kwargs)
        self.frames = (odom_frame, base_frame)
        self.rows: list[dict] = []
        self.key = ""  # the Zenoh key it is fed from, for messages

    def add(self, stamp_ns: int, position, quaternion, now_ns: int | None = None) -> str | None:
        problem = super().add(stamp_ns, position, quaternion, now_ns)
        if problem is None:
            self.rows.append({"schema": ODOMETRY_SCHEMA, "stamp_ns": int(stamp_ns), "frame_id": self.frames[0],
                              "child_frame_id": self.frames[1], "position": [float(v) for v in position],
                              "orientation": [float(v) for v in quaternion],
                              "arrival_ns": int(now_ns if now_ns is not None else stamp_ns)})
        return problem


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
