#!/usr/bin/env python3
"""Time per frame of both frame processors on hostile 1280x1024 frames (issue 8).

The frames are the ones tests/test_fuzz_images.py feeds (noise, flat, tags cut in half,
1620 real tags with the target's ids, 1620 tag-like squares) plus a good view of the cube
for comparison. Each processor gets each frame ``--repeat`` times (a fresh processor per
frame kind, so the first call is a full-frame search as after a loss); the table gives
the median and the worst call in milliseconds. The tests assert no wall time: this is the
measurement docs/security.md quotes.

    .venv/bin/python scripts/hostile-frames-timing.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests")]

import numpy as np  # noqa: E402
from test_fuzz_images import TARGET, full_frames  # noqa: E402

from cubeloc.calib.camera_info import paper_camera  # noqa: E402
from cubeloc.daemon.logs import configure_logging  # noqa: E402
from cubeloc.fakes import render_view  # noqa: E402
from cubeloc.positioning.range_map import camera_on_sphere  # noqa: E402
from cubeloc.positioning.single_frame import TargetPoseProcessor  # noqa: E402
from cubeloc.positioning.tracking.processor import TrackingProcessor  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    configure_logging("error", "console", stream=sys.stderr)  # stdout is the table
    calibration = paper_camera()
    frames = {"good view of the cube (reference)": render_view(camera_on_sphere(40.0, 30.0, 1.8), room=False, seed=11)}
    frames.update(full_frames())
    frames["black"] = np.zeros((1024, 1280), np.uint8)
    frames["white"] = np.full((1024, 1280), 255, np.uint8)
    print("| frame (1280x1024) | processor | median ms | worst ms | status |")
    print("|---|---|---:|---:|---|")
    for name, image in frames.items():
        for cls in (TargetPoseProcessor, TrackingProcessor):
            processor = cls(TARGET, calibration)
            times, status = [], ""
            for seq in range(args.repeat):
                started = time.perf_counter()
                status = processor.process(image, seq * 100_000_000, seq).status
                times.append((time.perf_counter() - started) * 1000)
            if hasattr(processor, "close"):
                processor.close()
            print(f"| {name} | {cls.__name__} | {statistics.median(times):.0f} | {max(times):.0f} | {status} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
