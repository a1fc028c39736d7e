"""A recorded or rendered sequence (EuRoC layout) replayed through the tracker in this
process, every frame in order: ``track_sequence``. It is what ``cubeloc track`` runs (the
command adds its outputs: TUM, pose documents, MCAP, map, plot, ATE), and what the benchmarks
and the tests replay. With ``ProcessorOptions.in_frame_loop()`` (the default) bundle
adjustment runs in the frame loop, so the same frames give the same poses. ``pose_images``
is the single-frame counterpart (``cubeloc pose``): each image's target pose on its own."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import structlog

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.drivers.sequence import read_image_sized, read_sequence_index
from cubeloc.errors import InputFileError
from cubeloc.positioning.estimator import FrameResult, PoseEstimate
from cubeloc.positioning.evaluation import RunScore, score_estimates
from cubeloc.positioning.target import Target, make_cube
from cubeloc.positioning.tracking.map import Map
from cubeloc.positioning.tracking.processor import ProcessorOptions, TrackingProcessor
from cubeloc.positioning.tracking.tracker import Tracker
from cubeloc.positioning.trajectory_io import read_tum

log = structlog.get_logger()


@dataclass(frozen=True)
class ReplayedFrame:
    """One frame of a replay: what the tracker made of it, or why it was not read
    (``result`` None and ``dropped`` the reason)."""

    seq: int
    stamp_ns: int
    result: FrameResult | None
    dropped: str = ""


@dataclass
class TrackRun:
    """A replay: every frame from the first replayed, in order, and the tracker after the
    last (its map, its loop closures)."""

    frames: list[ReplayedFrame]
    tracker: Tracker
    seconds: float  # wall time of the frame loop

    @property
    def results(self) -> list[FrameResult | None]:
        return [f.result for f in self.frames]

    @property
    def estimates(self) -> list[PoseEstimate | None]:
        return [None if f.result is None else f.result.estimate for f in self.frames]

    def score(self, sequence: Path) -> RunScore:
        """Scored against the sequence's ground truth (``groundtruth.tum``), frame for frame
        from the first one replayed."""
        first = self.frames[0].seq if self.frames else 0
        truth = read_tum(Path(sequence) / "groundtruth.tum")[first:first + len(self.frames)]
        return score_estimates(truth, self.estimates)


def pose_images(paths: list[Path], calibration: CameraCalibration, target: Target | None = None,
                options=None) -> Iterator[tuple[Path, FrameResult]]:
    """The target's pose from each image alone (``TargetPoseProcessor``, ``options`` a
    ``PoseOptions``), in order: what ``cubeloc pose`` prints. Every image is read and checked
    (``read_image_sized``) before the first is solved, so a bad file raises before anything
    is given; each is then read again when its turn comes, so a long list is never all in
    memory."""
    from cubeloc.positioning.single_frame import TargetPoseProcessor

    for path in paths:
        read_image_sized(path, calibration.width, calibration.height)
    processor = TargetPoseProcessor(target or make_cube(), calibration, options)
    for seq, path in enumerate(paths):
        processor.reset()  # images are independent views
        yield path, processor.process(read_image_sized(path, calibration.width, calibration.height), 0, seq)


class OdometryReplay:
    """Odometry samples given to ``buffer`` (an ``OdometryBuffer``) as they would have
    arrived: ``rows`` are (arrival_ns, stamp_ns, position, orientation) in the order they
    arrived, each given at its arrival stamp."""

    def __init__(self, rows: list[tuple], buffer) -> None:
        self.buffer = buffer
        self.rows = rows
        self._next = 0

    @classmethod
    def read(cls, path: Path, buffer) -> OdometryReplay:
        """The rows of an odometry file (``cubeloc.odometry/1`` documents, one a line, as
        ``cubeloc record --odometry`` writes them); a bad file raises ``InputFileError``."""
        from cubeloc.daemon.odometry_in import read_odometry_file

        return cls(read_odometry_file(path), buffer)

    def feed(self, now_ns: int) -> None:
        """Every sample that had arrived by ``now_ns``."""
        while self._next < len(self.rows) and self.rows[self._next][0] <= now_ns:
            arrival, stamp, position, orientation = self.rows[self._next]
            self.buffer.add(stamp, position, orientation, now_ns=arrival)
            self._next += 1


FrameHook = Callable[[ReplayedFrame, np.ndarray, TrackingProcessor], None]


def track_sequence(sequence: Path, calibration: CameraCalibration, target: Target | None = None,
                   options: ProcessorOptions | None = None, *, odometry_prior=None,
                   odometry: OdometryReplay | None = None, start_map: Map | None = None,
                   first: int = 0, last: int | None = None, strict: bool = False,
                   on_frame: FrameHook | None = None) -> TrackRun:
    """Replay frames ``first`` to ``last`` (exclusive; None: to the end) of ``sequence``
    through a tracker on ``target`` (the cube when None) with ``options``
    (``ProcessorOptions.in_frame_loop()`` when None).

    - ``odometry_prior`` (``preflight.odometry_prior``) with ``odometry``, the file it reads,
      fed up to each frame's stamp before the frame;
    - ``start_map``: a saved map to start from, as the daemon's ``[map] file``;
    - a frame that cannot be read, or is not the calibration's size, is dropped and counted
      (``ReplayedFrame.dropped``); with ``strict`` it stops the replay (``InputFileError``);
    - ``on_frame(frame, image, processor)`` after each frame the tracker saw (recordings,
      traces)."""
    entries = read_sequence_index(sequence)
    processor = TrackingProcessor(target or make_cube(), calibration,
                                  options or ProcessorOptions.in_frame_loop(), odometry_prior)
    if start_map is not None:
        processor.start_from_map(lambda: start_map)
    frames: list[ReplayedFrame] = []
    started = time.perf_counter()
    try:
        for seq, entry in enumerate(entries[first:last], start=first):
            try:
                image = read_image_sized(entry.path, calibration.width, calibration.height)
            except InputFileError as exc:
                if strict:
                    raise
                log.warning("track.frame_dropped", seq=seq, error=str(exc))
                frames.append(ReplayedFrame(seq, entry.stamp_ns, None, str(exc)))
                continue
            if odometry is not None:
                odometry.feed(entry.stamp_ns)
            frame = ReplayedFrame(seq, entry.stamp_ns, processor.process(image, entry.stamp_ns, seq))
            frames.append(frame)
            if on_frame is not None:
                on_frame(frame, image, processor)
    finally:
        processor.close()
    return TrackRun(frames, processor.tracker, time.perf_counter() - started)
