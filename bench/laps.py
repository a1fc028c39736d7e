"""Loop closure on repeated laps: the tracker with it and without it, on the same frames.

The ``laps`` scenario (fakes/scenarios.py: three laps of the room round the cube, ~52 m,
the cube out of view for ~190 s, each lap 0.15 m and 8 deg off the one before) is rendered
at 1280x1024 with several sensor-noise seeds (``CUBELOC_BENCH_LAPS_SEEDS``, default
0,1,2,3; kept in ``.cache/laps`` or ``CUBELOC_BENCH_LAPS``) and replayed in this process,
bundle adjustment in the frame loop, once without loop closure (the default) and once
with it (``TrackerOptions.loop.enabled``).

Per run: coverage, RMS position error over the run and per lap (no alignment), the last
lap's and the run's RMS over the first lap's (the trusted-pose issue's goals: at most 1 and
1.5), the loop closures applied and refused, and how many of those applied moved the pose
away from the truth (the error after the correction above the error before it).
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

import numpy as np

from bench.common import REPO, machine_line, markdown_table

TITLE = "Loop closure on repeated laps: with and without, on the same frames"
LAP_SECONDS = (3.0, 66.0, 129.0, 192.0)  # the laps' bounds in the 200 s scenario (fakes.scenarios._laps)


def _render(root: Path, seed: int) -> Path:
    from cubeloc.fakes.sequence import write_synthetic_sequence

    out = root / f"seed-{seed}"
    if not (out / "groundtruth.tum").exists():
        write_synthetic_sequence(out, "laps", seed=seed)
    return out


def _replay(sequence: Path, loop_closure: bool) -> dict:
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.daemon.replay import track_sequence
    from cubeloc.positioning.tracking.processor import ProcessorOptions
    from cubeloc.positioning.trajectory_io import read_tum

    calibration = read_camera_info(sequence / "camera.yaml")
    truth = read_tum(sequence / "groundtruth.tum")
    options = ProcessorOptions.in_frame_loop()
    loop = dataclasses.replace(options.tracker.loop, enabled=loop_closure)
    options = dataclasses.replace(options, tracker=dataclasses.replace(options.tracker, loop=loop))
    errors = np.full(len(truth), np.nan)
    moved = []  # (error before, error after) of the last closure of each frame that closed one, mm
    closed = [0]

    def closures(frame, image, processor) -> None:
        i, result, tracker = frame.seq, frame.result, processor.tracker
        where = truth[i].T_world_camera.translation
        if result.estimate is not None:
            errors[i] = 1000 * np.linalg.norm(result.estimate.T_world_camera.translation - where)
        if tracker.loops_closed > closed[0]:
            closed[0] = tracker.loops_closed
            _, before, after = tracker.last_closure
            moved.append((1000 * np.linalg.norm(before.translation - where),
                          1000 * np.linalg.norm(after.translation - where)))

    tracker = track_sequence(sequence, calibration, options=options, on_frame=closures).tracker
    closed, refused = closed[0], tracker.loops_refused
    seconds = np.array([(p.stamp_ns - truth[0].stamp_ns) / 1e9 for p in truth])
    laps = [float(np.sqrt(np.nanmean(errors[(seconds >= a) & (seconds < b)] ** 2)))
            for a, b in zip(LAP_SECONDS, LAP_SECONDS[1:], strict=False)]
    return {"coverage": float(np.mean(np.isfinite(errors))), "rms": float(np.sqrt(np.nanmean(errors**2))),
            "max": float(np.nanmax(errors)), "laps": laps, "closed": closed, "refused": refused,
            "wrong": int(sum(after > before for before, after in moved)), "moved": moved}


def run() -> str:
    from cubeloc.daemon.logs import configure_logging

    configure_logging("warning", "console", stream=sys.stderr)  # the tracker's debug lines are not the bench's
    seeds = [int(s) for s in os.environ.get("CUBELOC_BENCH_LAPS_SEEDS", "0,1,2,3").split(",") if s]
    root = Path(os.environ.get("CUBELOC_BENCH_LAPS", REPO / ".cache" / "laps")).resolve()
    root.mkdir(parents=True, exist_ok=True)
    rows, ratios = [], {True: [], False: []}
    for seed in seeds:
        sequence = _render(root, seed)
        for loop_closure in (False, True):
            r = _replay(sequence, loop_closure)
            ratios[loop_closure].append((r["laps"][2] / r["laps"][0], r["rms"] / r["laps"][0]))
            moves = ", ".join(f"{b:.1f} -> {a:.1f}" for b, a in r["moved"]) or "-"
            rows.append([seed, "on" if loop_closure else "off", f"{100 * r['coverage']:.1f} %", f"{r['rms']:.1f}",
                         f"{r['max']:.1f}", " / ".join(f"{x:.1f}" for x in r["laps"]),
                         f"{r['laps'][2] / r['laps'][0]:.2f}", f"{r['rms'] / r['laps'][0]:.2f}",
                         r["closed"], r["refused"], r["wrong"], moves])
            print(rows[-1], flush=True)
    summary = [[("on" if on else "off"), len(v), f"{np.median([x[0] for x in v]):.2f} / {max(x[0] for x in v):.2f}",
                f"{np.median([x[1] for x in v]):.2f} / {max(x[1] for x in v):.2f}"]
               for on, v in ((False, ratios[False]), (True, ratios[True]))]
    return (f"{machine_line()}. `python -m bench laps`: the `laps` scenario at 1280x1024, noise seeds "
            f"{', '.join(map(str, seeds))}, each replayed in one process with loop closure off and on (bundle "
            "adjustment in the frame loop). Errors are positions against the ground truth with no alignment, mm. "
            "*wrong way*: closures after which the pose was further from the truth than before.\n\n"
            + markdown_table(["loop closure", "runs", "last lap / first (median / worst)",
                              "run / first lap (median / worst)"], summary)
            + "\n\n" + markdown_table(["seed", "loop closure", "coverage", "RMS", "max", "RMS laps 1 / 2 / 3",
                                        "last / first", "run / first", "closed", "refused", "wrong way",
                                        "each closure: error before -> after"], rows))
