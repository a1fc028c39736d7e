"""``SyntheticCamera``: the camera protocol over rendered frames along a trajectory.

The daemon runs on it unchanged (camera source ``synthetic:TRAJECTORY[?OPTIONS]``):

=====================  ===================================================================
``seconds=S``          length of the trajectory (default per trajectory, see
                       ``fakes.trajectories``)
``fps=F``              frame rate (default 10, or the settings' ``frame_rate_hz``)
``seed=N``             noise seed (frame k uses seed (N, k)); default 0
``realtime=1``         pace frames at the frame rate on the host clock; a slow consumer
                       loses frames (counted as frame-id gaps), as with a real camera
``loop=1``             start the trajectory again instead of ending the stream
``noise=SIGMA``        Gaussian read noise in DN (default 2)
``blur=SIGMA``         defocus blur, Gaussian sigma in pixels (default 0)
``motion=PX``          motion blur length in pixels along the image x axis (default 0)
``hide=ID,ID``         tags painted over (to force the 2-face and 1-face cases)
``glare=ID``           over-expose the face of this tag
``room_seed=N``        texture seed of the room (default 0)
``calib=FILE``         camera_info YAML to render with (default: the paper's camera)
``target=FILE``        target file to render (default: the 18 cm cube, ids 0-5)
=====================  ===================================================================

``TRAJECTORY`` is a name (``static``, ``orbit``, ``paper``, ``room_walk``, ``spin`` or a
robot-motion scenario of ``fakes.scenarios``, with its effects) or a TUM file.
Example: ``synthetic:paper?seconds=20&fps=10&seed=1&realtime=1``.

Timestamps: the trajectory's own stamps (from ``fakes.trajectories.EPOCH_NS``), or with
``realtime=1`` the host clock at ``start()`` plus the trajectory time. Either way
``ground_truth_at(stamp_ns)`` gives the true pose of a delivered frame.
"""

from __future__ import annotations

import bisect
import contextlib
import queue
import threading
import time
from dataclasses import dataclass, field
from urllib.parse import parse_qsl

import numpy as np

from cubeloc.calib.camera_info import CameraCalibration, paper_camera, read_camera_info
from cubeloc.drivers.base import (
    CameraBase,
    CameraError,
    CameraNotFound,
    CameraSettings,
    CaptureStats,
    DeviceInfo,
    EndOfStream,
    FeatureNotSupported,
    Frame,
    FrameTimeout,
    StreamBroken,
)
from cubeloc.fakes.render import render_view
from cubeloc.fakes.room import Room, default_room
from cubeloc.fakes.scenarios import Effects, scenario_effects
from cubeloc.fakes.trajectories import TrajectoryError, make_trajectory
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.target import Target, load_target, make_cube
from cubeloc.positioning.trajectory_io import StampedPose, read_tum

NOMINAL_EXPOSURE_US = 5000.0  # the exposure at which a frame has the rendered brightness
_ENDED = object()  # the render-ahead worker's end-of-trajectory marker


@dataclass(frozen=True)
class RenderOptions:
    """The physical effects of ``fakes.render.render_view``, per camera."""

    noise_sigma: float = 2.0
    blur_sigma_px: float = 0.0
    motion_blur_px: float = 0.0
    hidden_tags: tuple[int, ...] = ()
    glare_tag: int | None = None
    supersample: int | None = None
    extra: dict = field(default_factory=dict)  # any other render_view keyword


class SyntheticCamera(CameraBase):
    """Frames of ``target`` in ``room`` along ``trajectory``, one per trajectory pose."""

    def __init__(
        self,
        trajectory: list[StampedPose],
        *,
        name: str = "custom",
        settings: CameraSettings | None = None,
        calibration: CameraCalibration | None = None,
        target: Target | None = None,
        room: Room | None = None,
        seed: int = 0,
        realtime: bool = False,
        loop: bool = False,
        options: RenderOptions | None = None,
        effects: Effects | None = None,
    ) -> None:
        if not trajectory:
            raise CameraNotFound("synthetic camera: the trajectory has no poses")
        self.trajectory = list(trajectory)
        self.calibration = calibration or paper_camera()
        self.target = target or make_cube()
        self.room = room or default_room()
        self.seed = int(seed)
        self.realtime = realtime
        self.loop = loop
        self.options = options or RenderOptions()
        self.effects = effects or Effects()
        self._name = name
        for k, pose in enumerate(self.trajectory):
            if not self.room.contains(pose.T_world_camera.translation):
                position = np.round(pose.T_world_camera.translation, 3).tolist()
                raise CameraNotFound(
                    f"synthetic:{name}: pose {k} at {position} m is outside the synthetic room "
                    f"(x {self.room.x_range}, y {self.room.y_range}, z {self.room.z_range})"
                )
        self._settings = settings or CameraSettings(width=self.calibration.width, height=self.calibration.height)
        self._stats = CaptureStats()
        self._stamps = [p.stamp_ns for p in self.trajectory]
        if len(self._stamps) > 1:
            period = (self._stamps[-1] - self._stamps[0]) / (len(self._stamps) - 1)
        else:
            period = 1e9 / (self._settings.frame_rate_hz or 10.0)
        self.frame_period_ns = max(1, int(round(period)))
        self._opened = False
        self._streaming = False
        self._next_index = 0  # frames counted over loops: index k is pose k % len
        self._origin_ns = self._stamps[0]
        self._start_monotonic = 0.0
        self._worker: threading.Thread | None = None
        self._stop_event = threading.Event()
        self._ready: queue.Queue = queue.Queue(maxsize=2)
        self._held: object = None  # a rendered frame not yet due at the last timeout

    # --- the camera protocol -----------------------------------------------------------
    @property
    def info(self) -> DeviceInfo:
        return DeviceInfo(
            device_id=f"synthetic:{self._name}",
            vendor="cubeloc",
            model="synthetic camera",
            serial=f"seed-{self.seed}",
            transport="synthetic",
        )

    def open(self) -> None:
        s = self._settings
        if (s.width, s.height) != (self.calibration.width, self.calibration.height) or s.offset_x or s.offset_y:
            raise FeatureNotSupported(
                f"synthetic camera renders {self.calibration.width}x{self.calibration.height} "
                f"(its calibration); settings ask for {s.width}x{s.height} at offset "
                f"({s.offset_x}, {s.offset_y}): set the camera width/height to match, offsets 0"
            )
        if s.trigger != "free":
            raise FeatureNotSupported(f"synthetic camera runs free only, not trigger {s.trigger!r}")
        self._opened = True

    def start(self) -> None:
        if not self._opened:
            self.open()
        self.stop()
        self._streaming = True
        self._next_index = 0
        self._held = None
        # the first frame builds the room's textures and the ray grid (seconds): do it
        # before the clock starts, as a real camera takes its time to start streaming
        first = self.render(0) if self.realtime else None
        self._start_monotonic = time.monotonic()
        self._origin_ns = time.time_ns() if self.realtime else self._stamps[0]
        if self.realtime:
            # render ahead in a thread, as a real camera exposes while the consumer works
            self._stop_event = threading.Event()
            self._ready = queue.Queue(maxsize=2)
            self._held = (0, first)
            self._worker = threading.Thread(target=self._render_ahead, name="synthetic-camera", daemon=True)
            self._worker.start()

    def next_frame(self, timeout_s: float) -> Frame:
        if not self._streaming:
            raise CameraError("synthetic camera: call start() before next_frame()")
        if self.realtime:
            index, image = self._take_rendered(timeout_s)
        else:
            index = self._next_index
            if not self.loop and index >= len(self.trajectory):
                raise EndOfStream(self._end_message())
            image = self.render(index)
        if index > self._next_index:  # frames the consumer was too slow for
            self._stats.frame_id_gaps += index - self._next_index
        self._next_index = index + 1
        offset_ns = self._offset_ns(index)
        self._stats.delivered += 1
        return Frame(
            image=image,
            frame_id=index,
            device_timestamp_ns=offset_ns,
            stamp_ns=self._origin_ns + offset_ns,
            exposure_us=self._settings.exposure_us or NOMINAL_EXPOSURE_US,
        )

    def stop(self) -> None:
        self._streaming = False
        if self._worker is not None:
            self._stop_event.set()
            with contextlib.suppress(queue.Empty):
                while True:  # unblock a worker waiting to put a frame
                    self._ready.get_nowait()
            self._worker.join(timeout=5.0)
            self._worker = None

    def close(self) -> None:
        self.stop()
        self._opened = False

    def render(self, index: int) -> np.ndarray:
        """The frame with index ``index`` (counted over loops), noise seeded by (seed, index),
        with the effects of its moment (passers-by, exposure steps, exposure-long blur)."""
        i = index % len(self.trajectory)
        t = (self._stamps[i] - self._stamps[0]) / 1e9
        return render_view(
            self.trajectory[i].T_world_camera,
            calibration=self.calibration,
            target=self.target,
            room=self.room,
            seed=int(np.random.SeedSequence([self.seed, index]).generate_state(1)[0]),
            noise_sigma=self.options.noise_sigma,
            blur_sigma_px=self.options.blur_sigma_px,
            motion_blur_px=self.options.motion_blur_px,
            hidden_tags=self.options.hidden_tags,
            glare_tag=self.options.glare_tag,
            supersample=self.options.supersample,
            exposure_gain=self._exposure_gain() * self.effects.gain_at(t),
            extra_objects=self.effects.objects_at(t),
            exposure_poses=self._exposure_poses(i),
            **self.options.extra,
        )

    def _exposure_poses(self, i: int) -> tuple[Transform, ...]:
        """Poses over the exposure (``effects.exposure_s``, centred on the frame's time, so
        the ground truth is the middle of the smear), one per ~0.7 px of image motion (at
        most 12), interpolated between the trajectory's neighbouring poses."""
        exposure = self.effects.exposure_s
        if exposure <= 0 or len(self.trajectory) < 2:
            return ()
        ends = [self._pose_at(i, -exposure / 2), self._pose_at(i, exposure / 2)]
        fx = float(self.calibration.camera_matrix[0, 0])
        # the image motion of a point 1 m away: the turn plus the translation over 1 m
        motion_px = fx * (ends[0].rotation_angle_to(ends[1])
                          + np.linalg.norm(ends[1].translation - ends[0].translation))
        count = int(np.clip(np.ceil(motion_px / 0.7), 1, 12))
        if count == 1:
            return ()
        return tuple(self._pose_at(i, exposure * ((k + 0.5) / count - 0.5)) for k in range(count))

    def _pose_at(self, i: int, offset_s: float) -> Transform:
        """The pose ``offset_s`` from frame ``i``, on the segment to its neighbour (rotation
        along the geodesic, position linear)."""
        j = min(i + 1, len(self.trajectory) - 1) if offset_s >= 0 else max(i - 1, 0)
        if j == i:
            j = i - 1 if offset_s >= 0 else i + 1
        a, b = self.trajectory[i], self.trajectory[j]
        fraction = offset_s * 1e9 / (b.stamp_ns - a.stamp_ns)
        step = a.T_world_camera.inverse() @ b.T_world_camera
        rotation = Transform.from_rvec_tvec(step.rvec() * fraction, np.zeros(3))
        position = a.T_world_camera.translation + fraction * (b.T_world_camera.translation
                                                              - a.T_world_camera.translation)
        return Transform((a.T_world_camera @ rotation).rotation, position)

    # --- ground truth ------------------------------------------------------------------
    def ground_truth_at(self, stamp_ns: int) -> Transform | None:
        """The true ``T_world_camera`` of the frame stamped ``stamp_ns`` (None if no frame
        was due within half a frame period of it)."""
        offset = stamp_ns - self._origin_ns
        duration = self._stamps[-1] - self._stamps[0] + self.frame_period_ns
        if self.loop:
            offset %= duration
        position = bisect.bisect_left(self._stamps, self._stamps[0] + offset)
        best = None
        for i in (position - 1, position):
            if 0 <= i < len(self._stamps):
                error = abs(self._stamps[i] - self._stamps[0] - offset)
                if error * 2 <= self.frame_period_ns and (best is None or error < best[0]):
                    best = (error, i)
        return None if best is None else self.trajectory[best[1]].T_world_camera

    # --- helpers -----------------------------------------------------------------------
    def _offset_ns(self, index: int) -> int:
        loops, i = divmod(index, len(self.trajectory))
        duration = self._stamps[-1] - self._stamps[0] + self.frame_period_ns
        return loops * duration + self._stamps[i] - self._stamps[0]

    def _end_message(self) -> str:
        return f"synthetic:{self._name}: the trajectory ended after {len(self.trajectory)} frames"

    def _due_index(self) -> int:
        """The newest frame whose time has come on the host clock (-1 before the first)."""
        elapsed_ns = int((time.monotonic() - self._start_monotonic) * 1e9)
        duration = self._stamps[-1] - self._stamps[0] + self.frame_period_ns
        loops, within = divmod(elapsed_ns, duration)
        return loops * len(self._stamps) + bisect.bisect_right(self._stamps, self._stamps[0] + within) - 1

    def _render_ahead(self) -> None:
        """Worker: render the next frame, skipping frames already past (a slow consumer
        loses them, as with a real camera); ``_ENDED`` marks the end of the trajectory."""
        index = 1  # frame 0 was rendered by start()
        while not self._stop_event.is_set():
            index = max(index, self._due_index())
            if not self.loop and index >= len(self.trajectory):
                item = _ENDED
            else:
                try:
                    item = (index, self.render(index))
                except Exception as exc:  # a bug: hand it to the consumer, do not die silently
                    item = exc
            while not self._stop_event.is_set():
                try:
                    self._ready.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if item is _ENDED or isinstance(item, Exception):
                return
            index += 1

    def _take_rendered(self, timeout_s: float) -> tuple[int, np.ndarray]:
        deadline = time.monotonic() + max(0.0, timeout_s)
        item, self._held = self._held, None
        if item is None:
            try:
                item = self._ready.get(timeout=max(0.0, timeout_s))
            except queue.Empty:
                self._stats.timeouts += 1
                raise FrameTimeout(f"synthetic:{self._name}: no frame rendered within {timeout_s:.3f} s") from None
        if item is _ENDED:
            self._held = _ENDED  # stays ended for the next call
            raise EndOfStream(self._end_message())
        if isinstance(item, Exception):
            raise StreamBroken(f"synthetic:{self._name}: rendering failed: {item!r}") from item
        index, image = item
        wait_s = self._start_monotonic + self._offset_ns(index) / 1e9 - time.monotonic()
        if wait_s > deadline - time.monotonic():
            # not due before the timeout: keep it for the next call
            time.sleep(max(0.0, deadline - time.monotonic()))
            self._held = item
            self._stats.timeouts += 1
            raise FrameTimeout(f"synthetic:{self._name}: next frame due in {wait_s:.3f} s, after the timeout")
        if wait_s > 0:
            time.sleep(wait_s)
        return index, image

    def _exposure_gain(self) -> float:
        s = self._settings
        gain = (s.exposure_us or NOMINAL_EXPOSURE_US) / NOMINAL_EXPOSURE_US
        return float(gain * 10 ** ((s.gain_db or 0.0) / 20.0))


# --- the registry's factory ------------------------------------------------------------

_OPTION_HELP = "seconds, fps, seed, realtime, loop, noise, blur, motion, hide, glare, room_seed, calib, target"


def _parse_options(argument: str) -> tuple[str, dict[str, str]]:
    name, _, query = argument.partition("?")
    options = dict(parse_qsl(query, keep_blank_values=True, strict_parsing=False))
    known = set(_OPTION_HELP.split(", "))
    unknown = sorted(set(options) - known)
    if unknown:
        raise FeatureNotSupported(
            f"synthetic:{argument}: unknown option(s) {', '.join(unknown)}; known: {_OPTION_HELP}"
        )
    return name or "paper", options


def _number(options: dict[str, str], key: str, argument: str, kind=float):
    if key not in options:
        return None
    try:
        return kind(options[key])
    except ValueError:
        raise FeatureNotSupported(
            f"synthetic:{argument}: option {key}={options[key]!r} is not a {kind.__name__}"
        ) from None


def _flag(options: dict[str, str], key: str) -> bool:
    return options.get(key, "0").lower() in ("1", "true", "yes", "on", "")


def open_synthetic_source(argument: str, settings: CameraSettings) -> SyntheticCamera:
    """Build the camera for ``synthetic:ARGUMENT`` (see the module docstring)."""
    name, options = _parse_options(argument)
    fps = _number(options, "fps", argument)
    if fps is not None and not (np.isfinite(fps) and 0 < fps <= 1000):
        raise FeatureNotSupported(f"synthetic:{argument}: option fps={options['fps']!r} must be in (0, 1000] frames/s")
    fps = fps or settings.frame_rate_hz
    seconds = _number(options, "seconds", argument)
    try:
        if name.endswith(".tum"):
            trajectory = read_tum(name)
        else:
            trajectory = make_trajectory(name, seconds, fps)
    except TrajectoryError as exc:
        raise CameraNotFound(f"synthetic:{argument}: {exc}") from None
    hide = options.get("hide", "")
    try:
        hidden = tuple(int(i) for i in hide.split(",") if i.strip())
    except ValueError:
        raise FeatureNotSupported(f"synthetic:{argument}: hide={hide!r} must be tag ids like 1,4") from None
    calibration = read_camera_info(options["calib"]) if "calib" in options else paper_camera()
    target = load_target(options["target"]) if "target" in options else make_cube()
    room_seed = _number(options, "room_seed", argument, int)
    render = RenderOptions(
        noise_sigma=_number(options, "noise", argument) if "noise" in options else 2.0,
        blur_sigma_px=_number(options, "blur", argument) or 0.0,
        motion_blur_px=_number(options, "motion", argument) or 0.0,
        hidden_tags=hidden,
        glare_tag=_number(options, "glare", argument, int),
    )
    # untouched default settings follow the calibration's image size; anything else must match it
    follow = (settings.width, settings.height) == (CameraSettings().width, CameraSettings().height)
    settings = CameraSettings(
        width=calibration.width if follow else settings.width,
        height=calibration.height if follow else settings.height,
        offset_x=settings.offset_x,
        offset_y=settings.offset_y,
        exposure_us=settings.exposure_us,
        gain_db=settings.gain_db,
        frame_rate_hz=1e9 / max(1, _period_ns(trajectory)),
        trigger=settings.trigger,
    )
    return SyntheticCamera(
        trajectory,
        name=name,
        settings=settings,
        calibration=calibration,
        target=target,
        room=default_room(room_seed) if room_seed is not None else None,
        seed=_number(options, "seed", argument, int) or 0,
        realtime=_flag(options, "realtime") if "realtime" in options else False,
        loop=_flag(options, "loop") if "loop" in options else False,
        options=render,
        effects=scenario_effects(name, trajectory),
    )


def _period_ns(trajectory: list[StampedPose]) -> int:
    if len(trajectory) < 2:
        return 100_000_000
    return int(round((trajectory[-1].stamp_ns - trajectory[0].stamp_ns) / (len(trajectory) - 1)))
