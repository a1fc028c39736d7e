"""Everything the daemon checks before it starts anything.

A bad camera source, a missing or unreadable calibration, a calibration for another
resolution, a bad target file or a bad Zenoh endpoint or file fails here, as one line and
exit code 2, before a camera or a Zenoh session is opened.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import structlog

from cubeloc.calib.camera_info import CameraCalibration, read_camera_info
from cubeloc.daemon.cameras import make_camera, parse_source
from cubeloc.daemon.config import Config
from cubeloc.daemon.zenoh_session import build_zenoh_config
from cubeloc.errors import ConfigError
from cubeloc.positioning.estimator import FrameProcessor
from cubeloc.positioning.target import Target, combine_targets, load_target

if TYPE_CHECKING:
    from cubeloc.positioning.target_pose import PoseOptions
    from cubeloc.positioning.tracking import ProcessorOptions
    from cubeloc.positioning.tracking.map import Map
    from cubeloc.positioning.tracking.odometry import OdometryBuffer, OdometryPrior

log = structlog.get_logger()


@dataclass(frozen=True)
class Prepared:
    """A configuration whose files have been read and checked."""

    config: Config
    calibration: CameraCalibration
    calibration_yaml: str  # the file's text, served on the ``calibration`` queryable
    target: Target


def prepare(config: Config) -> Prepared:
    parse_source(config.camera.source)
    prepared = read_positioning_files(config)
    if config.map.file is not None:
        if config.positioning.mode != "tracker":
            raise ConfigError('[map] file is for the tracker: positioning.mode = "target" has no map')
        from cubeloc.daemon.map_store import MapStore

        MapStore(config.map, prepared.calibration, prepared.target).check()
    build_zenoh_config(config.zenoh)
    # Build (not open) the camera last (the synthetic one takes a second): a bad source
    # argument (an unknown synthetic option, a replay without a directory) fails here; a
    # camera that is merely absent does not.
    make_camera(config.camera.source, config.camera.settings())
    return prepared


def prepare_on_loopback(workdir: Path, port: int, name: str, **sections: dict) -> Prepared:
    """A daemon prepared as tests, benchmarks and the soak run one on this machine: the
    synthetic camera, the paper camera's calibration and the default cube (written into
    ``workdir``), Zenoh listening on 127.0.0.1:``port`` only with no scouting, and quick
    reconnects. ``sections``: config sections (a dict each) merged key by key over these."""
    from cubeloc.calib.camera_info import paper_camera, write_camera_info
    from cubeloc.positioning.target import default_cube_yaml

    write_camera_info(workdir / "camera.yaml", paper_camera())
    (workdir / "target.yaml").write_text(default_cube_yaml())
    settings: dict[str, dict] = {
        "camera": {"source": "synthetic:static?seconds=1"},
        "positioning": {"calibration": workdir / "camera.yaml", "target": workdir / "target.yaml"},
        "zenoh": {"multicast_scouting": False, "listen": [f"tcp/127.0.0.1:{port}"]},
        "daemon": {"reconnect_initial_s": 0.1, "reconnect_max_s": 0.4},
    }
    for section, values in sections.items():
        settings[section] = {**settings.get(section, {}), **values}
    return prepare(Config.model_validate({"name": name, **settings}))


def read_positioning_files(config: Config) -> Prepared:
    """The calibration and target files the config names, read and checked (at start, and
    again on a reload: SIGHUP); CubelocError naming the file when one is not usable."""
    path = config.positioning.calibration
    calibration = read_camera_info(path)
    camera_size = (config.camera.width, config.camera.height)
    if calibration.size != camera_size:
        raise ConfigError(
            f"calibration {path} is for {calibration.width}x{calibration.height} images but the "
            f"camera is set to {camera_size[0]}x{camera_size[1]} (camera.width/height): calibrate "
            "at the camera's resolution or set camera.width and camera.height to match"
        )
    target = combined_target(config)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:  # replaced between the two reads
        raise ConfigError(f"calibration {path}: cannot read ({exc})") from None
    return Prepared(config, calibration, text, target)


def combined_target(config: Config) -> Target:
    """The target file of ``[positioning]`` and, with ``[[frames.targets]]``, the others
    moved into its frame by their placements in the map: one rigid target."""
    primary = load_target(config.positioning.target)
    T_map_primary = config.frames.robot_frames().T_map_target
    others = [(load_target(extra.file), (T_map_primary.inverse() @ extra.transform()).matrix())
              for extra in config.frames.targets]
    return combine_targets(primary, others)


def pose_options(config: Config) -> PoseOptions:
    """The target pose's face and residual limits of ``[positioning]``."""
    from cubeloc.positioning.target_pose import PoseOptions

    positioning = config.positioning
    return PoseOptions(allow_two_faces=positioning.allow_two_faces, allow_one_face=positioning.allow_one_face,
                       max_reproj_rms_px=positioning.max_reproj_rms_px)


def processor_options(config: Config, max_keyframes: int | None = None, **bundle_changes) -> ProcessorOptions:
    """The tracker's options as ``config`` sets them (``pose_options``, ``[positioning]
    loop_closure`` and ``floor``), with at most ``max_keyframes`` keyframes (None: the tracker's own) and
    bundle adjustment's options changed by ``bundle_changes`` (``background=False``: in
    the frame loop, every replay alike). The daemon, ``cubeloc track`` and the benchmarks
    all take their options from here."""
    from dataclasses import replace

    from cubeloc.positioning.tracking import ProcessorOptions

    defaults = ProcessorOptions()
    floor = replace(defaults.tracker.bundle.floor, enabled=config.positioning.floor)
    tracker = replace(defaults.tracker, loop=replace(defaults.tracker.loop, enabled=config.positioning.loop_closure),
                      bundle=replace(defaults.tracker.bundle, floor=floor, **bundle_changes))
    if max_keyframes is not None:
        tracker = replace(tracker, keyframes=replace(tracker.keyframes, max_kept=max_keyframes))
    return replace(defaults, pose=pose_options(config), tracker=tracker)


def make_processor(prepared: Prepared, odometry: OdometryBuffer | None = None,
                   start_map: Callable[[], Map | None] | None = None) -> FrameProcessor:
    """The frame processor the loop calls (positioning/ chooses how poses are made):
    the tracker (``positioning.mode = "tracker"``, the default) or the single-frame target
    pose (``"target"``). Both take the same face and residual limits. The tracker's only:
    ``odometry``, the wheels' samples (``[odometry]``, as ``odometry_prior`` makes them its
    motion prior), and ``start_map``, where a saved map comes from (``[map] file``, loaded
    again at every reset). This is the one place a processor is put together."""
    config = prepared.config
    if config.positioning.mode == "tracker":
        from cubeloc.positioning.tracking import TrackingProcessor

        # a map to keep: more keyframes than the tracker's own 40
        keyframes = config.map.keyframes if config.map.file is not None else None
        processor = TrackingProcessor(prepared.target, prepared.calibration, processor_options(config, keyframes),
                                      None if odometry is None else odometry_prior(config, odometry))
        if start_map is not None:
            processor.start_from_map(start_map)
        return processor
    from cubeloc.positioning.single_frame import TargetPoseProcessor

    if odometry is not None:
        log.warning("odometry is only used by the tracker (positioning.mode = \"tracker\")")
    return TargetPoseProcessor(prepared.target, prepared.calibration, pose_options(config))


def odometry_prior(config: Config, odometry: OdometryBuffer) -> OdometryPrior:
    """The wheels' samples as the tracker takes them: through the camera's mount on the
    base and the floor's up (``[frames]``), as its motion prior or only as the bridge
    while it has no pose (``[odometry] as_prior``)."""
    from cubeloc.positioning.tracking.odometry import OdometryPrior

    frames = config.frames.robot_frames()
    return OdometryPrior(odometry, frames.T_base_camera, frames.up_in_target, as_prior=config.odometry.as_prior)
