"""Write a synthetic sequence: frames in the EuRoC layout plus everything to score it.

::

    <out>/mav0/cam0/data.csv, <out>/mav0/cam0/data/<ns>.png   the frames
    <out>/groundtruth.tum                                     T_world_camera per frame
    <out>/camera.yaml                                         camera_info the frames were rendered with
    <out>/target.yaml                                         the target in view

The directory appears whole or not at all: everything is written into a hidden sibling
directory that is renamed to ``out`` at the end.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import structlog

from cubeloc.atomic import atomic_write_text, current_umask, fsync_directory
from cubeloc.calib.camera_info import CameraCalibration, paper_camera, write_camera_info
from cubeloc.drivers.sequence import SequenceWriter
from cubeloc.errors import InputFileError
from cubeloc.fakes.camera import RenderOptions, SyntheticCamera
from cubeloc.fakes.room import Room
from cubeloc.fakes.scenarios import Effects, scenario_effects
from cubeloc.fakes.trajectories import make_trajectory
from cubeloc.positioning.target import Target, make_cube
from cubeloc.positioning.trajectory_io import StampedPose, write_tum

log = structlog.get_logger()


@dataclass(frozen=True)
class SequenceSummary:
    path: Path
    frames: int
    seconds: float
    trajectory: str


def write_synthetic_sequence(
    out_dir: str | os.PathLike[str],
    trajectory: str = "paper",
    *,
    seconds: float | None = None,
    fps: float | None = None,
    seed: int = 0,
    calibration: CameraCalibration | None = None,
    target: Target | None = None,
    room: Room | None = None,
    options: RenderOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
    poses: list[StampedPose] | None = None,
    effects: Effects | None = None,
    extra_files: dict[str, str] | None = None,
) -> SequenceSummary:
    """Render ``trajectory`` into the sequence directory ``out_dir`` (which must not exist
    or be empty). ``progress(done, total)`` is called after every frame. ``poses`` and
    ``effects``, where given, replace the named trajectory's (``trajectory`` then only
    names the render). ``extra_files`` (name: text) are written beside them, in the same
    all-or-nothing directory."""
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputFileError(f"{out}: already exists and is not an empty directory; choose another --out")
    poses = make_trajectory(trajectory, seconds, fps) if poses is None else poses
    calibration = calibration or paper_camera()
    camera = SyntheticCamera(
        poses, name=trajectory, calibration=calibration, target=target, room=room, seed=seed, options=options,
        effects=scenario_effects(trajectory, poses) if effects is None else effects,
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    try:
        # mkdtemp makes it private (0700); the sequence gets the mode a plain mkdir would,
        # as `cubeloc record` writes (the usual umask: 0755)
        staging.chmod(0o777 & ~current_umask())
        # PNG encoding releases the GIL: write frame k in a thread while frame k + 1 renders
        with camera, SequenceWriter(staging) as writer, ThreadPoolExecutor(1) as encoder:
            camera.start()
            pending = None
            for done in range(1, len(poses) + 1):
                frame = camera.next_frame(timeout_s=1.0)
                if pending is not None:
                    pending.result()
                pending = encoder.submit(writer.write, frame.stamp_ns, frame.image)
                if progress is not None:
                    progress(done, len(poses))
            if pending is not None:
                pending.result()
        write_tum(staging / "groundtruth.tum", poses)
        write_camera_info(staging / "camera.yaml", calibration)
        atomic_write_text(staging / "target.yaml", target_yaml(target or make_cube()))
        for name, text in (extra_files or {}).items():
            atomic_write_text(staging / name, text)
        if out.exists():
            out.rmdir()  # empty, checked above
        os.replace(staging, out)
        fsync_directory(out.parent)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    seconds_written = (poses[-1].stamp_ns - poses[0].stamp_ns) / 1e9 if len(poses) > 1 else 0.0
    log.debug("synthetic sequence written", path=str(out), frames=len(poses), trajectory=trajectory)
    return SequenceSummary(out, len(poses), seconds_written, trajectory)


def target_yaml(target: Target) -> str:
    """The target file text: the cube shorthand for a cube, explicit tags otherwise."""
    if target.cube is None:
        return target.to_yaml()
    c = target.cube
    ids = ", ".join(str(i) for i in c.ids)
    return f"family: {target.family}\ncube: {{side: {c.side_m!r}, tag_size: {c.tag_size_m!r}, ids: [{ids}]}}\n"
