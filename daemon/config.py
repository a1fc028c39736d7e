"""The daemon's configuration: one validated, frozen pydantic tree.

Read from a TOML file (``--config``, else ``/etc/cubeloc/cubeloc.toml`` when present, else
built-in defaults), then environment overrides ``CUBELOC_<SECTION>__<FIELD>`` (for example
``CUBELOC_CAMERA__EXPOSURE_US=5000``, ``CUBELOC_NAME=robot7``; values are parsed as JSON
where they can be, so ``'["tcp/10.0.0.2:7447"]'`` is a list). An invalid value fails at
start with one line naming the field, the value and where it came from.
"""

from __future__ import annotations

import json
import math
import os
import re
import socket
import sys
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from scipy.spatial.transform import Rotation

from cubeloc.drivers.base import CameraSettings
from cubeloc.errors import ConfigError
from cubeloc.positioning.frames import RobotFrames
from cubeloc.positioning.geometry import Transform

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

DEFAULT_CONFIG_PATH = Path("/etc/cubeloc/cubeloc.toml")
ENV_PREFIX = "CUBELOC_"
# A hand-typed quaternion to 4 decimals is within 1e-4 of unit norm; further is a typo.
QUATERNION_TOLERANCE = 1e-3
MAX_PLACEMENT_M = 1.0e4
MAX_MOUNT_M = 10.0  # a camera further from the robot's base is a unit slip (mm for m)
FRAME_NAME = re.compile(r"[A-Za-z_/][A-Za-z0-9_/]*")
ROS_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CameraConfig(Section):
    source: str = Field("aravis", description="BACKEND[:ARGUMENT], see daemon.cameras")
    width: int = Field(1280, gt=0, le=16384)
    height: int = Field(1024, gt=0, le=16384)
    offset_x: int = Field(0, ge=0)
    offset_y: int = Field(0, ge=0)
    exposure_us: float | None = Field(None, gt=0, le=10_000_000, description="None: auto exposure")
    gain_db: float | None = Field(None, ge=0, le=60, description="None: auto gain")
    frame_rate_hz: float | None = Field(None, gt=0, le=1000)
    trigger: Literal["free", "software", "line0"] = "free"
    frame_timeout_s: float = Field(1.0, gt=0, le=60)
    stream_buffers: int = Field(8, ge=2, le=64, description="buffers in flight (usbfs budget: cubeloc doctor)")
    usb_mode: Literal["async", "sync", "default"] = Field("async", description="USB3 Vision transfers")
    usb_bandwidth_mbps: float | None = Field(None, gt=0, le=40_000, description="None: the camera's own limit")
    pixel_format: Literal["Mono8", "Mono10", "Mono12", "Mono16"] = Field(
        "Mono8", description="Mono10/12/16 (unpacked) where the camera has them, brought to 8 bits")

    def settings(self) -> CameraSettings:
        return CameraSettings(
            width=self.width,
            height=self.height,
            offset_x=self.offset_x,
            offset_y=self.offset_y,
            exposure_us=self.exposure_us,
            gain_db=self.gain_db,
            frame_rate_hz=self.frame_rate_hz,
            trigger=self.trigger,
            stream_buffers=self.stream_buffers,
            usb_mode=self.usb_mode,
            usb_bandwidth_mbps=self.usb_bandwidth_mbps,
            pixel_format=self.pixel_format,
        )


class PositioningConfig(Section):
    calibration: Path = Path("/etc/cubeloc/camera.yaml")
    target: Path = Path("/etc/cubeloc/target.yaml")
    allow_two_faces: bool = True
    allow_one_face: bool = False
    max_reproj_rms_px: float = Field(1.5, gt=0, le=100)
    # tracker: initialise on the target, then track (positioning.tracking); target: the
    # single-frame target pose only (no pose while the cube is out of view)
    mode: Literal["tracker", "target"] = "tracker"
    # the tracker: when the view comes back to a place mapped long ago, move the map being
    # tracked onto it (docs/tracker.md, "Loop closure"; off: not yet honest on the family)
    loop_closure: bool = False
    # the tracker: once the cube has left the view, hold the map's scale to the floor it
    # measured, when the camera kept its height while the cube was in view (a wheeled robot)
    # and a textured floor was seen (docs/tracker.md, "The floor"; off: it moves the family
    # both ways)
    floor: bool = False


class ZenohConfig(Section):
    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = True
    config_file: Path | None = Field(None, description="a Zenoh JSON5 file (TLS, access control)")

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        for endpoint in value:
            protocol, sep, address = endpoint.partition("/")
            if not sep or not address or protocol not in {"tcp", "udp", "tls", "quic", "ws", "unixsock-stream"}:
                raise ValueError(f"{endpoint!r} is not a Zenoh endpoint such as 'tcp/192.168.1.10:7447'")
        return value


class DaemonConfig(Section):
    """Rates and back-off of the ``cubeloc run`` loop (daemon/service.py)."""

    status_period_s: float = Field(1.0, gt=0, le=60, description="period of the status publication")
    reconnect_initial_s: float = Field(0.5, gt=0, le=60, description="first wait before reopening a camera")
    reconnect_max_s: float = Field(10.0, gt=0, le=600, description="longest wait between reopen attempts")
    timeout_streak: int = Field(3, ge=1, le=1000, description="frame timeouts in a row that mean: reopen the camera")


class Placement(Section):
    """A fixed rigid transform, measured by hand: ``xyz`` in metres and at most one of
    ``quaternion`` ([x, y, z, w], unit), ``rpy`` (radians) or ``rpy_deg`` (degrees): roll
    about X, pitch about Y, yaw about Z, applied in that order about the fixed axes (URDF,
    tf2). No rotation given: the identity."""

    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quaternion: tuple[float, float, float, float] | None = None
    rpy: tuple[float, float, float] | None = None
    rpy_deg: tuple[float, float, float] | None = None

    @field_validator("xyz", "quaternion", "rpy", "rpy_deg")
    @classmethod
    def _finite(cls, value):
        if value is not None and not all(math.isfinite(v) for v in value):
            raise ValueError("every number must be finite")
        return value

    @field_validator("xyz")
    @classmethod
    def _plausible(cls, value):
        if max(abs(v) for v in value) > MAX_PLACEMENT_M:
            raise ValueError(f"more than {MAX_PLACEMENT_M:g} m: metres expected")
        return value

    @field_validator("quaternion")
    @classmethod
    def _unit(cls, value):
        if value is not None:
            norm = math.sqrt(sum(v * v for v in value))
            if abs(norm - 1.0) > QUATERNION_TOLERANCE:
                raise ValueError(f"not a unit quaternion [x, y, z, w] (norm {norm:.6g})")
        return value

    @model_validator(mode="after")
    def _one_rotation(self):
        given = [name for name in ("quaternion", "rpy", "rpy_deg") if getattr(self, name) is not None]
        if len(given) > 1:
            raise ValueError(f"give one rotation, not {' and '.join(given)}")
        return self

    def transform(self) -> Transform:
        if self.quaternion is not None:
            rotation = Rotation.from_quat(self.quaternion)  # normalised (within the tolerance)
        elif self.rpy is not None or self.rpy_deg is not None:
            rotation = Rotation.from_euler("xyz", self.rpy_deg or self.rpy, degrees=self.rpy_deg is not None)
        else:
            rotation = Rotation.identity()
        return Transform(rotation.as_matrix(), np.array(self.xyz))


class TargetPlacement(Placement):
    """Another target (a second cube, a board) and where it stands in the map."""

    file: Path


class FramesConfig(Section):
    """The robot's frames (REP 105). With ``base_from_camera`` or ``map_from_target`` set,
    ``map`` -> ``base_link`` is published beside the camera's pose (``base_pose``); the one
    not set is the identity. With ``[odometry]`` on, ``map`` -> ``odom`` too (``map_odom``,
    and on ROS 2's ``tf`` instead of ``map`` -> ``base_link``)."""

    base_from_camera: Placement | None = Field(None, description="the camera's mount on the robot: T_base_camera")
    map_from_target: Placement | None = Field(None, description="where the target stands in the map: T_map_target")
    # more targets: [[frames.targets]] file = "...", xyz = [...], rpy_deg = [...] (T_map_target of each)
    targets: tuple[TargetPlacement, ...] = ()
    map_frame: str = "map"
    base_frame: str = "base_link"
    camera_frame: str = "camera_optical"
    odom_frame: str = "odom"  # the wheel odometry's frame: the parent of base_frame in its odom -> base_link
    # map -> odom on tf with its steps spread over time (s, time constant; 0: none) for
    # controllers that dislike steps; map_odom carries the unspread value beside it
    map_odom_spread_s: float = Field(0.0, ge=0.0, le=60.0)

    @field_validator("map_frame", "base_frame", "camera_frame", "odom_frame")
    @classmethod
    def _frame_name(cls, value: str) -> str:
        if not FRAME_NAME.fullmatch(value):
            raise ValueError("a frame name is letters, digits, '_' and '/' (not starting with a digit)")
        return value

    @field_validator("base_from_camera")
    @classmethod
    def _on_the_robot(cls, value: Placement | None) -> Placement | None:
        if value is not None and max(abs(v) for v in value.xyz) > MAX_MOUNT_M:
            raise ValueError(f"xyz {list(value.xyz)} puts the camera more than {MAX_MOUNT_M:g} m from the base: "
                             "metres expected")
        return value

    @property
    def enabled(self) -> bool:
        return self.base_from_camera is not None or self.map_from_target is not None

    def robot_frames(self) -> RobotFrames:
        identity = Placement()
        return RobotFrames((self.base_from_camera or identity).transform(),
                           (self.map_from_target or identity).transform(),
                           self.map_frame, self.base_frame, self.camera_frame, self.odom_frame)


def _ros_name(value: str, what: str) -> str:
    """A ROS 2 name: tokens of letters, digits and '_' (not starting with a digit) joined
    by '/', optionally absolute (a leading '/')."""
    body = value[1:] if value.startswith("/") else value
    if not all(ROS_TOKEN.fullmatch(token) for token in body.split("/")):
        raise ValueError(f"not a ROS 2 {what}: tokens of letters, digits and '_' (not starting with a digit) "
                         "joined by '/'")
    return value


class Ros2Topics(Section):
    """Topic names, relative to ``[ros2] namespace`` unless they start with '/'."""

    pose: str = "cubeloc/pose"  # geometry_msgs/msg/PoseWithCovarianceStamped, map -> base_link
    odometry: str = "cubeloc/odometry"  # nav_msgs/msg/Odometry, the same pose (the twist is not measured)
    tf: str = "tf"  # tf2_msgs/msg/TFMessage with publish_tf: map -> odom with [odometry] on, else map -> base_link
    camera_info: str = "cubeloc/camera_info"  # sensor_msgs/msg/CameraInfo, once, transient local
    # diagnostic_msgs/msg/DiagnosticArray from each status (1 Hz): OK while the camera or the
    # target measures the pose, WARN held or bridged or before the first pose, ERROR lost or
    # without a camera; empty: none
    diagnostics: str = "/diagnostics"

    @field_validator("pose", "odometry", "tf", "camera_info")
    @classmethod
    def _topic(cls, value: str) -> str:
        return _ros_name(value, "topic name")

    @field_validator("diagnostics")
    @classmethod
    def _optional_topic(cls, value: str) -> str:
        return value and _ros_name(value, "topic name")


class Ros2Config(Section):
    """ROS 2 messages over the daemon's Zenoh session as rmw_zenoh_cpp sends them (daemon/ros2.py)."""

    enabled: bool = False
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID of the ROS 2 side")
    namespace: str = Field("", description="the node's namespace, '' or absolute ('/robot7')")
    node_name: str = "cubeloc"
    distro: Literal["jazzy", "kilted", "lyrical", "rolling"] = Field(
        "jazzy", description="whose message definitions give the type hashes in the keys")
    publish_tf: bool = Field(False, description="on tf: map -> odom with [odometry] on (REP 105); without it "
                                                "map -> base_link, only if nothing else parents base_link")
    topics: Ros2Topics = Ros2Topics()

    @field_validator("namespace")
    @classmethod
    def _namespace(cls, value: str) -> str:
        if value in ("", "/"):
            return ""
        if not value.startswith("/"):
            raise ValueError("a namespace is absolute: '/robot7', or '' for none")
        return _ros_name(value.rstrip("/"), "namespace")

    @field_validator("node_name")
    @classmethod
    def _node(cls, value: str) -> str:
        if not ROS_TOKEN.fullmatch(value):
            raise ValueError("not a ROS 2 node name: letters, digits and '_', not starting with a digit")
        return value

    def topic(self, name: str) -> str:
        """The fully qualified name of a topic."""
        return name if name.startswith("/") else f"{self.namespace}/{name}"


class OdometryConfig(Section):
    """Wheel odometry in (positioning/tracking/odometry.py): the tracker's bridge where the
    camera has no pose (and with ``as_prior``, the default, its motion prior and a
    relative-motion factor on its map poses too); never over the target."""

    enabled: bool = False
    # ros2: nav_msgs/msg/Odometry in CDR on rmw_zenoh's key for [ros2] domain_id + topic;
    # json: cubeloc.odometry/1 documents on cubeloc/<name>/odometry (docs/robot.md)
    source: Literal["ros2", "json"] = "ros2"
    topic: str = Field("odom", description="the ROS 2 topic, relative to [ros2] namespace unless absolute")
    # as_prior (default): the bridge, and the tracker's motion prior, held position and a
    # relative-motion factor on each map pose; false: only the bridge (a pose from the last
    # one while the camera has none; every pose the camera has is vision's alone)
    as_prior: bool = True
    scale_sigma: float = Field(0.02, gt=0, le=1, description="position error per metre driven")
    turn_sigma: float = Field(0.02, gt=0, le=1, description="heading error per radian turned")
    heading_drift_deg_s: float = Field(0.2, ge=0, le=90, description="heading error per second")
    stale_s: float = Field(0.5, gt=0, le=60, description="a sample older than this when it arrives is dropped")
    max_extrapolation_s: float = Field(0.1, ge=0, le=5, description="how far past the newest sample to predict")

    @field_validator("topic")
    @classmethod
    def _topic(cls, value: str) -> str:
        return _ros_name(value, "topic name")

    def buffer(self):
        from cubeloc.positioning.tracking.odometry import OdometryBuffer, OdometryModel

        model = OdometryModel(self.scale_sigma, self.turn_sigma, math.radians(self.heading_drift_deg_s))
        return OdometryBuffer(model, stale_s=self.stale_s, max_extrapolation_s=self.max_extrapolation_s)


class MapConfig(Section):
    """A saved map (docs/map.md; the tracker only): loaded at start and at every reset, so a
    pose comes in a mapped place without the cube; saved every ``save_every_min`` minutes
    and at shutdown (atomically: a kill -9 loses only what came after the last save)."""

    file: Path | None = Field(None, description="the map file; None: no map (the cube at every start)")
    # false: localisation only: the file is read, never written (several robots sharing one map)
    save: bool = True
    save_every_min: float = Field(5.0, gt=0, le=1440)
    keyframes: int = Field(400, ge=2, le=100_000, description="the most keyframes the map file holds: thinned where dense at each save (~17 kB each)")
    # a map file that cannot be used (damaged, another calibration or target): fail = exit 2
    # at start with one line; ignore = log it and start without a map (the next save replaces it)
    on_error: Literal["fail", "ignore"] = "fail"


class FoxgloveConfig(Section):
    """The Foxglove viewer (daemon/viewer.py): a WebSocket server the Foxglove app connects
    to; off unless ``listen`` is set. ``127.0.0.1:PORT`` admits clients on this machine only
    (an SSH tunnel from a laptop); ``0.0.0.0:PORT`` or an interface's address admits others
    (docs/security.md)."""

    listen: str | None = Field(None, description="HOST:PORT of the WebSocket server; None: off")
    image_width: int = Field(640, ge=16, le=16384, description="the image channel's width (height to scale)")
    image_max_hz: float = Field(10.0, gt=0, le=1000, description="image and annotations at most this often")
    jpeg_quality: int = Field(80, ge=10, le=100)
    trajectory_poses: int = Field(2000, ge=2, le=100_000, description="the trajectory keeps this many poses")

    @field_validator("listen")
    @classmethod
    def _host_port(cls, value: str | None) -> str | None:
        if value is not None:
            parse_listen(value)
        return value

    @property
    def address(self) -> tuple[str, int] | None:
        return None if self.listen is None else parse_listen(self.listen)


def parse_listen(value: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[V6]:PORT`` for IPv6) -> (host, port); ValueError naming the problem."""
    host, sep, port = value.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{value!r} is not HOST:PORT (for example 127.0.0.1:8765)")
    return host, int(port)


class LoggingConfig(Section):
    level: Literal["debug", "info", "warning", "error"] = "info"
    format: Literal["auto", "json", "console"] = "auto"


class Config(Section):
    name: str = Field(default_factory=lambda: socket.gethostname().split(".")[0] or "cubeloc")
    camera: CameraConfig = CameraConfig()
    positioning: PositioningConfig = PositioningConfig()
    zenoh: ZenohConfig = ZenohConfig()
    daemon: DaemonConfig = DaemonConfig()
    frames: FramesConfig = FramesConfig()
    ros2: Ros2Config = Ros2Config()
    odometry: OdometryConfig = OdometryConfig()
    foxglove: FoxgloveConfig = FoxgloveConfig()
    map: MapConfig = MapConfig()
    logging: LoggingConfig = LoggingConfig()

    @field_validator("name")
    @classmethod
    def _key_safe(cls, value: str) -> str:
        if not value or any(c in value for c in "/*$?#[] \t"):
            raise ValueError(f"{value!r} cannot be part of a Zenoh key (no / * $ ? # [ ] or spaces)")
        return value


def _env_overrides(environ: dict[str, str]) -> list[tuple[str, tuple[str, ...], Any]]:
    """[(variable, path, value)] for every CUBELOC_* variable that names a config field."""
    overrides = []
    for variable, raw in sorted(environ.items()):
        # CUBELOC_LOCK_DIR is the drivers' camera lock directory, not a config field.
        if not variable.startswith(ENV_PREFIX) or variable in ("CUBELOC_CONFIG", "CUBELOC_LOCK_DIR"):
            continue
        path = tuple(part.lower() for part in variable[len(ENV_PREFIX):].split("__"))
        try:
            value: Any = json.loads(raw)
        except ValueError:
            value = raw
        overrides.append((variable, path, value))
    return overrides


def _set_path(doc: dict[str, Any], path: tuple[str, ...], value: Any) -> None:
    node = doc
    for key in path[:-1]:
        child = node.setdefault(key, {})
        if not isinstance(child, dict):
            raise ConfigError(f"cannot override {'.'.join(path)}: {key} is not a section")
        node = child
    node[path[-1]] = value


def _format_error(error: dict[str, Any], origin: str) -> str:
    field = ".".join(str(part) for part in error["loc"])
    if error["type"] == "extra_forbidden":
        return f"config {origin}: unknown key '{field}'"
    if error["type"] == "missing":
        return f"config {origin}: '{field}' is required"
    return f"config {origin}: {field} = {error.get('input')!r}: {error['msg']}"


def load_config(path: str | os.PathLike[str] | None = None, environ: dict[str, str] | None = None) -> Config:
    """Load, override from the environment, validate. Raise ConfigError with one line."""
    environ = dict(os.environ if environ is None else environ)
    if path is None and environ.get("CUBELOC_CONFIG"):
        path = environ["CUBELOC_CONFIG"]
    if path is None and DEFAULT_CONFIG_PATH.exists():
        path = DEFAULT_CONFIG_PATH
    doc: dict[str, Any] = {}
    origin = "(built-in defaults)"
    if path is not None:
        origin = str(path)
        try:
            doc = tomllib.loads(Path(path).read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ConfigError(f"config {path}: file not found") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"config {path}: cannot read ({exc})") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"config {path}: not valid TOML ({exc})") from None
        except RecursionError:  # tomllib recurses per nesting level: "a = [[[[..." overflows
            raise ConfigError(f"config {path}: not valid TOML (nested too deeply)") from None
    overrides = _env_overrides(environ)
    for _, key_path, value in overrides:
        _set_path(doc, key_path, value)
    try:
        return Config.model_validate(doc)
    except ValidationError as exc:
        error = exc.errors()[0]
        # Name the environment variable when the bad value came from one.
        for variable, key_path, _ in overrides:
            if tuple(str(p) for p in error["loc"][: len(key_path)]) == key_path:
                raise ConfigError(_format_error(error, f"{origin} + {variable}")) from None
        raise ConfigError(_format_error(error, origin)) from None
