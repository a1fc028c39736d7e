"""The tracker on a board instead of the cube: the hard scenarios with a 6 x 6 board of
tag36h11 (88 mm tags, 26 mm apart) standing where the cube stands, facing the camera's
first position, rendered through the paper's camera at half resolution and a VGA camera
(``fakes.lenses``), tracked in-process with bundle adjustment in the frame loop
(deterministic), the board's model and nothing else known. A board has one plane: the map
starts on it as on the cube's two or three faces.

The cube's rows for the same scenarios, lenses and seed are ``bench intrinsics``.
Environment: ``CUBELOC_BENCH_SEQUENCES=DIR`` keeps the renders; ``CUBELOC_BENCH_BOARDS`` a
comma-separated subset of the lenses.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from bench.common import machine_line, markdown_table, renders_root
from bench.intrinsics import SCENARIOS, SEED
from cubeloc.daemon.replay import track_sequence

TITLE = "The tracker on a board"
LENSES = ("paper_half", "vga")
CENTRE = np.array([0.0, 0.0, 0.36])  # the board's centre: where the cube stands, its foot 4 cm up


def board_for(scenario: str):
    """The standing board of ``scenario``: facing its camera's first position."""
    from cubeloc.fakes.planar_views import standing_board
    from cubeloc.fakes.trajectories import make_trajectory
    from cubeloc.positioning.target import make_board

    start = make_trajectory(scenario, SCENARIOS[scenario])[0].T_world_camera.translation
    return standing_board(make_board(), CENTRE, start - CENTRE)


def _run(root: Path, lens: str, scenario: str):
    from cubeloc.fakes.lenses import lens_calibration
    from cubeloc.fakes.sequence import write_synthetic_sequence

    calibration, board = lens_calibration(lens), board_for(scenario)
    out = root / f"board-{lens}-{scenario}"
    if not (out / "groundtruth.tum").is_file():
        write_synthetic_sequence(out, scenario, seconds=SCENARIOS[scenario], seed=SEED, calibration=calibration,
                                 target=board)
    return track_sequence(out, calibration, board).score(out)


def run() -> str:
    lenses = [s for s in os.environ.get("CUBELOC_BENCH_BOARDS", ",".join(LENSES)).split(",") if s]
    rows = []
    with renders_root("boards") as (root, _):
        for lens in lenses:
            for scenario in SCENARIOS:
                s = _run(root, lens, scenario)
                rows.append([lens, scenario, f"{100 * s.coverage:.1f} %", str(s.longest_gap_frames),
                             f"{s.rmse_m * 1000:.1f}", f"{s.max_m * 1000:.1f}",
                             f"{100 * s.consistent:.1f} % ({s.beyond_5_sigma})"])
                print("  " + " | ".join(rows[-1]), flush=True)
    table = markdown_table(["camera", "scenario", "coverage", "longest gap (frames)", "RMS mm", "max mm",
                            "inside 3 sigma (beyond 5)"], rows)
    return (f"{machine_line()}. A 6 x 6 board (88 mm tags) standing where the cube stands, facing the "
            f"camera's first position; seed {SEED}, the half-resolution tests' lengths, bundle adjustment in "
            "the frame loop; errors against the ground truth with no alignment. The cube's rows: "
            "[the tracker behind other lenses](#the-tracker-behind-other-lenses).\n\n" + table)
