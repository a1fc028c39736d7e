"""Trajectories in the TUM format: ``timestamp tx ty tz qx qy qz qw`` per line.

Timestamps in seconds (as float text), poses ``T_world_camera``; readable by ``evo``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cubeloc.atomic import atomic_write_text
from cubeloc.errors import InputFileError
from cubeloc.positioning.geometry import Transform


@dataclass(frozen=True)
class StampedPose:
    stamp_ns: int
    T_world_camera: Transform


def format_tum_line(pose: StampedPose) -> str:
    t = pose.T_world_camera.translation
    q = pose.T_world_camera.quaternion()
    seconds = f"{pose.stamp_ns // 1_000_000_000}.{pose.stamp_ns % 1_000_000_000:09d}"
    values = " ".join(f"{v:.9f}" for v in (*t, *q))
    return f"{seconds} {values}"


def write_tum(path: str | os.PathLike[str], poses: list[StampedPose]) -> None:
    atomic_write_text(path, "".join(format_tum_line(p) + "\n" for p in poses))


def read_tum(path: str | os.PathLike[str]) -> list[StampedPose]:
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path}: cannot read trajectory ({exc})") from None
    poses = []
    for number, line in enumerate(lines, start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        if len(fields) != 8:
            raise InputFileError(f"{path}:{number}: expected 8 fields 'timestamp tx ty tz qx qy qz qw'")
        try:
            seconds, _, fraction = fields[0].partition(".")
            stamp_ns = int(seconds) * 1_000_000_000 + int((fraction + "000000000")[:9])
            values = np.array([float(v) for v in fields[1:]])
        except ValueError:
            raise InputFileError(f"{path}:{number}: not a number in {line!r}") from None
        if not np.all(np.isfinite(values)) or np.linalg.norm(values[3:]) < 1e-6:
            raise InputFileError(f"{path}:{number}: NaN, infinite or zero quaternion")
        poses.append(StampedPose(stamp_ns, Transform.from_quaternion(values[:3], values[3:])))
    return poses
