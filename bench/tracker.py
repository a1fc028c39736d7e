"""The tracker on the synthetic camera at full resolution (1280x1024, the paper's camera).

Scenarios (sequences rendered once into a temporary directory, then replayed from PNG
exactly as ``cubeloc track`` does; processing time excludes PNG decoding):

- ``paper``: the paper's experiment, 30 s at 10 fps, the cube in view for ~5 s; RMS ATE
  with no alignment (paper: 5.75 mm with ORB-SLAM3, 87.3 mm with SVO).
- ``orbit``: the cube always in view, 20 s.
- ``room_walk``: 40 s, the cube out of view for more than 20 s and back at the end: scale
  drift while away, RMS ATE after its return.
- bundle adjustment solvers: ours and SciPy's on the same windows of ``paper``.
- throughput: the ``paper`` frames played forwards and backwards (a continuous motion),
  bundle adjustment in its worker thread as in the daemon; sustained fps is the median
  over ``RUNS`` runs of ``THROUGHPUT_FRAMES`` frames (wall time of ``process()``, and the
  process CPU time too, since the machine is shared), and the time per frame by state.
- memory: a ten-minute sequence (6000 frames of a 10 fps camera) in a child process, its
  peak RSS and the map's size at the end. The frames are the 30 s of ``paper`` rendered
  once and cycled forwards and backwards (rendering 6000 frames would take most of an
  hour here); the tracker sees one continuous 10-minute motion.
- live: frames on the camera's clock (10 and 30 fps) through the daemon's newest-frame
  slot, bundle adjustment in its thread; several runs of our solver and of SciPy's (the
  baseline) in turn.

Environment: ``CUBELOC_BENCH_SEQUENCES=DIR`` renders the sequences into DIR once and reuses
them on later runs (paper 30 s seed 1, orbit 20 s seed 2, room_walk 40 s seed 3);
``CUBELOC_BENCH_LONG_FRAMES`` sets the length of the memory run (default
6000), ``CUBELOC_BENCH_RUNS`` the number of throughput runs (default 3),
``CUBELOC_BENCH_LIVE_RUNS`` the number of live runs of each solver at 10 fps (default 4).
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bench.common import markdown_table

TITLE = "Tracker: accuracy on the synthetic camera, throughput at 1280x1024"


def _render(root: Path, name: str, seconds: float, seed: int, fps: float = 10.0, trajectory: str | None = None) -> Path:
    """The sequence ``name`` (trajectory ``name`` unless given) under ``root``; reused when
    ``root`` already holds it (see ``CUBELOC_BENCH_SEQUENCES``), so that a rerun skips
    minutes of rendering."""
    from cubeloc.fakes.sequence import write_synthetic_sequence

    out = root / name
    if not (out / "groundtruth.tum").is_file():
        write_synthetic_sequence(out, trajectory or name, seconds=seconds, fps=fps, seed=seed)
    return out


def _replay(sequence: Path, background: bool, frames: int | None = None, problems: list | None = None):
    """(results, ground truth poses, per-frame processing seconds, processor) for one pass,
    or for ``frames`` frames played forwards and backwards (a continuous motion) with the
    stamps running on. ``problems``, when given, receives the bundle adjustment problem of
    every new keyframe (for the solver comparison)."""
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.drivers.sequence import read_image, read_sequence_index
    from cubeloc.positioning.target import load_target
    from cubeloc.positioning.tracking import bundle
    from cubeloc.positioning.tracking.processor import TrackingProcessor
    from cubeloc.positioning.trajectory_io import read_tum

    options = _options(background=background)
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
            image = read_image(entry.path)
            stamp = entries[0].stamp_ns + k * period
            started = time.perf_counter()
            keyframes = processor.tracker.map.next_kf_id
            results.append(processor.process(image, stamp, k))
            seconds.append(time.perf_counter() - started)
            if problems is not None and processor.tracker.map.next_kf_id != keyframes:
                problem = bundle.build_problem(processor.tracker.map, options.tracker.bundle)
                if problem is not None:
                    problems.append(problem)
    finally:
        processor.close()
    return results, truth, seconds, processor


def _solver_comparison(problems: list, fx: float, repeats: int = 3) -> dict:
    """Our Schur-complement solver against SciPy's least_squares on the same windows (every
    third keyframe's): median time per window (each the median of ``repeats`` solves) and
    the final reprojection error of both, in this process, one after the other."""
    from cubeloc.positioning.tracking import bundle
    from cubeloc.positioning.tracking.options import BundleOptions

    seconds: dict[str, list[float]] = {"schur": [], "scipy": []}
    rms: dict[str, list[float]] = {"schur": [], "scipy": []}
    for problem in problems[::3]:
        for solver in seconds:
            options = BundleOptions(solver=solver)
            runs = [bundle.solve(problem, options, fx) for _ in range(repeats)]
            seconds[solver].append(float(np.median([r.seconds for r in runs])))
            rms[solver].append(runs[0].final_rms_px)
    ratio = np.array(seconds["scipy"]) / np.array(seconds["schur"])
    return {
        "windows": len(seconds["schur"]),
        "schur_ms": 1000 * float(np.median(seconds["schur"])),
        "scipy_ms": 1000 * float(np.median(seconds["scipy"])),
        "speedup": float(np.median(ratio)),
        "schur_rms": float(np.mean(rms["schur"])),
        "scipy_rms": float(np.mean(rms["scipy"])),
    }


THROUGHPUT_FRAMES = 300
RUNS = 3
LIVE_RUNS = 4  # live runs of each solver at 10 fps (half as many at 30 fps)


def _long_run(sequence: Path, frames: int) -> dict:
    """In this (child) process: ``frames`` frames with background bundle adjustment;
    peak RSS and the map at the end."""
    started = time.process_time()
    results, _, seconds, processor = _replay(sequence, background=True, frames=frames)
    world = processor.tracker.map
    return {
        "frames": frames,
        "fps": frames / float(np.sum(seconds)),
        "cpu_s": time.process_time() - started,
        "posed": sum(r.estimate is not None for r in results),
        "peak_rss_mb": _peak_rss_mb(),
        "keyframes": len(world.keyframes),
        "points": len(world.points),
    }


def _live(sequence: Path, options=None) -> dict:
    """The daemon's situation: the frames arrive on the camera's clock (the sequence's own
    rate) into the daemon's newest-frame slot, and the tracker takes the newest one when it
    is ready; frames it is too slow for are skipped, as live. Bundle adjustment in its
    thread. The images are decoded beforehand: PNG decoding is not the camera's work."""
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.daemon.frame_queue import CapturedFrame, LatestFrameSlot
    from cubeloc.drivers.base import Frame
    from cubeloc.drivers.sequence import read_image, read_sequence_index
    from cubeloc.positioning.evaluation import absolute_trajectory_error
    from cubeloc.positioning.target import load_target
    from cubeloc.positioning.tracking.processor import TrackingProcessor
    from cubeloc.positioning.trajectory_io import StampedPose, read_tum

    entries = read_sequence_index(sequence)
    images = [read_image(e.path) for e in entries]
    truth = read_tum(sequence / "groundtruth.tum")
    processor = TrackingProcessor(load_target(sequence / "target.yaml"), read_camera_info(sequence / "camera.yaml"),
                                  options)
    slot, delivered = LatestFrameSlot(), threading.Event()
    period_s = (entries[1].stamp_ns - entries[0].stamp_ns) / 1e9

    def camera() -> None:
        started = time.monotonic()
        for i, (entry, image) in enumerate(zip(entries, images, strict=True)):
            time.sleep(max(0.0, started + i * period_s - time.monotonic()))
            slot.put(CapturedFrame(Frame(image, i, entry.stamp_ns, entry.stamp_ns, 0.0), i, time.monotonic_ns()))
        delivered.set()

    results, stamps, busy = [], [], []
    feeder = threading.Thread(target=camera, daemon=True)
    cpu, wall = time.process_time(), time.perf_counter()
    feeder.start()
    try:
        while True:
            item = slot.get(0.2)
            if item is None and delivered.is_set():
                item = slot.get(0.0)  # the last frame may have come just after the wait
                if item is None:
                    break
            if item is None:
                continue
            began = time.perf_counter()
            results.append(processor.process(item.frame.image, item.frame.stamp_ns, item.seq))
            busy.append(time.perf_counter() - began)
            stamps.append(item.frame.stamp_ns)
    finally:
        processor.close()
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    estimates = [StampedPose(t, r.estimate.T_world_camera) for r, t in zip(results, stamps, strict=True)
                 if r.estimate is not None]
    ate = absolute_trajectory_error(truth, estimates)
    return {
        "camera_fps": 1.0 / period_s,
        "frames": len(entries),
        "processed": len(results),
        "fps": len(results) / wall,
        "busy_ms": 1000 * float(np.median(busy)),
        "cpu_per_frame_ms": 1000 * cpu / max(1, len(results)),
        "states": _states(results),
        "ate_mm": 1000 * ate.rmse_m,
        "max_mm": 1000 * ate.max_m,
        "bundles": len(processor.tracker.bundle_runs),
        "bundle_ms": 1000 * float(np.median([b.seconds for b in processor.tracker.bundle_runs] or [0.0])),
    }


def _live_section(paper: Path, paper_30: Path, live_runs: int) -> str:
    """Runs of our solver and SciPy's in turn, live at 10 and 30 fps: a markdown note."""
    rows = []
    for sequence, camera, runs in ((paper, "paper 30 s, 10 fps camera", live_runs),
                                   (paper_30, "paper 20 s, 30 fps camera", max(1, live_runs // 2))):
        by_solver: dict[str, list[dict]] = {"ours": [], "SciPy's (baseline)": []}
        for _ in range(runs):  # in turn, so that the machine's load falls on both alike
            by_solver["ours"].append(_live(sequence, _options(solver="schur")))
            by_solver["SciPy's (baseline)"].append(_live(sequence, _options(solver="scipy")))
        for solver, lives in by_solver.items():
            ate = [live["ate_mm"] for live in lives]
            rows.append([
                camera, solver,
                f"**{np.median(ate):.2f}** ({min(ate):.2f}-{max(ate):.2f}; {sum(a <= 5.0 for a in ate)} of "
                f"{len(ate)} within 5 mm)",
                ", ".join(f"{a:.2f}" for a in ate),
                f"{np.median([live['fps'] for live in lives]):.1f} of {lives[0]['camera_fps']:.0f}",
                f"{sum(live['frames'] - live['processed'] for live in lives)} of {sum(live['frames'] for live in lives)}",
                f"{np.median([live['busy_ms'] for live in lives]):.1f}",
                f"{np.median([live['cpu_per_frame_ms'] for live in lives]):.0f}",
                f"{np.median([live['bundle_ms'] for live in lives]):.0f}",
            ])
    return (
        "Live, as the daemon runs it (`_live`): frames on the camera's clock into the daemon's newest-frame slot, "
        "the tracker taking the newest when ready (skipping what it is too slow for), bundle adjustment in its "
        "worker thread; images decoded beforehand. Our solver and SciPy's run in turn. The runs differ (which "
        "keyframes a background solution covers depends on timing), so the RMS ATE is the median of the runs, "
        "with its range.\n\n" + markdown_table(
            ["camera", "bundle adjustment solver", "RMS ATE mm, median (range)", "runs", "frames processed per s",
             "skipped", "median ms per frame", "process CPU ms per frame", "median BA ms per window"], rows))


def _options(**bundle_changes):
    """The daemon's options with the default configuration, these bundle adjustment
    options changed."""
    from cubeloc.daemon.config import Config
    from cubeloc.daemon.preflight import processor_options

    return processor_options(Config(), **bundle_changes)


def _peak_rss_mb() -> float:
    """This process's peak RSS since it started its program. Linux's ``ru_maxrss`` keeps the
    peak from before ``exec``, when the forked child still shared its parent's pages (it
    reported 908 MB here once the parent held the live runs' decoded images); ``VmHWM``
    belongs to the process image itself."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _estimates(results, truth):
    from cubeloc.positioning.trajectory_io import StampedPose

    return [StampedPose(p.stamp_ns, r.estimate.T_world_camera)
            for r, p in zip(results, truth, strict=False) if r.estimate is not None]


def _states(results) -> str:
    counts: dict[str, int] = {}
    for r in results:
        key = r.estimate.state.value if r.estimate is not None else r.status
        counts[key] = counts.get(key, 0) + 1
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))


def run() -> str:
    from cubeloc.positioning.evaluation import (
        absolute_trajectory_error,
        relative_pose_error,
        scale_drift,
    )

    rows, notes = [], []
    keep = os.environ.get("CUBELOC_BENCH_SEQUENCES")
    with tempfile.TemporaryDirectory(prefix="cubeloc-bench-tracker-") as tmp:
        root = Path(keep) if keep else Path(tmp)
        paper = _render(root, "paper", 30.0, seed=1)
        problems: list = []
        results, truth, seconds, processor = _replay(paper, background=False, problems=problems)
        solvers = _solver_comparison(problems, processor.tracker.fx)
        ate = absolute_trajectory_error(truth, _estimates(results, truth))
        rpe = relative_pose_error(truth, _estimates(results, truth), delta_m=1.0)
        if keep:  # for a check with evo: evo_ape tum DIR/paper/groundtruth.tum DIR/paper.tum
            from cubeloc.positioning.trajectory_io import write_tum

            write_tum(root / "paper.tum", _estimates(results, truth))
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

        runs = int(os.environ.get("CUBELOC_BENCH_RUNS", str(RUNS)))
        fps, cpu_fps, per_state, bundles = [], [], {}, []
        for _ in range(runs):
            cpu = time.process_time()
            results, truth, seconds, processor = _replay(paper, background=True, frames=THROUGHPUT_FRAMES)
            cpu = time.process_time() - cpu
            fps.append(THROUGHPUT_FRAMES / float(np.sum(seconds)))
            cpu_fps.append(THROUGHPUT_FRAMES / cpu)  # includes PNG decoding and the BA thread
            bundles += [b.seconds for b in processor.tracker.bundle_runs]
            for r, t in zip(results, seconds, strict=True):
                key = r.estimate.state.value if r.estimate is not None else r.status
                per_state.setdefault(key, []).append(t)
        split = ", ".join(f"{k} {1000 * np.median(v):.1f} ms (n={len(v)})" for k, v in sorted(per_state.items()))
        load = os.getloadavg()[0]
        notes.append(
            f"Load average {load:.1f} on {os.cpu_count()} cores at the end of these runs (a shared machine: "
            f"the fps follows the others' load). "
            f"Throughput at 1280x1024, bundle adjustment in its worker thread, the paper sequence played "
            f"forwards and backwards, {THROUGHPUT_FRAMES} frames per run: **{np.median(fps):.1f} fps** sustained "
            f"(median of {runs} runs: {', '.join(f'{f:.1f}' for f in fps)}; wall time of the frame processor). "
            f"By process CPU time (PNG decoding and the BA thread included): {np.median(cpu_fps):.1f} frames per "
            f"CPU-second. Median time per frame by state: {split}. Median bundle adjustment "
            f"{1000 * np.median(bundles):.0f} ms for a window of "
            f"{processor.options.tracker.bundle.window_keyframes} keyframes (in its thread, never awaited)."
        )

        notes.append(
            f"Bundle adjustment solvers side by side on the same {solvers['windows']} windows of `paper` (every "
            f"third keyframe's; each time the median of 3 solves, one solver after the other): ours "
            f"(Levenberg-Marquardt on the Schur complement) **{solvers['schur_ms']:.0f} ms** per window, SciPy's "
            f"least_squares (trf, LSMR; the former solver) {solvers['scipy_ms']:.0f} ms; median ratio "
            f"**{solvers['speedup']:.1f}x**. Final reprojection error, mean over the windows: "
            f"{solvers['schur_rms']:.4f} px (ours), {solvers['scipy_rms']:.4f} px (SciPy)."
        )

        # As live: the camera's clock, the newest-frame slot, bundle adjustment in its thread.
        paper_30 = _render(root, "paper_30fps", 20.0, seed=1, fps=30.0, trajectory="paper")
        live_runs = int(os.environ.get("CUBELOC_BENCH_LIVE_RUNS", str(LIVE_RUNS)))
        notes.append(_live_section(paper, paper_30, live_runs))

        frames = int(os.environ.get("CUBELOC_BENCH_LONG_FRAMES", "6000"))
        child = subprocess.run(
            [sys.executable, "-c", f"import json, sys; from pathlib import Path; from bench.tracker import _long_run; "
                                   f"print(json.dumps(_long_run(Path(sys.argv[1]), {frames})))", str(paper)],
            capture_output=True, text=True, check=True, cwd=Path(__file__).resolve().parents[1],
        )
        long = json.loads(child.stdout.strip().splitlines()[-1])
        notes.append(
            f"Memory: {long['frames']} frames ({long['frames'] / 600:.1f} minutes of a 10 fps camera; the 30 s of "
            f"`paper` cycled forwards and backwards, not 10 minutes of fresh rendering) in a child process: "
            f"peak RSS **{long['peak_rss_mb']:.0f} MB**, {long['fps']:.1f} fps, {long['posed']} frames with a "
            f"pose; map at the end: {long['keyframes']} keyframes, {long['points']} points (bounded by culling)."
        )
    table = markdown_table(["scenario", "RMS ATE mm (no alignment)", "max mm", "relative / drift", "frames"], rows)
    return table + "\n" + "\n\n".join(notes) + "\n"
