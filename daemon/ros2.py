"""ROS 2 over Zenoh, as ``rmw_zenoh_cpp`` sends it, with no ROS installed here.

Followed: rmw_zenoh's ``docs/design.md`` at commit 99a6a2b (the rolling branch, 2025, Zenoh
1.x: "Topic and Service name mapping to Zenoh key expressions", "Graph Cache",
"Publishers"), with ``liveliness_utils.cpp`` (3411fde: ``qos_to_keyexpr``, ``mangle_name``),
``qos.cpp`` (7efeee2: the default QoS the key leaves out), ``attachment_helpers.cpp`` and
``rmw_publisher_data.cpp`` (3e19ec7: the attachment, TRANSIENT_LOCAL as an advanced
publisher with a cache and publisher detection). What goes on the wire:

* data key ``<domain_id>/<fully qualified topic, no leading '/'>/<DDS type name>/<type hash>``,
  e.g. ``0/robot7/cubeloc/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/RIHS01_2643...``;
* payload: CDR, little endian, with its 4-byte encapsulation header (``rosbags``);
* attachment: sequence number (int64 LE, from 1 per publisher), source timestamp (int64 LE,
  ns since the epoch), the publisher's GID (length byte 16, then 16 bytes), written with
  Zenoh's own serializer (``zenoh.ext.z_serialize``): 33 bytes;
* liveliness tokens ``@ros2_lv/<domain>/<session id>/<node id>/<entity id>/<NN|MP>/<enclave>/
  <namespace>/<node>[/<topic>/<type>/<hash>/<qos>]`` with '/' mangled to '%' and the QoS
  written as ``qos_to_keyexpr`` does (a default value is left empty: RELIABLE, VOLATILE,
  KEEP_LAST, depth 42, infinite durations, AUTOMATIC liveliness).

Type hashes (RIHS01, REP 2016) are computed by ``rosbags`` from the chosen distribution's
message definitions, never typed in. The GID is any 16 bytes unique to the publisher
(rmw_zenoh hashes its token with XXH3-128; here BLAKE2b of the token, as opaque).
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass

import numpy as np
import structlog

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.daemon.messages import StatusReport
from cubeloc.positioning.estimator import PoseEstimate, PoseSource
from cubeloc.positioning.frames import RobotFrames
from cubeloc.positioning.geometry import Transform

log = structlog.get_logger()

ADMIN_SPACE = "@ros2_lv"
DEFAULT_DEPTH = 42  # rmw_zenoh's default history depth: left out of a token's QoS
POSE_DEPTH = 10
# The twist is not measured: zero, with this variance ((m/s)^2, (rad/s)^2) on the diagonal.
UNKNOWN_TWIST_VARIANCE = 1.0e6
POSE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
# diagnostic_msgs/msg/DiagnosticStatus levels
OK, WARN, ERROR = 0, 1, 2


def diagnostic_level(report: StatusReport) -> tuple[int, str]:
    """The level of a status report on ``/diagnostics``, and why: ERROR without a camera
    or lost (no pose, after there was one); WARN held on rays, bridged by the wheels, or
    no pose yet (waiting for the target at the start); OK while the target, the map or a
    relocalisation measures the pose."""
    camera = report.camera
    if camera.state != "streaming":
        return ERROR, f"camera {camera.state}" + (f": {camera.detail}" if camera.detail else "")
    source = report.extra.get("source")
    if source in (PoseSource.HELD.value, PoseSource.ODOMETRY.value):
        return WARN, f"pose {source}" + (f" ({report.detail})" if report.detail else "")
    if source is not None:
        return OK, f"pose from the {source}"
    why = f"{report.state}" + (f": {report.detail}" if report.detail else "")
    if report.extra.get("lost_now_s", 0.0) > 0.0:
        return ERROR, f"no pose for {report.extra['lost_now_s']:.1f} s ({why})"
    return WARN, f"no pose yet ({why})"


def typestore(distro: str):
    """The message definitions of a ROS 2 distribution (rosbags)."""
    from rosbags.typesys import Stores, get_typestore

    stores = {"jazzy": Stores.ROS2_JAZZY, "kilted": Stores.ROS2_KILTED, "lyrical": Stores.ROS2_LYRICAL,
              "rolling": Stores.LATEST}
    return get_typestore(stores[distro])


def dds_type_name(typename: str) -> str:
    """``geometry_msgs/msg/Pose`` -> ``geometry_msgs::msg::dds_::Pose_`` (the CDR type name)."""
    package, kind, name = typename.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    return name.replace("/", "%")


def qos_keyexpr(depth: int, transient_local: bool = False) -> str:
    """rmw_zenoh's ``qos_to_keyexpr`` for a RELIABLE, KEEP_LAST publisher of ``depth``,
    VOLATILE or TRANSIENT_LOCAL (1), every duration infinite, liveliness AUTOMATIC."""
    durability = "1" if transient_local else ""
    history_depth = "" if depth == DEFAULT_DEPTH else str(depth)
    # reliability : durability : history,depth : deadline s,ns : lifespan s,ns : liveliness,s,ns
    return f":{durability}:,{history_depth}:,:,:,,"


@dataclass(frozen=True)
class RosTopic:
    """One publisher's names on the Zenoh side."""

    typename: str  # e.g. geometry_msgs/msg/PoseWithCovarianceStamped
    name: str  # fully qualified: /robot7/cubeloc/pose
    key: str  # the data key
    token: str  # its liveliness token
    gid: bytes  # 16 bytes


def ros_topic(typename: str, name: str, type_hash: str, domain_id: int, session_id: str, node_id: int,
              entity_id: int, namespace: str, node_name: str, depth: int, transient_local: bool = False) -> RosTopic:
    dds = dds_type_name(typename)
    key = f"{domain_id}/{name.strip('/')}/{dds}/{type_hash}"
    token = "/".join([ADMIN_SPACE, str(domain_id), session_id, str(node_id), str(entity_id), "MP", "%",
                      mangle(namespace or "/"), node_name, mangle(name), mangle(dds), type_hash,
                      qos_keyexpr(depth, transient_local)])
    return RosTopic(typename, name, key, token, hashlib.blake2b(token.encode(), digest_size=16).digest())


def node_token(domain_id: int, session_id: str, node_id: int, namespace: str, node_name: str) -> str:
    return "/".join([ADMIN_SPACE, str(domain_id), session_id, str(node_id), str(node_id), "NN", "%",
                     mangle(namespace or "/"), node_name])


class Ros2Publisher:
    """The node and its publishers on a Zenoh session: ``publish(seq, stamp_ns, estimate)``
    per pose, the camera's CameraInfo at start and after a reload (transient local, depth
    1), ``publish_diagnostics`` per status; ``close`` undeclares everything (tokens first,
    so the graph sees the node go). With ``map_odom`` (the robot's wheel odometry in),
    ``tf`` carries what ``publish_map_odom`` is given, ``map`` -> ``odom`` (REP 105), and
    never ``map`` -> ``base_link``: the odometry's ``odom`` -> ``base_link`` is the base's
    only parent."""

    def __init__(self, session, config, frames: RobotFrames, calibration: CameraCalibration,
                 map_odom: bool = False) -> None:
        import zenoh
        import zenoh.ext

        self._zenoh = zenoh
        self._types = typestore(config.distro)
        self._frames = frames
        self._map_odom = map_odom
        self.session_id = str(session.info.zid())
        domain, namespace, node = config.domain_id, config.namespace, config.node_name
        self._node_name = node
        self.node_token = node_token(domain, self.session_id, 0, namespace, node)
        wanted = [("pose", POSE_TYPE, config.topics.pose), ("odometry", ODOMETRY_TYPE, config.topics.odometry),
                  ("camera_info", CAMERA_INFO_TYPE, config.topics.camera_info)]
        if config.publish_tf:
            wanted.append(("tf", TF_TYPE, config.topics.tf))
        if config.topics.diagnostics:
            wanted.append(("diagnostics", DIAGNOSTICS_TYPE, config.topics.diagnostics))
        self.topics: dict[str, RosTopic] = {}
        for entity_id, (role, typename, name) in enumerate(wanted, start=1):
            latched = role == "camera_info"
            self.topics[role] = ros_topic(typename, config.topic(name), self._types.hash_rihs01(typename), domain,
                                          self.session_id, 0, entity_id, namespace, node,
                                          1 if latched else POSE_DEPTH, latched)
        self._sequence = dict.fromkeys(self.topics, 0)
        self._tokens = [session.liveliness().declare_token(self.node_token)]
        self._publishers = {}
        for role, topic in self.topics.items():
            if role == "camera_info":  # rmw_zenoh's TRANSIENT_LOCAL: a cache late joiners query
                self._publishers[role] = zenoh.ext.declare_advanced_publisher(
                    session, topic.key, cache=zenoh.ext.CacheConfig(max_samples=1), publisher_detection=True)
            else:
                self._publishers[role] = session.declare_publisher(
                    topic.key, congestion_control=zenoh.CongestionControl.DROP, reliability=zenoh.Reliability.RELIABLE)
            self._tokens.append(session.liveliness().declare_token(topic.token))
        self._closed = False
        self.publish_camera_info(calibration)
        log.info("ros2 publishers declared", node=f"{namespace}/{node}", domain_id=domain, distro=config.distro,
                 topics={role: topic.name for role, topic in self.topics.items()})

    # -- messages ------------------------------------------------------------------------
    def _msg(self, typename: str, **fields):
        return self._types.types[typename](**fields)

    def _header(self, stamp_ns: int, frame_id: str):
        stamp = self._msg("builtin_interfaces/msg/Time", sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        return self._msg("std_msgs/msg/Header", stamp=stamp, frame_id=frame_id)

    def _pose(self, transform):
        x, y, z = (float(v) for v in transform.translation)
        qx, qy, qz, qw = (float(v) for v in transform.quaternion())
        return self._msg("geometry_msgs/msg/Pose", position=self._msg("geometry_msgs/msg/Point", x=x, y=y, z=z),
                         orientation=self._msg("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw))

    def messages(self, stamp_ns: int, estimate: PoseEstimate) -> dict[str, object]:
        """role -> message, for one pose: the base in the map under [frames]' names."""
        frames = self._frames
        transform, covariance = frames.base_in_map(estimate.T_world_camera, estimate.covariance)
        covariance = np.zeros(36) if covariance is None else np.asarray(covariance, np.float64).reshape(36)
        header = self._header(stamp_ns, frames.map_frame)
        with_covariance = self._msg("geometry_msgs/msg/PoseWithCovariance", pose=self._pose(transform),
                                    covariance=covariance)
        zero = self._msg("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)
        twist = self._msg("geometry_msgs/msg/TwistWithCovariance",
                          twist=self._msg("geometry_msgs/msg/Twist", linear=zero, angular=zero),
                          covariance=(np.eye(6) * UNKNOWN_TWIST_VARIANCE).reshape(36))
        out = {"pose": self._msg(POSE_TYPE, header=header, pose=with_covariance),
               "odometry": self._msg(ODOMETRY_TYPE, header=header, child_frame_id=frames.base_frame,
                                     pose=with_covariance, twist=twist)}
        if "tf" in self.topics and not self._map_odom:
            out["tf"] = self._tf(stamp_ns, frames.base_frame, transform)
        return out

    def _tf(self, stamp_ns: int, child_frame: str, transform: Transform):
        """A TFMessage of ``map`` -> ``child_frame``."""
        pose = self._pose(transform)
        moved = self._msg("geometry_msgs/msg/Transform",
                          translation=self._msg("geometry_msgs/msg/Vector3", x=pose.position.x, y=pose.position.y,
                                                z=pose.position.z),
                          rotation=pose.orientation)
        return self._msg(TF_TYPE, transforms=[self._msg(
            "geometry_msgs/msg/TransformStamped", header=self._header(stamp_ns, self._frames.map_frame),
            child_frame_id=child_frame, transform=moved)])

    def diagnostics(self, report: StatusReport):
        """The DiagnosticArray of one status report: one status, named after the node."""
        level, message = diagnostic_level(report)
        latency = report.latency_ms or {}
        values = {"state": report.state, "source": report.extra.get("source") or "", "fps": f"{report.fps:.1f}",
                  "poses": str(report.poses), "dropped_frames": str(report.dropped_frames),
                  "latency_p50_ms": "" if latency.get("p50") is None else f"{latency['p50']:.1f}",
                  "latency_p99_ms": "" if latency.get("p99") is None else f"{latency['p99']:.1f}",
                  "held_frames": str(report.extra.get("held_frames", 0)),
                  "lost_now_s": str(report.extra.get("lost_now_s", 0.0)), "camera": report.camera.state,
                  "version": report.version}
        camera = report.camera
        status = self._msg("diagnostic_msgs/msg/DiagnosticStatus", level=level, name=f"{self._node_name}: pose",
                           message=message, hardware_id=" ".join(p for p in (camera.model, camera.serial) if p),
                           values=[self._msg("diagnostic_msgs/msg/KeyValue", key=k, value=v) for k, v in values.items()])
        return self._msg(DIAGNOSTICS_TYPE, header=self._header(report.stamp_ns, ""), status=[status])

    def _camera_info(self, calibration: CameraCalibration, stamp_ns: int):
        k = np.asarray(calibration.camera_matrix, np.float64)
        projection = np.zeros((3, 4))
        projection[:, :3] = k
        roi = self._msg("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                        do_rectify=False)
        return self._msg(CAMERA_INFO_TYPE, header=self._header(stamp_ns, self._frames.camera_frame),
                         height=int(calibration.height), width=int(calibration.width),
                         distortion_model=calibration.distortion_model,
                         d=np.asarray(calibration.distortion, np.float64).ravel(), k=k.ravel(),
                         r=np.eye(3).ravel(), p=projection.ravel(), binning_x=0, binning_y=0, roi=roi)

    # -- the wire ------------------------------------------------------------------------
    def attachment(self, role: str) -> bytes:
        """The next attachment of a publisher (rmw_zenoh's AttachmentData)."""
        from zenoh.ext import Int64, z_serialize

        self._sequence[role] += 1
        return z_serialize((Int64(self._sequence[role]), Int64(time.time_ns()), self.topics[role].gid)).to_bytes()

    def _put(self, role: str, message) -> None:
        payload = bytes(self._types.serialize_cdr(message, self.topics[role].typename))
        self._publishers[role].put(payload, attachment=self.attachment(role))

    def publish_camera_info(self, calibration: CameraCalibration) -> None:
        """The camera's CameraInfo, kept for late joiners (at start, and after a reload)."""
        if not self._closed:
            self._put("camera_info", self._camera_info(calibration, time.time_ns()))

    def publish(self, seq: int, stamp_ns: int, estimate: PoseEstimate) -> None:
        if self._closed:
            return
        for role, message in self.messages(stamp_ns, estimate).items():
            self._put(role, message)

    def publish_map_odom(self, stamp_ns: int, T_map_odom: Transform) -> None:
        """``map`` -> ``odom`` on ``tf`` (with ``publish_tf`` and ``map_odom``)."""
        if not self._closed and self._map_odom and "tf" in self.topics:
            self._put("tf", self._tf(stamp_ns, self._frames.odom_frame, T_map_odom))

    def publish_diagnostics(self, report: StatusReport) -> None:
        """``report`` on ``/diagnostics`` (with ``topics.diagnostics`` set)."""
        if not self._closed and "diagnostics" in self.topics:
            self._put("diagnostics", self.diagnostics(report))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for entity in [*self._tokens, *self._publishers.values()]:
            try:
                entity.undeclare()
            except self._zenoh.ZError as exc:  # the session may already be closing
                log.debug("undeclare failed", error=str(exc))
