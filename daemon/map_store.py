"""``[map]``: the daemon's saved map (positioning/tracking/map_file.py, docs/map.md).

Loaded at start (checked by ``cubeloc run``'s preflight: a file that cannot be used is
exit 2 with one line, or with ``on_error = "ignore"`` a warning and no map) and again at
every ``reset``; the tracker relocalises in it (``TrackingProcessor.start_from_map``).
Saved every ``save_every_min`` minutes and at shutdown, thinned first to ``keyframes`` (where
the map is dense it loses keyframes, the 10 newest stay: ``Map.thin``), so the file and the
memory stay bounded across runs: the copy is taken in the frame
loop's thread, where the map does not change under it, and compressed and written
atomically in a thread of its own, so the loop does not wait for the disk. With ``save =
false`` the file is only read. A map with fewer than 2 keyframes is not saved (a daemon
that never saw the cube must not replace a good map with an empty one).
"""

from __future__ import annotations

import threading
import time

import structlog

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.daemon.config import MapConfig
from cubeloc.errors import ConfigError, CubelocError
from cubeloc.positioning.target import Target
from cubeloc.positioning.tracking.map import Map

log = structlog.get_logger()

MIN_KEYFRAMES_TO_SAVE = 2
KEEP_NEWEST = 10  # keyframes a thinning never drops: those tracking and bundle adjustment use


class MapStore:
    def __init__(self, config: MapConfig, calibration: CameraCalibration, target: Target) -> None:
        self.config, self.calibration, self.target = config, calibration, target
        self.path = config.file
        self._stats = {"loads": 0, "saves": 0, "failed_saves": 0, "last_saved_ns": None, "loaded": None,
                       "error": None}
        self._writer: threading.Thread | None = None
        self._next_save = time.monotonic() + 60.0 * config.save_every_min

    def check(self) -> None:
        """At start: the file is usable, absent (the first run makes it), or ``on_error``
        says to go on without it; else ConfigError (one line)."""
        self.load(at_start=True)

    def load(self, at_start: bool = False) -> Map | None:
        """The map in the file (None: no file yet, or not usable and ignored)."""
        from cubeloc.positioning.tracking.map_file import load_map

        if not self.path.exists():
            if at_start:
                log.info("no map yet: one is made as the cube is seen", map=str(self.path))
            return None
        try:
            world_map, header = load_map(self.path, self.calibration, self.target)
        except CubelocError as exc:
            self._stats["error"] = str(exc)
            if at_start and self.config.on_error == "fail":
                raise ConfigError(f"[map] {exc} (or set [map] on_error = \"ignore\" to start without it)") from None
            log.error("map not used: starting without it", error=str(exc))
            return None
        self._stats["loads"] += 1
        self._stats["loaded"] = {"keyframes": header["keyframes"], "points": header["points"],
                                 "created_ns": header["created_ns"]}
        if not at_start:
            log.info("map loaded", map=str(self.path), keyframes=header["keyframes"], points=header["points"])
        return world_map

    def maybe_save(self, world_map: Map, live_track_ids: set[int]) -> None:
        """From the frame loop: a copy of the map written in the background when one is due."""
        if time.monotonic() >= self._next_save:
            self._next_save = time.monotonic() + 60.0 * self.config.save_every_min
            self.save(world_map, wait=False, live_track_ids=live_track_ids)

    def save(self, world_map: Map, wait: bool, live_track_ids: set[int] = frozenset()) -> None:
        """Thinned to ``keyframes`` (points the live tracks follow are kept), copied, and
        written in a thread (``wait``: until it is on disk)."""
        from cubeloc.positioning.tracking.map_file import map_arrays, write_map

        if not self.config.save or len(world_map.keyframes) < MIN_KEYFRAMES_TO_SAVE:
            return
        if self._writer is not None and self._writer.is_alive():
            if not wait:
                return  # the last one is still being written: the next period takes this
            self._writer.join()
        # the file's budget: where the map is dense it loses keyframes, the newest stay
        world_map.thin(self.config.keyframes, KEEP_NEWEST, set(live_track_ids))
        arrays = map_arrays(world_map, self.calibration, self.target)
        self._writer = threading.Thread(target=self._write, args=(write_map, arrays), name="map-save", daemon=True)
        self._writer.start()
        if wait:
            self._writer.join()

    def _write(self, write_map, arrays) -> None:
        started = time.monotonic()
        try:
            write_map(self.path, arrays)
        except OSError as exc:  # a full disk, a read-only directory: logged, counted, retried next period
            self._stats["failed_saves"] += 1
            self._stats["error"] = f"{self.path}: cannot write ({exc})"
            log.error("map not saved", error=self._stats["error"])
            return
        self._stats["saves"] += 1
        self._stats["last_saved_ns"] = time.time_ns()
        log.info("map saved", map=str(self.path), keyframes=len(arrays["kf_ids"]), points=len(arrays["point_ids"]),
                 seconds=round(time.monotonic() - started, 2))

    def report(self) -> dict:
        return {"file": str(self.path), "save": self.config.save, **self._stats}
