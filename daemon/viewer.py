"""What cubeloc sees, on Foxglove's own schemas: live (a WebSocket server the Foxglove app
connects to, ``[foxglove] listen``) or into an MCAP file (``cubeloc track --mcap``,
``cubeloc record --mcap``), through Foxglove's SDK (``foxglove-sdk``).

Channels (one ``SceneChannels`` builds them all; topic, schema, what):

- ``/camera/image`` ``foxglove.CompressedImage``: the frame as JPEG, ``image_width`` wide
  (640 x 512 from 1280 x 1024), at most ``image_max_hz`` by the frames' own stamps;
- ``/camera/calibration`` ``foxglove.CameraCalibration``: that image's intrinsics, so the
  Image panel can overlay the 3-D scene;
- ``/camera/annotations`` ``foxglove.ImageAnnotations``, with each image: the target's tags
  decoded (outline and id; green when the pose used it, orange when not) and the tracked
  features (green: a map point that agreed with the pose, yellow: no map point yet, red:
  rejected this frame);
- ``/pose`` ``foxglove.PoseInFrame``: the base in ``map`` (the camera in the target's frame
  without ``[frames]``);
- ``/tf`` ``foxglove.FrameTransforms``: ``map -> <target>``, ``map -> base_link``,
  ``base_link -> camera`` (frame names from ``[frames]``);
- ``/trajectory`` ``foxglove.PosesInFrame``: the last ``trajectory_poses`` poses in ``map``,
  one kept every 1 cm or 2 degrees, sent once a second;
- ``/target`` ``foxglove.SceneUpdate``: the target in its frame, each tag a black square
  with its id (the cube's body too), sent once a second;
- ``/status`` ``foxglove.Log``: the daemon's ``status`` document (JSON) as it goes out.

A channel nobody subscribes to builds nothing (``has_sinks``). Live, the processing loop
only puts the frame into a one-slot queue (``daemon.frame_queue.LatestFrameSlot``, the
newest wins) that the viewer's own thread empties: the loop never waits for a viewer, and
the frames the viewer had no time for are dropped and counted (``status.extra.foxglove``).
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import foxglove
import numpy as np
import structlog
from foxglove import channels as fc
from foxglove import messages as fm
from foxglove.mcap import MCAPWriteOptions

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.daemon.config import FoxgloveConfig
from cubeloc.daemon.frame_queue import CapturedFrame, LatestFrameSlot
from cubeloc.daemon.messages import pose_label
from cubeloc.errors import ConfigError, InputFileError
from cubeloc.positioning.estimator import FeatureState, FrameResult
from cubeloc.positioning.frames import RobotFrames
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.target import Target

log = structlog.get_logger()

SLOW_PERIOD_NS = 1_000_000_000  # the trajectory and the target: once a second
TRAJECTORY_STEP_M = 0.01
TRAJECTORY_STEP_DEG = 2.0
MCAP_FLUSH_S = 1.0  # a kill -9 loses at most the last second: each flush ends a chunk
TARGET_FRAME = "target"

GREEN, ORANGE, YELLOW, RED = (0.1, 0.85, 0.2, 1.0), (1.0, 0.55, 0.0, 1.0), (1.0, 0.9, 0.1, 1.0), (1.0, 0.15, 0.1, 1.0)
FEATURE_COLOURS = {FeatureState.MAPPED: GREEN, FeatureState.CANDIDATE: YELLOW, FeatureState.OUTLIER: RED}


def rgba(value) -> fm.Color:
    return fm.Color(r=value[0], g=value[1], b=value[2], a=value[3])


def timestamp(stamp_ns: int) -> fm.Timestamp:
    return fm.Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)


def _parts(T: Transform) -> tuple[fm.Vector3, fm.Quaternion]:
    x, y, z = (float(v) for v in T.translation)
    qx, qy, qz, qw = (float(v) for v in T.quaternion())
    return fm.Vector3(x=x, y=y, z=z), fm.Quaternion(x=qx, y=qy, z=qz, w=qw)


def _pose(T: Transform) -> fm.Pose:
    position, orientation = _parts(T)
    return fm.Pose(position=position, orientation=orientation)


def _transform(stamp_ns: int, parent: str, child: str, T: Transform) -> fm.FrameTransform:
    translation, rotation = _parts(T)
    return fm.FrameTransform(timestamp=timestamp(stamp_ns), parent_frame_id=parent, child_frame_id=child,
                             translation=translation, rotation=rotation)


@dataclass
class ViewerStats:
    frames: int = 0  # frames shown (their image or pose went to a subscriber or a file)
    images: int = 0

    def report(self) -> dict:
        return {"frames": self.frames, "images": self.images}


class ImageOut:
    """The ``/camera/image`` channel: frames scaled to ``image_width`` wide, as JPEG; and the
    pixels of annotations brought into that image."""

    def __init__(self, context: foxglove.Context, config: FoxgloveConfig, frame_id: str) -> None:
        self.channel = fc.CompressedImageChannel("/camera/image", context=context)
        self.config, self.frame_id = config, frame_id
        self.scale, self.size = 1.0, (0, 0)

    def fit(self, width: int, height: int) -> None:
        """Scale for frames of ``width`` x ``height`` (again only when the size changes)."""
        scale = min(1.0, self.config.image_width / width)
        self.scale, self.size = scale, (max(1, round(width * scale)), max(1, round(height * scale)))

    def px(self, points) -> list[fm.Point2]:
        """OpenCV pixels (centres at integers) of the full frame -> this image's, where
        Foxglove puts pixel centres at +0.5."""
        s = self.scale
        return [fm.Point2(x=(float(x) + 0.5) * s, y=(float(y) + 0.5) * s) for x, y in points]

    def publish(self, stamp_ns: int, image: np.ndarray, log_time: int | None) -> bool:
        if self.size != (round(image.shape[1] * self.scale), round(image.shape[0] * self.scale)) or not self.size[0]:
            self.fit(image.shape[1], image.shape[0])
        if not self.channel.has_sinks():
            return False
        small = image if self.scale == 1.0 else cv2.resize(image, self.size, interpolation=cv2.INTER_AREA)
        ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, self.config.jpeg_quality])
        if ok:
            self.channel.log(fm.CompressedImage(timestamp=timestamp(stamp_ns), frame_id=self.frame_id,
                                                data=jpeg.tobytes(), format="jpeg"), log_time=log_time)
        return bool(ok)


def label(stamp: fm.Timestamp, position: fm.Point2, text: str, colour=(1.0, 1.0, 1.0, 1.0),
          size: float = 14.0) -> fm.TextAnnotation:
    """A text on the image on a dark background."""
    return fm.TextAnnotation(timestamp=stamp, position=position, text=text, font_size=size,
                             text_color=rgba(colour), background_color=rgba((0.0, 0.0, 0.0, 0.6)))


class SceneChannels:
    """Every channel of the module docstring on one Foxglove context, and the messages."""

    def __init__(self, context: foxglove.Context, target: Target | None, calibration: CameraCalibration | None,
                 frames: RobotFrames, config: FoxgloveConfig) -> None:
        """``target`` None: no ``/target``; ``calibration`` None: no ``/camera/calibration``
        (``cubeloc record --mcap`` without positioning files)."""
        self.frames, self.config = frames, config
        self._sent: dict[str, int] = {}  # what goes out at a limited rate -> the stamp it last went
        self.picture = ImageOut(context, config, frames.camera_frame)
        self.retarget(target, calibration)
        self.camera_info = fc.CameraCalibrationChannel("/camera/calibration", context=context)
        self.annotations = fc.ImageAnnotationsChannel("/camera/annotations", context=context)
        self.pose = fc.PoseInFrameChannel("/pose", context=context)
        self.tf = fc.FrameTransformsChannel("/tf", context=context)
        self.trajectory = fc.PosesInFrameChannel("/trajectory", context=context)
        self.scene = fc.SceneUpdateChannel("/target", context=context)
        self.status = fc.LogChannel("/status", context=context)
        self.stats = ViewerStats()
        self._image_period_ns = int(1e9 / config.image_max_hz)
        self._path: list[Transform] = []
        self._path_poses: list[fm.Pose] = []

    def retarget(self, target: Target | None, calibration: CameraCalibration | None) -> None:
        """Other files from a reload (SIGHUP): the next frame is shown with them."""
        self.target, self.calibration = target, calibration
        if calibration is not None:
            self.picture.fit(calibration.width, calibration.height)
        self._sent.pop("target", None)  # the new target at once

    # -- per frame -------------------------------------------------------------------------
    def frame(self, stamp_ns: int, image: np.ndarray, result: FrameResult, log_time: int | None = None) -> None:
        """Everything this frame has for the subscribed channels. ``log_time`` (ns since the
        epoch): the record's time in an MCAP file, None for now."""
        shown = False
        if (self.picture.channel.has_sinks() or self.annotations.has_sinks()) and self._due("image", stamp_ns,
                                                                                  self._image_period_ns):
            self._image(stamp_ns, image, result, log_time)
            shown = True
        estimate = result.estimate
        if estimate is not None:
            T_map_base, _ = self.frames.base_in_map(estimate.T_world_camera, None)
            self._keep(T_map_base)
            shown = shown or self.pose.has_sinks() or self.tf.has_sinks() or self.trajectory.has_sinks()
            if self.pose.has_sinks():
                self.pose.log(fm.PoseInFrame(timestamp=timestamp(stamp_ns), frame_id=self.frames.map_frame,
                                             pose=_pose(T_map_base)), log_time=log_time)
            if self.tf.has_sinks():
                f = self.frames
                self.tf.log(fm.FrameTransforms(transforms=[
                    _transform(stamp_ns, f.map_frame, TARGET_FRAME, f.T_map_target),
                    _transform(stamp_ns, f.map_frame, f.base_frame, T_map_base),
                    _transform(stamp_ns, f.base_frame, f.camera_frame, f.T_base_camera)]), log_time=log_time)
            if self.trajectory.has_sinks() and self._due("trajectory", stamp_ns, SLOW_PERIOD_NS):
                self.trajectory.log(fm.PosesInFrame(timestamp=timestamp(stamp_ns), frame_id=self.frames.map_frame,
                                                    poses=list(self._path_poses)), log_time=log_time)
        if self.target is not None and self.scene.has_sinks() and self._due("target", stamp_ns, SLOW_PERIOD_NS):
            self.scene.log(self._scene(stamp_ns), log_time=log_time)
        self.stats.frames += shown

    def _due(self, what: str, stamp_ns: int, period_ns: int) -> bool:
        """True (and noted) when ``what`` last went out ``period_ns`` or more ago by the
        frames' stamps (less a tenth: a 10 Hz camera's jitter must not halve a 10 Hz
        limit), or never, or the stamps went back (a replay restarted)."""
        last = self._sent.get(what)
        if last is not None and 0 <= stamp_ns - last < 0.9 * period_ns:
            return False
        self._sent[what] = stamp_ns
        return True

    def _keep(self, T: Transform) -> None:
        """The trajectory: a pose kept when it moved 1 cm or turned 2 deg from the last kept."""
        if self._path:
            last = self._path[-1]
            if (np.linalg.norm(T.translation - last.translation) < TRAJECTORY_STEP_M
                    and np.degrees(last.rotation_angle_to(T)) < TRAJECTORY_STEP_DEG):
                return
        self._path.append(T)
        self._path_poses.append(_pose(T))
        if len(self._path) > self.config.trajectory_poses:
            del self._path[0], self._path_poses[0]

    def _image(self, stamp_ns: int, image: np.ndarray, result: FrameResult, log_time: int | None) -> None:
        self.stats.images += self.picture.publish(stamp_ns, image, log_time)
        if (self.calibration is not None and self.camera_info.has_sinks()
                and self.calibration.size == (image.shape[1], image.shape[0])):
            self.camera_info.log(self._camera_info(stamp_ns), log_time=log_time)
        if self.annotations.has_sinks():
            self.annotations.log(self._annotations(stamp_ns, result), log_time=log_time)

    def _camera_info(self, stamp_ns: int) -> fm.CameraCalibration:
        c, s = self.calibration, self.picture.scale
        k = c.camera_matrix.astype(np.float64).copy()
        k[:2, :] *= s
        k[:2, 2] += 0.5 * s - 0.5  # OpenCV's pixel centres at integers, kept so after scaling
        projection = np.hstack([k, np.zeros((3, 1))])
        return fm.CameraCalibration(timestamp=timestamp(stamp_ns), frame_id=self.frames.camera_frame,
                                    width=self.picture.size[0], height=self.picture.size[1], distortion_model=c.distortion_model,
                                    D=[float(v) for v in c.distortion], K=[float(v) for v in k.ravel()],
                                    R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                                    P=[float(v) for v in projection.ravel()])

    def _annotations(self, stamp_ns: int, result: FrameResult) -> fm.ImageAnnotations:
        stamp, px = timestamp(stamp_ns), self.picture.px
        points, texts = [], []
        used = set(result.estimate.tag_ids) if result.estimate is not None else set()
        view = result.view
        for tag_id, corners in (view.tags if view is not None else ()):
            colour = GREEN if tag_id in used else ORANGE
            points.append(fm.PointsAnnotation(timestamp=stamp, type=fm.PointsAnnotationType.LineLoop,
                                              points=px(corners), outline_color=rgba(colour), thickness=2.0))
            texts.append(label(stamp, px(corners.mean(axis=0, keepdims=True))[0], str(tag_id), colour))
        if view is not None and len(view.features):
            colours = [rgba(FEATURE_COLOURS[FeatureState(int(k))]) for k in view.feature_states]
            points.append(fm.PointsAnnotation(
                timestamp=stamp, type=fm.PointsAnnotationType.Points, thickness=4.0, outline_colors=colours,
                points=px(view.features)))
        estimate = result.estimate
        state = pose_label(estimate.state.value, estimate.source.value) if estimate is not None else result.status
        texts.append(label(stamp, fm.Point2(x=8.0, y=20.0), state, size=16.0))
        return fm.ImageAnnotations(points=points, texts=texts)

    def _scene(self, stamp_ns: int) -> fm.SceneUpdate:
        stamp = timestamp(stamp_ns)
        triangles, texts, lines = [], [], []
        for tag in self.target.tags:
            c = tag.corners + 0.0005 * tag.normal  # just off the surface, so the body does not hide it
            triangles.append(fm.TriangleListPrimitive(
                points=[fm.Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in c[[0, 1, 2, 0, 2, 3]]],
                color=rgba((0.05, 0.05, 0.05, 1.0))))
            lines.append(fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineLoop, thickness=2.0, scale_invariant=True,
                                          points=[fm.Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in c],
                                          color=rgba(GREEN)))
            centre = tag.center + 0.01 * tag.normal
            texts.append(fm.TextPrimitive(pose=_pose(Transform(np.eye(3), centre)), billboard=True, font_size=14.0,
                                          scale_invariant=True, color=rgba((1.0, 1.0, 1.0, 1.0)),
                                          text=str(tag.tag_id)))
        cubes = []
        if self.target.cube is not None:  # the cube's body, centred in the target's frame (positioning/target.py)
            side = self.target.cube.side_m
            cubes.append(fm.CubePrimitive(pose=_pose(Transform.identity()), size=fm.Vector3(x=side, y=side, z=side),
                                          color=rgba((0.85, 0.85, 0.85, 0.9))))
        entity = fm.SceneEntity(timestamp=stamp, frame_id=TARGET_FRAME, id="target", frame_locked=True,
                                cubes=cubes, triangles=triangles, lines=lines, texts=texts)
        return fm.SceneUpdate(entities=[entity])

    # -- status ----------------------------------------------------------------------------
    def publish_status(self, document: bytes, log_time: int | None = None) -> None:
        if not self.status.has_sinks():
            return
        state = json.loads(document).get("state", "")
        level = fm.LogLevel.Info if state in ("target", "tracking", "relocalised", "starting") else fm.LogLevel.Warning
        self.status.log(fm.Log(timestamp=timestamp(time.time_ns() if log_time is None else log_time), level=level,
                               message=document.decode(),
                               name="cubeloc/status"), log_time=log_time)


@dataclass(frozen=True)
class _Shown:
    seq: int
    stamp_ns: int
    image: np.ndarray
    result: FrameResult


def serve(context: foxglove.Context, listen: str, name: str) -> foxglove.WebSocketServer:
    """The Foxglove WebSocket server for ``context`` on ``listen`` (HOST:PORT); an address
    in use or not this machine's is a ConfigError (exit 2, one line)."""
    from cubeloc.daemon.config import parse_listen

    try:
        host, port = parse_listen(listen)
    except ValueError as exc:
        raise ConfigError(f"foxglove listen: {exc}") from None
    try:
        server = foxglove.start_server(name=name, host=host, port=port, context=context)
    except Exception as exc:  # the SDK raises RuntimeError for a bind failure
        raise ConfigError(f"foxglove listen {listen}: cannot listen there ({exc})") from None
    log.info("foxglove viewer listening", listen=f"{host}:{server.port}",
             note=f"in the Foxglove app: Open connection, ws://{host}:{server.port}")
    return server


class LiveViewer:
    """The Foxglove WebSocket server and the thread that feeds it (``offer`` from the loop)."""

    def __init__(self, config: FoxgloveConfig, target: Target, calibration: CameraCalibration,
                 frames: RobotFrames, name: str = "cubeloc") -> None:
        self.context = foxglove.Context()
        self.channels = SceneChannels(self.context, target, calibration, frames, config)
        self.server = serve(self.context, config.listen, name)
        self.port = self.server.port
        self.listen = f"{config.address[0]}:{self.port}"
        self._slot = LatestFrameSlot()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="foxglove", daemon=True)
        self._thread.start()

    def offer(self, item: CapturedFrame, result: FrameResult) -> None:
        """From the processing loop: never blocks; a frame still waiting is replaced (dropped)."""
        self._slot.put(_Shown(item.seq, item.frame.stamp_ns, item.frame.image, result))

    def status(self, document: bytes) -> None:
        self.channels.publish_status(document)

    def report(self) -> dict:
        # dropped: frames the viewer's thread had no time for (the loop never waited)
        return {**self.channels.stats.report(), "dropped": self._slot.dropped, "listen": self.listen}

    def _run(self) -> None:
        while not self._stop.is_set():
            item = self._slot.get(0.2)
            if item is None:
                continue
            try:
                self.channels.frame(item.stamp_ns, item.image, item.result)
            except Exception:  # a viewer's bug must not stop the daemon: logged, the next frame goes on
                log.exception("foxglove viewer failed on a frame", seq=item.seq)

    def close(self) -> None:
        self._stop.set()
        self._slot.close()
        self._thread.join(1.0)
        self.server.stop()


class McapRecording:
    """The channels into an MCAP file, records timed by the frames' stamps; a chunk is
    finished every second of wall time, so a kill -9 leaves a file readable up to there."""

    def __init__(self, path: Path, target: Target | None, calibration: CameraCalibration | None,
                 frames: RobotFrames, config: FoxgloveConfig | None = None) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise InputFileError(f"{self.path}: already exists (choose another --mcap)")
        if not self.path.parent.is_dir():
            raise InputFileError(f"{self.path}: the directory {self.path.parent} does not exist")
        self.context = foxglove.Context()
        self.channels = SceneChannels(self.context, target, calibration, frames, config or FoxgloveConfig())
        try:
            # Whole chunks only: with seeking the writer puts a chunk's record down before
            # its length is known and comes back for it, so a kill -9 left a record of
            # length 2^64-1 that readers stop at; without, a killed file ends after its last
            # finished chunk (or inside the one being written out).
            self.writer = foxglove.open_mcap(self.path, context=self.context,
                                             writer_options=MCAPWriteOptions(disable_seeking=True))
        except Exception as exc:
            raise InputFileError(f"{self.path}: cannot write ({exc})") from None
        self._flushed = time.monotonic()
        self._last_state: tuple[str, str] | None = None

    def frame(self, stamp_ns: int, image: np.ndarray, result: FrameResult) -> None:
        """The frame's records; on ``/status`` a line whenever the state or status changes."""
        self.channels.frame(stamp_ns, image, result, log_time=stamp_ns)
        state = (result.estimate.state.value if result.estimate is not None else result.status, result.status)
        if state != self._last_state:
            self._last_state = state
            document = {"state": state[0], "status": result.status, "detail": result.detail,
                        "tags_seen": list(result.tags_seen), "stamp_ns": stamp_ns}
            self.channels.publish_status(json.dumps(document).encode(), log_time=stamp_ns)
        self._maybe_flush()

    def _maybe_flush(self) -> None:
        now = time.monotonic()
        if now - self._flushed >= MCAP_FLUSH_S:
            self.writer.flush()
            self._flushed = now

    def close(self) -> None:
        self.writer.close()

    def __enter__(self) -> McapRecording:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

