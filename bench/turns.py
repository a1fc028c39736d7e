"""Brisk turns: the robot turning on the spot (the camera 0.2 m ahead of its axis, two turns
right after initialisation, ``fakes.trajectories.spin_trajectory``) at turn rates and frame
rates beyond the scenarios', with the motion blur of the exposure, through the paper's camera
at half resolution and through the other lenses of ``fakes.lenses``; tracked in-process with
bundle adjustment in the frame loop (deterministic). Seed 11.

What it showed first (2026-12-02): the paper camera keeps every frame at 120 deg/s at 10 fps
(12 deg a frame, ``spin_brisk``) and at 180 deg/s at 30 fps; at 180 deg/s at 10 fps (18 deg a
frame) the rays no longer hold the turn and the track is lost for 1.3 s (84 % of frames);
behind the narrow lens (HFOV 29 deg) 90 deg/s at 10 fps drifted 1 deg a turn and, where the
second turn came round to the first turn's points, PnP took a pose 7.7 deg from the
prediction and the track went on 16 deg and 0.7 m off (254 mm RMS): a pose turned more
than ``motion.max_deg`` (5) from the prediction is now refused (52-64 mm RMS; the drift stays).

Environment: ``CUBELOC_BENCH_SEQUENCES=DIR`` keeps the renders.
"""

from __future__ import annotations

from pathlib import Path

from bench.common import machine_line, markdown_table, renders_root
from cubeloc.daemon.replay import track_sequence

TITLE = "Brisk turns"
SEED = 11
# camera (a fakes.lenses name), turn rate deg/s, frames per second, exposure s
CASES = (
    ("paper_half", 120.0, 10.0, 0.008),
    ("paper_half", 180.0, 30.0, 0.006),
    ("paper_half", 180.0, 10.0, 0.008),
    ("wide", 90.0, 10.0, 0.008),
    ("narrow", 90.0, 10.0, 0.008),
    ("narrow", 60.0, 10.0, 0.008),
    ("vga", 120.0, 10.0, 0.008),
)


def _run(root: Path, camera: str, rate: float, fps: float, exposure_s: float):
    from cubeloc.fakes.lenses import lens_calibration
    from cubeloc.fakes.scenarios import Effects
    from cubeloc.fakes.sequence import write_synthetic_sequence
    from cubeloc.fakes.trajectories import spin_trajectory

    calibration = lens_calibration(camera)
    out = root / f"spin-{camera}-{rate:g}-{fps:g}-{exposure_s * 1000:g}ms"
    if not (out / "groundtruth.tum").is_file():
        write_synthetic_sequence(out, "spin_in_place", seed=SEED, calibration=calibration,
                                 poses=spin_trajectory(rate, 14.0, fps), effects=Effects(exposure_s=exposure_s))
    return track_sequence(out, calibration).score(out)


def run() -> str:
    from cubeloc.fakes.lenses import LENSES

    rows = []
    with renders_root("turns") as (root, _):
        for camera, rate, fps, exposure_s in CASES:
            s = _run(root, camera, rate, fps, exposure_s)
            what = f"{camera}, {LENSES[camera][0]}x{LENSES[camera][1]}, f {LENSES[camera][2]:.0f} px"
            rows.append([what, f"{rate:g} deg/s", f"{fps:g} fps ({rate / fps:g} deg a frame)",
                         f"{exposure_s * 1000:g} ms", f"{100 * s.coverage:.1f} %", str(s.longest_gap_frames),
                         f"{s.rmse_m * 1000:.1f}", f"{s.max_m * 1000:.1f}", f"{100 * s.consistent:.1f} % ({s.beyond_5_sigma})"])
            print("  " + " | ".join(rows[-1]), flush=True)
    table = markdown_table(["camera", "turn rate", "frame rate", "exposure", "coverage", "longest gap (frames)",
                            "RMS mm", "max mm", "inside 3 sigma (beyond 5)"], rows)
    return (f"{machine_line()}. Two turns on the spot, 14 s, seed {SEED}, bundle adjustment in the frame loop; "
            "errors against the ground truth with no alignment.\n\n" + table)
