"""The tracker on the synthetic camera at full resolution (1280x1024, the paper's camera).

Scenarios (sequences rendered once into a temporary directory, then replayed from PNG
exactly as ``cubeloc track`` does; processing time excludes PNG decoding):

- ``paper``: the paper's experiment, 30 s at 10 fps, the cube in view for ~5 s; RMS ATE
  with no alignment (paper: 5.75 mm with ORB-SLAM3, 87.3 mm with SVO).
- ``orbit``: the cube always in view, 20 s.
- ``room_walk``: 40 s, the cube out of view for more than 20 s and back at the end: scale
  drift while away, RMS ATE after its return.
- throughput: the ``paper`` frames played forwards and backwards, back to back, with
  bundle adjustment in its worker thread as in the daemon; sustained fps, time per frame
  by state, peak RSS and the map's size at the end.

Environment: ``CUBELOC_BENCH_LONG_FRAMES`` sets the length of the throughput run
(default 2000 frames; 6000 is ten minutes of a 10 fps camera).
"""

from __future__ import annotations

import os
import resource
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.common import markdown_table

TITLE = "Tracker: accuracy on the synthetic camera, throughput at 1280x1024"


def _render(root: Path, name: str, seconds: float, seed: int) -> Path:
    from fakes.sequence import write_synthetic_sequence

    out = root / name
    write_synthetic_sequence(out, name, seconds=seconds, fps=10.0, seed=seed)
    return out


def _replay(sequence: Path, background: bool, frames: int | None = None):
    """(results, ground truth poses, per-frame processing seconds, processor) for one pass,
    or for ``frames`` frames played forwards and backwards (a continuous motion) with the
    stamps running on."""
    from calib.camera_info import read_camera_info
    from drivers.sequence import read_mono_png, read_sequence_index
    from positioning.target import load_target
    from positioning.tracking.processor import ProcessorOptions, TrackingProcessor
    from positioning.trajectory_io import read_tum

    defaults = ProcessorOptions()
    options = replace(defaults, tracker=replace(
        defaults.tracker, bundle=replace(defaults.tracker.bundle, background=background)))
    processor = TrackingProcessor(load_target(sequence / "target.yaml"), read_camera_info(sequence / "camera.yaml"),
                                  options)
    entries = read_sequence_index(sequence)
    truth = read_tum(sequence / "groundtruth.tum")
    count = frames or len(entries)
    period = entries[1].stamp_ns - entries[0].stamp_ns
    results, seconds = [], []
    cycle = list(range(len(entries))) + list(range(len(entries) - 2, 0, -1))  # forwards, then back
    try:
        for k in range(count):
            entry = entries[cycle[k % len(cycle)]]
            image = read_mono_png(entry.path)
            stamp = entries[0].stamp_ns + k * period
            started = time.perf_counter()
            results.append(processor.process(image, stamp, k))
            seconds.append(time.perf_counter() - started)
    finally:
        processor.close()
    return results, truth, seconds, processor


def _estimates(results, truth):
    from positioning.trajectory_io import StampedPose

    return [StampedPose(p.stamp_ns, r.estimate.T_world_camera)
            for r, p in zip(results, truth, strict=False) if r.estimate is not None]


def _states(results) -> str:
    counts: dict[str, int] = {}
    for r in results:
        key = r.estimate.state.value if r.estimate is not None else r.status
        counts[key] = counts.get(key, 0) + 1
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))


def run() -> str:
    from positioning.evaluation import absolute_trajectory_error, relative_pose_error, scale_drift

    rows, notes = [], []
    with tempfile.TemporaryDirectory(prefix="cubeloc-bench-tracker-") as tmp:
        root = Path(tmp)
        paper = _render(root, "paper", 30.0, seed=1)
        results, truth, seconds, _ = _replay(paper, background=False)
        ate = absolute_trajectory_error(truth, _estimates(results, truth))
        rpe = relative_pose_error(truth, _estimates(results, truth), delta_m=1.0)
        rows.append(["paper (30 s, cube first ~5 s)", f"{ate.rmse_m * 1000:.2f}", f"{ate.max_m * 1000:.2f}",
                     f"{rpe.translation_rmse_percent:.2f} %/m", _states(results)])

        orbit = _render(root, "orbit", 20.0, seed=2)
        results, truth, seconds, _ = _replay(orbit, background=False)
        ate = absolute_trajectory_error(truth, _estimates(results, truth))
        rows.append(["orbit (20 s, cube always in view)", f"{ate.rmse_m * 1000:.2f}", f"{ate.max_m * 1000:.2f}",
                     "", _states(results)])

        walk = _render(root, "room_walk", 40.0, seed=3)
        results, truth, seconds, _ = _replay(walk, background=False)
        est = _estimates(results, truth)
        ate = absolute_trajectory_error(truth, est)
        away = [p.stamp_ns for r, p in zip(results, truth, strict=True)
                if r.estimate is not None and r.estimate.state.value == "tracking"]
        back = [p.stamp_ns for r, p in zip(results, truth, strict=True)
                if r.estimate is not None and r.estimate.state.value != "tracking" and away and p.stamp_ns > away[0]]
        cells = ["room_walk (40 s, cube away > 20 s)", f"{ate.rmse_m * 1000:.2f}", f"{ate.max_m * 1000:.2f}", "",
                 _states(results)]
        if away:
            drift = scale_drift(truth, est, away[0], away[-1])
            cells[3] = (f"away {drift.distance_m:.1f} m: scale {drift.scale_error_percent:+.2f} %, "
                        f"drift {drift.drift_percent_per_m:+.2f} %/m, end error {drift.end_error_m * 1000:.1f} mm")
        if back:
            after = absolute_trajectory_error(truth, est, start_ns=back[0])
            cells[1] += f" (after return: {after.rmse_m * 1000:.2f})"
        rows.append(cells)

        frames = int(os.environ.get("CUBELOC_BENCH_LONG_FRAMES", "2000"))
        results, truth, seconds, processor = _replay(paper, background=True, frames=frames)
        rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        world = processor.tracker.map
        bundles = processor.tracker.bundle_runs
        ba = np.median([b.seconds for b in bundles]) if bundles else float("nan")
        total = float(np.sum(seconds))
        per_state: dict[str, list[float]] = {}
        for r, t in zip(results, seconds, strict=True):
            key = r.estimate.state.value if r.estimate is not None else r.status
            per_state.setdefault(key, []).append(t)
        split = ", ".join(f"{k} {1000 * np.median(v):.1f} ms (n={len(v)})" for k, v in sorted(per_state.items()))
        notes.append(
            f"Throughput at 1280x1024, bundle adjustment in its worker thread, the paper sequence played "
            f"forwards and backwards for {frames} frames: {total:.1f} s of processing, "
            f"**{frames / total:.1f} fps** sustained ({1000 * total / frames:.1f} ms per frame on average; "
            f"median per state: {split}). Peak RSS of the whole benchmark process {rss_mb:.0f} MB "
            f"(it rendered the sequences too); map at the end: {len(world.keyframes)} keyframes, "
            f"{len(world.points)} points (bounded by culling). Median bundle adjustment {ba * 1000:.0f} ms "
            f"for a window of {processor.options.tracker.bundle.window_keyframes} keyframes."
        )
    table = markdown_table(["scenario", "RMS ATE mm (no alignment)", "max mm", "relative / drift", "frames"], rows)
    return table + "\n" + "\n\n".join(notes) + "\n"
