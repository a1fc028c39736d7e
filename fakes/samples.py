"""Write the sample frames shown in docs/synthetic.md: ``python -m cubeloc.fakes.samples [DIR]``.

One frame per trajectory (default directory ``docs/samples``), downscaled to 640x512.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2

from cubeloc.fakes.render import render_view
from cubeloc.fakes.trajectories import make_trajectory

# (trajectory, second of the frame shown, what it shows)
SAMPLES = (
    ("static", 0.0, "the start pose of every trajectory: three faces at 2.3 m"),
    ("orbit", 12.0, "orbiting the cube"),
    ("paper", 6.0, "the paper's trolley turning away: the cube about to leave the view"),
    ("room_walk", 20.0, "walking the room, the cube out of view: texture for the tracker"),
)


def write_samples(directory: Path) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name, second, _ in SAMPLES:
        poses = make_trajectory(name)
        pose = poses[min(len(poses) - 1, round(second * 10))].T_world_camera
        image = cv2.resize(render_view(pose, seed=1), (640, 512), interpolation=cv2.INTER_AREA)
        path = directory / f"synthetic_{name}.png"
        cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        written.append(path)
    return written


if __name__ == "__main__":
    for written_path in write_samples(Path(sys.argv[1] if len(sys.argv) > 1 else "docs/samples")):
        print(f"{written_path} ({written_path.stat().st_size // 1024} KB)")
