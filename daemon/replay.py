"""A recorded or rendered sequence (EuRoC layout) replayed through the tracker in this
process, every frame in order: ``track_sequence``. It is what ``cubeloc track`` runs (the
command adds its outputs: TUM, pose documents, MCAP, map, plot, ATE), and what the benchmarks
and the tests replay. With ``ProcessorOptions.in_frame_loop()`` (the default) bundle
adjustment runs in the frame loop, so the same frames give the same poses. ``pose_images``
is the single-frame counterpart (``cubeloc pose``): each image's target pose on its own;
``calibrate_mount`` solves the camera's mount from a recorded drive
(``cubeloc calibrate-mount``), ``place_target`` a second target in the first's frame from
images of both (``cubeloc calibrate-target --place``)."""

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


MEASURED_SOURCES = ("target", "map", "relocalised")  # the pose sources a mount is solved from


@dataclass(frozen=True)
class MountDrive:
    """The camera's mount solved from a drive (``calibrate_mount``): the solution, how much
    of the drive went into it, and what it could not use (``warnings``)."""

    result: object  # positioning.mount.MountResult
    poses: int  # camera poses within the odometry's span
    samples: int  # odometry samples
    warnings: tuple[str, ...]

    def table(self) -> str:
        """The ``[frames.base_from_camera]`` TOML table, its uncertainty and what the drive
        measured besides as comments (what ``cubeloc calibrate-mount`` prints and writes)."""
        from scipy.spatial.transform import Rotation

        result = self.result
        mount = result.T_base_camera
        rpy = Rotation.from_matrix(mount.rotation).as_euler("xyz", degrees=True)
        sigma_m, sigma_deg = result.sigma()
        z_note = (f"{sigma_m[2] * 1000:.1f} mm, {result.height_source}" if result.observed["z"]
                  else "NOT OBSERVED (a drive on the floor cannot see it): measure the camera's height above the "
                       "base's origin and set it, or give --target with a cube on the floor, or --height")
        return (
            "[frames.base_from_camera]\n"
            f"xyz = [{mount.translation[0]:.4f}, {mount.translation[1]:.4f}, {mount.translation[2]:.4f}]\n"
            f"rpy_deg = [{rpy[0]:.3f}, {rpy[1]:.3f}, {rpy[2]:.3f}]\n"
            f"# standard deviations: x {sigma_m[0] * 1000:.1f} mm, y {sigma_m[1] * 1000:.1f} mm, z {z_note}\n"
            f"# rotation about the base's x {sigma_deg[0]:.2f} deg, y {sigma_deg[1]:.2f} deg, z {sigma_deg[2]:.2f} deg\n"
            f"# the wheels measured {result.distance_scale:.4f} times the distance and {result.turn_scale:.4f} times "
            f"the turn the camera saw, and drifted {result.heading_drift_deg_s:+.3f} deg/s in heading\n"
            + ("" if result.map_scale is None else
               f"# the map away from the target: {result.map_scale:.4f} times the target's scale (sigma "
               f"{100 * result.map_scale_sigma:.1f} %, from the {result.target_pairs} stretches the target measured; "
               "in the lever's standard deviations)\n")
        )


def calibrate_mount(poses: Path, odometry: Path, frames, pair_seconds: float = 1.0, height: float | None = None,
                    target: Path | None = None, base_height: float = 0.0) -> MountDrive:
    """The camera's mount on the robot from a drive (positioning/mount.py): the camera poses
    of ``poses`` (cubeloc.pose/3 documents; those the camera measured: target, map,
    relocalised) against the wheel odometry of ``odometry`` (cubeloc.odometry/1), compared
    over stretches of ``pair_seconds``. The lever's z is ``height`` when given, else the
    camera's height above the floor a cube ``target`` stands on (``frames``' up) less
    ``base_height``, else unobserved. A file that cannot be used raises ``InputFileError``."""
    from cubeloc.daemon.odometry_in import read_odometry_file
    from cubeloc.positioning.mount import make_pairs, solve_mount
    from cubeloc.positioning.tracking.odometry import OdometryBuffer

    camera = _measured_poses(poses)
    rows = read_odometry_file(odometry)
    if len(rows) < 2:
        raise InputFileError(f"{odometry}: {len(rows)} odometry samples, at least 2 needed")
    buffer = OdometryBuffer(capacity=len(rows))
    for _, stamp, position, orientation in sorted(rows, key=lambda r: r[1]):
        buffer.add(stamp, position, orientation)
    first, last = rows[0][1], max(r[1] for r in rows)
    inside = [c for c in camera if first <= c[0] <= last]
    if not inside:
        raise InputFileError(f"{odometry}: its samples ({first} to {last} ns) do not cover any pose of "
                             f"{poses} ({camera[0][0]} to {camera[-1][0]} ns): not recorded together")
    height_sigma, height_source, warnings = 0.0, "given (--height)", []
    if height is None and target is not None:
        height, height_sigma, height_source = _height_from_cube(
            target, frames, np.array([c[1].translation for c in inside]), base_height, warnings)
    pairs = make_pairs(inside, buffer.pose_at, pair_seconds)
    result = solve_mount(pairs, height, height_source, height_sigma_m=height_sigma)
    return MountDrive(result, len(inside), len(rows), tuple(warnings))


def _measured_poses(path: Path) -> list:
    """(stamp_ns, T_world_camera, measured by the target) of the poses the camera
    measured, in time order."""
    from cubeloc.jsonlines import read_json_lines
    from cubeloc.positioning.geometry import Transform

    def parse(doc: dict):
        if doc.get("schema") not in ("cubeloc.pose/1", "cubeloc.pose/3"):
            raise ValueError(f"schema {doc.get('schema')!r}")
        source = doc.get("source", "target" if doc.get("state") == "target" else "map")  # /1 has no source
        if source not in MEASURED_SOURCES:
            return None
        pose = Transform.from_quaternion(np.array(doc["position"], float), np.array(doc["orientation"], float))
        if not np.all(np.isfinite(pose.translation)):
            raise ValueError("not finite")
        return int(doc["stamp_ns"]), pose, source == "target"

    camera = read_json_lines(path, parse, "cubeloc.pose/3 (camera)")
    if not camera:
        raise InputFileError(f"{path}: no pose the camera measured (target, map or relocalised)")
    return sorted(camera, key=lambda c: c[0])


def _height_from_cube(target: Path, frames, positions: np.ndarray, base_height: float,
                      warnings: list[str]) -> tuple[float | None, float, str]:
    """The lever's z from a cube standing on the floor: the camera's height above the
    cube's bottom face (its centre less half its side along the map's up), less
    ``base_height``; with its spread over the drive as its standard deviation."""
    from cubeloc.positioning.mount import camera_height
    from cubeloc.positioning.target import load_target

    cube = load_target(target)
    if cube.cube is None:
        warnings.append(f"{target} is not a cube: it says nothing of the floor, so the lever's z is not observed "
                        "(give --height)")
        return None, 0.0, "unobserved"
    up = frames.up_in_target
    height, spread = camera_height(positions, up, -up * cube.cube.side_m / 2.0)
    source = (f"the camera {height:.3f} m above the cube's floor (spread {spread * 1000:.1f} mm over the drive) "
              f"less --base-height {base_height:g}")
    return height - base_height, spread, source


MIN_VIEWS_OF_BOTH = 2  # images with a pose of both targets that place one in the other's frame


@dataclass(frozen=True)
class Placement:
    """A second target's pose in the first's frame, averaged over ``views`` images (None
    with fewer than MIN_VIEWS_OF_BOTH)."""

    T_first_other: object | None  # positioning.geometry.Transform
    views: int
    spread_mm: float  # RMS of the images' translations about the mean
    spread_deg: float  # RMS of their rotations' angles to the mean


def place_target(paths: list[Path], first: Target, other: Target, calibration: CameraCalibration) -> Placement:
    """``other``'s placement in ``first``'s frame (``cubeloc calibrate-target --place``):
    T_first_other = T_world_camera(first) @ inverse(T_world_camera(other)) per image where each
    gives a pose of its own, averaged (rotations by their mean, translations by theirs); none
    with fewer than MIN_VIEWS_OF_BOTH such images. Every image is read and checked
    (``read_image_sized``) before the first is solved."""
    from scipy.spatial.transform import Rotation

    from cubeloc.positioning.geometry import Transform
    from cubeloc.positioning.single_frame import TargetPoseProcessor

    for path in paths:
        read_image_sized(path, calibration.width, calibration.height)
    poses = {name: TargetPoseProcessor(target, calibration) for name, target in (("first", first), ("other", other))}
    relations = []
    for path in paths:
        image = read_image_sized(path, calibration.width, calibration.height)
        found = {}
        for name, processor in poses.items():
            processor.reset()
            found[name] = processor.process(image, 0, 0).estimate
        if found["first"] is not None and found["other"] is not None:
            relations.append(found["first"].T_world_camera @ found["other"].T_world_camera.inverse())
    if len(relations) < MIN_VIEWS_OF_BOTH:
        return Placement(None, len(relations), float("nan"), float("nan"))
    rotation = Rotation.from_matrix(np.stack([r.rotation for r in relations])).mean()
    translations = np.array([r.translation for r in relations])
    relative = Transform(rotation.as_matrix(), translations.mean(axis=0))
    spread_mm = float(np.sqrt(np.mean(np.sum((translations - relative.translation) ** 2, axis=1)))) * 1000
    spread_deg = float(np.degrees(np.sqrt(np.mean([relative.rotation_angle_to(r) ** 2 for r in relations]))))
    return Placement(relative, len(relations), spread_mm, spread_deg)


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
