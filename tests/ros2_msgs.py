"""The ROS 2 messages cubeloc sends, as pycdr2 structs written from their .msg definitions:
a CDR decoder that shares nothing with daemon/ros2.py (which serialises with rosbags).
Shared by the test modules (``from ros2_msgs import decode``, like helpers)."""

# no "from __future__ import annotations": pycdr2 reads the annotations as types
from dataclasses import dataclass

from pycdr2 import IdlStruct
from pycdr2.types import array, float64, int32, sequence, uint8, uint32

POSE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"


@dataclass
class Time(IdlStruct, typename="builtin_interfaces/msg/Time"):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs/msg/Header"):
    stamp: Time
    frame_id: str


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs/msg/Vector3"):
    x: float64
    y: float64
    z: float64


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs/msg/Quaternion"):
    x: float64
    y: float64
    z: float64
    w: float64


@dataclass
class Pose(IdlStruct, typename="geometry_msgs/msg/Pose"):
    position: Vector3  # Point has the layout of Vector3
    orientation: Quaternion


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs/msg/PoseWithCovariance"):
    pose: Pose
    covariance: array[float64, 36]


@dataclass
class PoseWithCovarianceStamped(IdlStruct, typename=POSE_TYPE):
    header: Header
    pose: PoseWithCovariance


@dataclass
class Twist(IdlStruct, typename="geometry_msgs/msg/Twist"):
    linear: Vector3
    angular: Vector3


@dataclass
class TwistWithCovariance(IdlStruct, typename="geometry_msgs/msg/TwistWithCovariance"):
    twist: Twist
    covariance: array[float64, 36]


@dataclass
class Odometry(IdlStruct, typename=ODOMETRY_TYPE):
    header: Header
    child_frame_id: str
    pose: PoseWithCovariance
    twist: TwistWithCovariance


@dataclass
class TransformMsg(IdlStruct, typename="geometry_msgs/msg/Transform"):
    translation: Vector3
    rotation: Quaternion


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs/msg/TransformStamped"):
    header: Header
    child_frame_id: str
    transform: TransformMsg


@dataclass
class TFMessage(IdlStruct, typename=TF_TYPE):
    transforms: sequence[TransformStamped]


@dataclass
class RegionOfInterest(IdlStruct, typename="sensor_msgs/msg/RegionOfInterest"):
    x_offset: uint32
    y_offset: uint32
    height: uint32
    width: uint32
    do_rectify: bool


@dataclass
class CameraInfo(IdlStruct, typename=CAMERA_INFO_TYPE):
    header: Header
    height: uint32
    width: uint32
    distortion_model: str
    d: sequence[float64]
    k: array[float64, 9]
    r: array[float64, 9]
    p: array[float64, 12]
    binning_x: uint32
    binning_y: uint32
    roi: RegionOfInterest


@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs/msg/KeyValue"):
    key: str
    value: str


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs/msg/DiagnosticStatus"):
    level: uint8  # byte: OK 0, WARN 1, ERROR 2, STALE 3
    name: str
    message: str
    hardware_id: str
    values: sequence[KeyValue]


@dataclass
class DiagnosticArray(IdlStruct, typename=DIAGNOSTICS_TYPE):
    header: Header
    status: sequence[DiagnosticStatus]


DECODERS = {"pose": PoseWithCovarianceStamped, "odometry": Odometry, "tf": TFMessage, "camera_info": CameraInfo,
            "diagnostics": DiagnosticArray}


def decode(payload: bytes, role: str):
    """A payload of ``role`` (pose, odometry, tf, camera_info, diagnostics): CDR, little endian."""
    assert payload[:4] == b"\x00\x01\x00\x00", payload[:4]
    return DECODERS[role].deserialize(payload)
