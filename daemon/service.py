"""The daemon, wired: capture thread -> newest-frame slot -> processing loop -> Zenoh.

Three threads of its own: capture (daemon/capture.py), processing (the caller's thread,
daemon/pipeline.py) and status (here, once a second). Others come with what is switched
on: the tracker's bundle adjustment worker (``cubeloc-ba``), the Foxglove server
(``foxglove``, daemon/viewer.py), a map being saved (``map-save``, daemon/map_store.py),
Aravis' buffer release (``aravis-release``), and Zenoh's own. ``stop`` is the only way to end
it; signal handlers (daemon/commands/run.py) only set it. ``reload`` (SIGHUP, systemctl
reload) makes the status thread read the calibration and target files again, check them
and hand the loop a processor built on them between two frames; a file that does not
pass is logged and the old ones stay. Shutdown is in order: the loop
finishes its frame, the capture thread closes the camera, a last ``status`` goes out, the
Zenoh entities are undeclared and the session closed, all within about a second.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable

import structlog

from cubeloc import __version__
from cubeloc.daemon.cameras import make_camera
from cubeloc.daemon.capture import CaptureThread
from cubeloc.daemon.frame_queue import LatestFrameSlot
from cubeloc.daemon.loop_stats import LoopStats
from cubeloc.daemon.map_store import MapStore
from cubeloc.daemon.messages import (
    StatusReport,
    base_pose_message,
    map_odom_message,
    status_message,
)
from cubeloc.daemon.odometry_in import OdometryInput
from cubeloc.daemon.pipeline import CAPTURE_STALL_MARGIN_S, ProcessingLoop
from cubeloc.daemon.preflight import Prepared, make_processor, read_positioning_files
from cubeloc.daemon.publisher import ZenohPublisher
from cubeloc.daemon.ros2 import Ros2Publisher
from cubeloc.daemon.sdnotify import SystemdNotifier
from cubeloc.daemon.viewer import LiveViewer
from cubeloc.daemon.zenoh_session import ZenohUnreachable, open_session
from cubeloc.drivers.base import Camera, CameraSettings
from cubeloc.errors import CubelocError
from cubeloc.positioning.estimator import FrameProcessor
from cubeloc.positioning.frames import SpreadCorrection

log = structlog.get_logger()

JOIN_TIMEOUT_S = 1.0
RELOAD_POLL_S = 0.1
BAD_FRAMES_WINDOW_S = 1.0  # status says "bad_frames" while frames arrive and all are dropped


class Daemon:
    def __init__(
        self,
        prepared: Prepared,
        stop: threading.Event,
        *,
        notifier: SystemdNotifier | None = None,
        processor: FrameProcessor | None = None,
        camera_factory: Callable[[str, CameraSettings], Camera] = make_camera,
        reload: threading.Event | None = None,
    ) -> None:
        self.prepared = prepared
        self.config = prepared.config
        self.stop = stop
        self.reload = reload or threading.Event()
        self._reloads = {"ok": 0, "failed": 0, "last": None}  # on status: extra.reload
        self.notifier = notifier or SystemdNotifier()
        # wheel odometry in ([odometry]): filled from Zenoh, read by the tracker
        self.odometry = self.config.odometry.buffer() if self.config.odometry.enabled else None
        self._odometry_in: OdometryInput | None = None
        self._map_odom = collections.Counter(published=0, no_odometry=0)  # map -> odom, per frame with a pose
        self.map_store: MapStore | None = None
        if processor is None:
            processor, self.map_store = self._processor(prepared)
        self.processor = processor
        self.stats = LoopStats()
        self.slot = LatestFrameSlot()
        camera = self.config.camera
        service = self.config.daemon
        self.capture = CaptureThread(
            camera.source, camera.settings(), self.slot, stop,
            frame_timeout_s=camera.frame_timeout_s,
            timeout_streak=service.timeout_streak,
            backoff_initial_s=service.reconnect_initial_s,
            backoff_max_s=service.reconnect_max_s,
            camera_factory=camera_factory,
        )
        self._started = time.monotonic()
        self._publisher: ZenohPublisher | None = None
        self._ros2: Ros2Publisher | None = None
        self._loop: ProcessingLoop | None = None
        self._viewer: LiveViewer | None = None
        self.serving = threading.Event()  # set once the Zenoh keys are declared

    def run(self) -> int:
        """Run until ``stop`` is set or a finite source ends. Returns the exit code."""
        config = self.config
        if config.foxglove.listen is not None:  # an address in use or not ours: exit 2 here, at once
            self._viewer = LiveViewer(config.foxglove, self.prepared.target, self.prepared.calibration,
                                      config.frames.robot_frames(), name=f"cubeloc {config.name}")
        session = self._open_session()
        if session is None:  # stopped while waiting for the Zenoh router
            if self._viewer is not None:
                self._viewer.close()
            self.notifier.close()
            return 0
        status_thread = threading.Thread(target=self._status_loop, name="status", daemon=True)
        try:
            loop = ProcessingLoop(
                self.processor, self.slot, self.capture, self.stats,
                publish_pose=lambda payload: self._publisher.publish_pose(payload),
                notifier=self.notifier, stop=self.stop,
                expected_size=self.prepared.calibration.size,
                capture_stall_s=config.camera.frame_timeout_s + CAPTURE_STALL_MARGIN_S,
                pose_sinks=self._pose_sinks(),
                frame_sinks=self._frame_sinks(),
            )
            self._publisher = ZenohPublisher(session, config.name, self.prepared.calibration_yaml, loop.request_reset,
                                             base_pose=config.frames.enabled, map_odom=self.odometry is not None)
            if config.ros2.enabled:
                self._ros2 = Ros2Publisher(session, config.ros2, config.frames.robot_frames(),
                                           self.prepared.calibration, map_odom=self.odometry is not None)
            if self.odometry is not None:
                self._odometry_in = OdometryInput(session, config, self.odometry)
            self._loop = loop
            log.info("daemon started", name=config.name, source=config.camera.source, version=__version__,
                     calibration=str(config.positioning.calibration), target=str(config.positioning.target))
            self.capture.start()
            status_thread.start()
            self.serving.set()
            loop.run()
        finally:
            self._shutdown(session, status_thread)
        if self.capture.failure is not None:
            raise self.capture.failure
        return 0

    def _processor(self, prepared: Prepared) -> tuple[FrameProcessor, MapStore | None]:
        """The processor for ``prepared`` (``preflight.make_processor``, with the wheels'
        samples when ``[odometry]`` is on) and the store of ``[map] file`` it starts from
        (the tracker's only)."""
        store = None
        if self.config.map.file is not None and self.config.positioning.mode == "tracker":
            store = MapStore(self.config.map, prepared.calibration, prepared.target)
        return make_processor(prepared, self.odometry, None if store is None else store.load), store

    def _frame_sinks(self) -> tuple:
        """What sees every processed frame: the Foxglove viewer, the map's periodic save."""
        sinks = []
        if self._viewer is not None:
            sinks.append(self._viewer.offer)
        if self.map_store is not None:
            sinks.append(self._save_map_if_due)
        return tuple(sinks)

    def _save_map_if_due(self, item, result) -> None:
        """A frame sink (the loop's thread, where the map does not change under the copy)."""
        processor = self._loop.processor
        self.map_store.maybe_save(processor.tracker.map, {int(t) for t in processor.front_end.ids})

    def _pose_sinks(self) -> tuple:
        """What each published pose also goes to: the base in the map on ``base_pose``
        (with ``[frames]``), ``map`` -> ``odom`` on ``map_odom`` (with ``[odometry]``), the
        ROS 2 messages (with ``[ros2] enabled``)."""
        config, sinks = self.config, []
        frames = config.frames.robot_frames()
        if config.frames.enabled:

            def base_pose(seq: int, stamp_ns: int, estimate) -> None:
                self._publisher.publish_base_pose(base_pose_message(seq, stamp_ns, estimate, frames, time.time_ns()))

            sinks.append(base_pose)
        if self.odometry is not None:
            spread = SpreadCorrection(config.frames.map_odom_spread_s)

            def map_odom(seq: int, stamp_ns: int, estimate) -> None:
                T_odom_base = self.odometry.pose_at(stamp_ns)
                if T_odom_base is None:  # no odometry around this frame: no map -> odom for it
                    self._map_odom["no_odometry"] += 1
                    return
                raw, covariance = frames.odom_in_map(estimate.T_world_camera, estimate.covariance, T_odom_base)
                spread_value = spread.update(stamp_ns, raw)
                self._publisher.publish_map_odom(map_odom_message(seq, stamp_ns, estimate, frames, raw, covariance,
                                                                  spread_value, time.time_ns()))
                if self._ros2 is not None:
                    self._ros2.publish_map_odom(stamp_ns, spread_value)
                self._map_odom["published"] += 1

            sinks.append(map_odom)
        if config.ros2.enabled:
            if not config.frames.enabled:
                log.warning("ros2 without [frames]: map is the target's frame and base_link is the camera")

            def ros2(seq: int, stamp_ns: int, estimate) -> None:
                if self._ros2 is not None:
                    self._ros2.publish(seq, stamp_ns, estimate)

            sinks.append(ros2)
        return tuple(sinks)

    def _open_session(self):
        """The Zenoh session; in client mode, wait for the router with back-off (at boot it
        may not be up yet: exiting would be exit 2, which systemd does not restart)."""
        delay = self.config.daemon.reconnect_initial_s
        while True:
            try:
                return open_session(self.config.zenoh, purpose="daemon", timestamping=self.config.ros2.enabled)
            except ZenohUnreachable as exc:
                log.warning("zenoh router unreachable, retrying", error=str(exc), retry_in_s=round(delay, 2))
                self.notifier.status("waiting for the Zenoh router")
                self.notifier.watchdog()  # before READY: extends the start timeout
                if self.stop.wait(delay):
                    return None
                delay = min(delay * 2, self.config.daemon.reconnect_max_s)

    def _shutdown(self, session, status_thread: threading.Thread) -> None:
        started = time.monotonic()
        self.stop.set()
        self.notifier.stopping()
        self.slot.close()
        if self.capture.ident is not None:  # started
            self.capture.join(JOIN_TIMEOUT_S)
        if status_thread.ident is not None:
            status_thread.join(JOIN_TIMEOUT_S)
        if self._odometry_in is not None:
            self._odometry_in.close()
        if self._ros2 is not None:
            self._ros2.close()
        if self._publisher is not None:
            self._publish_status()  # the last word: the camera's final state
            self._publisher.close()
        if self._viewer is not None:
            self._viewer.close()
        session.close()
        self.notifier.close()
        if self.map_store is not None and self._loop is not None:  # the loop has ended: the map is still
            self.map_store.save(self._loop.processor.tracker.map, wait=True)
        # Last, after everything others can see has closed: the tracker waits for a
        # bundle adjustment in flight (its worker thread would hold the exit anyway).
        close_processor = getattr(self.processor, "close", None)
        if close_processor is not None:
            close_processor()
        log.info("daemon stopped", seconds=round(time.monotonic() - started, 3),
                 camera_closed=not self.capture.is_alive())

    # -- status ---------------------------------------------------------------------------
    def report(self) -> StatusReport:
        camera = self.capture.status()
        stats = self.stats
        last_fault = self.capture.last_fault
        if camera.state != "streaming":
            state, detail = camera.state, camera.detail
        elif last_fault is not None and self._only_bad_frames(last_fault[0]):
            # Streaming, but every recent frame was dropped at the camera boundary.
            state, detail = "bad_frames", last_fault[1]
        elif stats.frames == 0:
            state, detail = "starting", "waiting for the first frame"
        else:
            state, detail = stats.last_status, stats.last_detail
        return StatusReport(
            name=self.config.name,
            state=state,
            detail=detail,
            stamp_ns=time.time_ns(),
            # a camera not streaming (quiet since its first frame timeout, reconnecting...)
            # delivers nothing: 0, not the last rate for the rest of the rate's window
            fps=stats.fps() if camera.state == "streaming" else 0.0,
            frames=stats.frames,
            poses=stats.poses,
            dropped_frames=self.slot.dropped,
            rejected_poses=stats.rejected_poses,
            latency_ms=stats.latency_percentiles(),
            camera=camera,
            uptime_s=time.monotonic() - self._started,
            version=__version__,
            tags_seen=stats.last_tags,
            extra={"processor_errors": stats.processor_errors, "faults": self.capture.faults(),
                   # time without a pose since the first one, and now; frames held on rays;
                   # the last frame's pose source (null: no pose) and the poses by source
                   "lost_s": round(stats.lost_s, 2), "lost_now_s": round(stats.lost_now_s(), 2),
                   "held_frames": stats.held_frames, "source": stats.source_now(),
                   "poses_by_source": stats.source_counts(), "reload": dict(self._reloads),
                   **({"odometry": self.odometry.report(), "map_odom": dict(self._map_odom)}
                      if self.odometry is not None else {}),
                   **({"foxglove": self._viewer.report()} if self._viewer is not None else {}),
                   **({"map": self.map_store.report()} if self.map_store is not None else {})},
        )

    # -- reload (SIGHUP) -------------------------------------------------------------------
    def _reload_if_requested(self) -> None:
        if not self.reload.is_set() or self._loop is None:
            return
        self.reload.clear()
        config = self.config.positioning
        old_store, old_prepared = self.map_store, self.prepared
        try:
            prepared = read_positioning_files(self.config)
            processor, store = self._processor(prepared)
        except CubelocError as exc:
            self._reloads["failed"] += 1
            self._reloads["last"] = {"ok": False, "stamp_ns": time.time_ns(), "detail": str(exc)}
            log.error("reload refused: the files in use stay", error=str(exc), calibration=str(config.calibration),
                      target=str(config.target))
            return
        self.map_store = store
        self._loop.swap_processor(processor, prepared.calibration.size,
                                  self._map_handover(old_store, old_prepared, prepared))
        self.processor, self.prepared = processor, prepared
        self._publisher.calibration_yaml = prepared.calibration_yaml
        if self._ros2 is not None:
            self._ros2.publish_camera_info(prepared.calibration)
        if self._viewer is not None:
            self._viewer.channels.retarget(prepared.target, prepared.calibration)
        self._reloads["ok"] += 1
        self._reloads["last"] = {"ok": True, "stamp_ns": time.time_ns(),
                                 "detail": f"calibration {config.calibration}, target {config.target}"}
        log.info("reloaded", calibration=str(config.calibration), target=str(config.target),
                 size=f"{prepared.calibration.width}x{prepared.calibration.height}")

    def _map_handover(self, old_store: MapStore | None, old: Prepared, new: Prepared):
        """At a reload that keeps the calibration and the target: the map in memory saved
        (in the loop's thread, at the swap) and the new processor started from that file,
        so a reload loses nothing of the map since the last save. None otherwise: another
        calibration or target starts from what the file has (or, refused, without it)."""
        from cubeloc.positioning.tracking.map_file import (
            calibration_fingerprint,
            target_fingerprint,
        )

        if old_store is None or self.map_store is None or not self.config.map.save:
            return None
        if (calibration_fingerprint(old.calibration), target_fingerprint(old.target)) != (
                calibration_fingerprint(new.calibration), target_fingerprint(new.target)):
            return None

        def handover(before, after) -> None:
            old_store.save(before.tracker.map, wait=True, live_track_ids={int(t) for t in before.front_end.ids})
            after.reset()
        return handover

    def _only_bad_frames(self, last_fault_at: float) -> bool:
        """Frames dropped at the camera boundary lately, and none passed on for a while
        (whatever the processor's speed: a slow frame is not a bad one)."""
        now = time.monotonic()
        accepted = self.capture.last_accepted
        return now - last_fault_at < BAD_FRAMES_WINDOW_S and (accepted is None or now - accepted > BAD_FRAMES_WINDOW_S)

    def _publish_status(self) -> StatusReport:
        report = self.report()
        document = status_message(report)
        if self._publisher is not None:
            self._publisher.publish_status(document)
        if self._viewer is not None:
            self._viewer.status(document)
        if self._ros2 is not None:
            try:
                self._ros2.publish_diagnostics(report)
            except Exception:  # a ROS side that fails costs its own output, never the status
                log.exception("ros2 diagnostics not published")
        self.notifier.status(f"{report.state}, {report.fps:.1f} fps, camera {report.camera.state}")
        return report

    def _status_loop(self) -> None:
        period = self.config.daemon.status_period_s
        deadline = time.monotonic()
        while not self.stop.is_set():
            self._publish_status()
            deadline += period
            # Monotonic deadlines: a slow publish does not make the rate drift. A reload
            # is done within a tenth of a second, and status says so at once.
            while not self.stop.wait(min(RELOAD_POLL_S, max(0.0, deadline - time.monotonic()))):
                if self.reload.is_set():
                    self._reload_if_requested()
                    self._publish_status()
                if time.monotonic() >= deadline:
                    break
