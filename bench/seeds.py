"""One scenario over several renders: how much a figure of ``bench scenarios`` (seed 1)
depends on the render it was measured on.

``turn_after_init`` by default (a brisk turn right after initialisation, then a 70 s lap
with the cube out of view): the scale the map carries out of the turn is off by a random
+-0.5-1 % (both signs seen), set in the turn and kept for the lap, so the error grows with
the distance from the cube and the RMS differs several-fold between renders of one
trajectory. Each seed is rendered at full resolution (1280x1024; the seed sets the sensor
noise) and replayed through ``cubeloc track`` from this tree in a child process, bundle
adjustment in the frame loop (deterministic), as ``bench scenarios`` does.

Environment: ``CUBELOC_BENCH_SEEDS`` (comma-separated, default ``1,2,6,8``),
``CUBELOC_BENCH_SEEDS_SCENARIO`` (default ``turn_after_init``), ``CUBELOC_BENCH_SEQUENCES=DIR``
keeps the renders (~1.5 min each), as for ``bench scenarios``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from bench.common import REPO, machine_line, markdown_table, renders_root
from bench.scenarios import _render, _score, _track

TITLE = "One scenario over several renders (seeds)"


def run() -> str:
    seeds = [int(s) for s in os.environ.get("CUBELOC_BENCH_SEEDS", "1,2,6,8").split(",") if s]
    name = os.environ.get("CUBELOC_BENCH_SEEDS_SCENARIO", "turn_after_init")
    rows, rms = [], []
    with renders_root("seeds") as (root, tmp):
        for seed in seeds:
            sequence = _render(root, name, seed)
            out = Path(tmp) / f"{name}-{seed}.tum"
            _track(REPO, sequence, out, True)
            s = _score(sequence, out, True)
            rms.append(s.rmse_m * 1000)
            rows.append([str(seed), f"{100 * s.coverage:.1f} %", f"{s.rmse_m * 1000:.2f}", f"{s.max_m * 1000:.1f}",
                         f"{100 * s.consistent:.1f} % ({s.beyond_5_sigma})"])
            print("  " + " | ".join(rows[-1]), flush=True)
    table = markdown_table(["seed", "coverage", "RMS mm", "max mm", "inside 3 sigma (beyond 5)"], rows)
    return (f"{machine_line()}. `{name}` at 1280x1024, one render per seed, `cubeloc track` with bundle "
            "adjustment in the frame loop; errors against the ground truth with no alignment.\n\n" + table +
            f"\nRMS over the seeds: median {np.median(rms):.2f} mm, {min(rms):.2f}-{max(rms):.2f} mm.")
