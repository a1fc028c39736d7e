"""The tracker through the robot-motion scenarios, the new tracker and the previous one
side by side, at full resolution (1280x1024, the paper's camera).

Each scenario of ``fakes.scenarios`` (and ``paper``, ``orbit``, ``room_walk``, which must be
no worse than before) is rendered once (default length, seed 1) and replayed through
``cubeloc track`` in a child process, bundle adjustment in the frame loop (deterministic):

- **new**: this tree, with ``--poses`` (the covariance of every pose);
- **previous**: the tracker of commit ``BASELINE_COMMIT`` (the last one before the robot
  motions), checked out with ``git worktree`` into a temporary directory and run the
  same way, from its own tree. It publishes no covariance while tracking, so it has no
  consistency figure.

Per run: coverage (frames with a pose / frames), RMS and max position error with no
alignment, the longest stretch without a pose, the share of poses inside their own 3-sigma
ellipsoid (NEES <= 14.16, 3 dof) and the count beyond 5 sigma, frames per second (the
replay's own figure: PNG decoding excluded), and the child's peak RSS (VmHWM).

Then each scenario **live**, as the daemon runs it (``bench.tracker._live``: frames on the
camera's clock into the newest-frame slot, bundle adjustment in its thread), new tracker
only: frames processed and skipped, and the error of what was published.

Environment: ``CUBELOC_BENCH_SEQUENCES=DIR`` keeps the renders (an hour's worth at full
resolution, agile's exposure-long blur the most) for later runs; ``CUBELOC_BENCH_SCENARIOS``
a comma-separated subset; ``CUBELOC_BENCH_BASELINE=DIR`` an existing checkout of the
previous tracker instead of a fresh worktree; ``CUBELOC_BENCH_BASELINE_COMMIT`` another
previous commit (the tree before a change).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.common import (
    REPO,
    baseline_commit,
    machine_line,
    markdown_table,
    package_prefix,
    previous_tree,
)
from bench.tracker import _live, _options

TITLE = "Tracker through robot motions: new and previous side by side"
BASELINE_COMMIT = "9580d93"
SCENARIOS = ("turn_after_init", "spin_in_place", "spin_in_place_fast", "spin_on_axis", "agile", "passers_by",
             "blank_wall", "long_lap", "paper", "orbit", "room_walk")
# run cubeloc's CLI (the module named first: a tree's own, bench.common.package_prefix), then report the process's peak resident memory on stderr
_WRAPPER = (
    "import atexit, runpy, sys\n"
    "def _peak():\n"
    "    for line in open('/proc/self/status'):\n"
    "        if line.startswith('VmHWM:'):\n"
    "            print('PEAK_RSS_KB', line.split()[1], file=sys.stderr)\n"
    "atexit.register(_peak)\n"
    "module = sys.argv[1]\n"
    "sys.argv = ['cubeloc', *sys.argv[2:]]\n"
    "runpy.run_module(module, run_name='__main__')\n"
)


def _render(root: Path, name: str, seed: int = 1) -> Path:
    from cubeloc.fakes.sequence import write_synthetic_sequence

    out = root / (name if seed == 1 else f"{name}-seed{seed}")
    if not (out / "groundtruth.tum").is_file():
        write_synthetic_sequence(out, name, seed=seed)
    return out


def _track(tree: Path, sequence: Path, out: Path, poses: bool, extra: tuple[str, ...] = ()) -> dict:
    """One ``cubeloc track`` (with ``extra`` arguments) in a child process from ``tree``:
    its summary figures."""
    args = [sys.executable, "-c", _WRAPPER, f"{package_prefix(tree)}daemon.cli", "track", "--target", str(sequence / "target.yaml"),
            "--calib", str(sequence / "camera.yaml"), "--sequence", str(sequence), "--out", str(out), *extra]
    if poses:
        args += ["--poses", str(out.with_suffix(".jsonl"))]
    # the bench's own CUBELOC_BENCH_* variables are not config keys for the child's --config
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("CUBELOC_BENCH_")}, "PYTHONPATH": str(tree)}
    done = subprocess.run(args, cwd=tree, env=env, capture_output=True, text=True, timeout=3600)
    if done.returncode != 0:
        raise RuntimeError(f"cubeloc track in {tree} failed: {done.stderr.strip()[-400:]}")
    fps = re.search(r"\(([0-9.]+) fps\)", done.stdout)
    peak = re.search(r"PEAK_RSS_KB (\d+)", done.stderr)
    return {"fps": float(fps.group(1)) if fps else float("nan"),
            "peak_mb": int(peak.group(1)) / 1024 if peak else float("nan")}


def read_poses(sequence: Path, poses_jsonl: Path, sources: list | None = None) -> list:
    """Per frame of ``sequence``: (StampedPose, 6x6 covariance or None) from ``cubeloc track
    --poses``, or None for a frame without a pose. ``sources``, when given, is filled with
    each frame's pose source (``target``, ``map``, ...; None without a pose)."""
    from cubeloc.drivers.sequence import read_sequence_index
    from cubeloc.positioning.geometry import Transform
    from cubeloc.positioning.trajectory_io import StampedPose

    by_stamp = {}
    for line in poses_jsonl.read_text().splitlines():
        doc = json.loads(line)
        pose = Transform.from_quaternion(np.array(doc["position"]), np.array(doc["orientation"]))
        cov = None if doc["covariance"] is None else np.array(doc["covariance"]).reshape(6, 6)
        by_stamp[doc["stamp_ns"]] = (StampedPose(doc["stamp_ns"], pose), cov, doc.get("source"))
    frames = [by_stamp.get(e.stamp_ns) for e in read_sequence_index(sequence)]
    if sources is not None:
        sources[:] = [None if f is None else f[2] for f in frames]
    return [None if f is None else f[:2] for f in frames]


def _score(sequence: Path, out: Path, poses: bool):
    from cubeloc.drivers.sequence import read_sequence_index
    from cubeloc.positioning.evaluation import score_run
    from cubeloc.positioning.trajectory_io import read_tum

    truth = read_tum(sequence / "groundtruth.tum")
    if poses:
        return score_run(truth, read_poses(sequence, out.with_suffix(".jsonl")))
    stamps = [e.stamp_ns for e in read_sequence_index(sequence)]
    by_stamp: dict[int, tuple] = {}
    frame_stamps = np.array(stamps)
    for p in read_tum(out):  # TUM stamps are seconds: back to the nearest frame's
        i = int(np.clip(np.searchsorted(frame_stamps, p.stamp_ns), 1, len(stamps) - 1))
        nearest = i if abs(stamps[i] - p.stamp_ns) < abs(stamps[i - 1] - p.stamp_ns) else i - 1
        by_stamp[stamps[nearest]] = (p, None)
    return score_run(truth, [by_stamp.get(s) for s in stamps])


def run() -> str:
    chosen = [s for s in os.environ.get("CUBELOC_BENCH_SCENARIOS", ",".join(SCENARIOS)).split(",") if s]
    keep = os.environ.get("CUBELOC_BENCH_SEQUENCES")
    with tempfile.TemporaryDirectory(prefix="cubeloc-bench-scenarios-") as tmp:
        work = Path(tmp)
        root = Path(keep) if keep else work / "sequences"
        root.mkdir(parents=True, exist_ok=True)
        rows = []
        with previous_tree(baseline_commit(BASELINE_COMMIT), work, os.environ.get("CUBELOC_BENCH_BASELINE")) as previous:
            for name in chosen:
                sequence = _render(root, name)
                for label, tree, poses in (("new", REPO, True), ("previous", previous, False)):
                    if tree is None:
                        continue
                    out = work / f"{name}-{label}.tum"
                    figures = _track(tree, sequence, out, poses)
                    s = _score(sequence, out, poses)
                    rows.append([name, label, f"{100 * s.coverage:.1f} %", f"{s.rmse_m * 1000:.2f}",
                                 f"{s.max_m * 1000:.1f}", str(s.longest_gap_frames),
                                 f"{100 * s.consistent:.1f} % ({s.beyond_5_sigma})" if poses else "-",
                                 f"{figures['fps']:.1f}", f"{figures['peak_mb']:.0f}"])
                    print("  " + " | ".join(rows[-1]), flush=True)
        live_rows = []
        for name in chosen:
            live = _live(root / name, _options())
            posed = sum(int(n) for n in re.findall(r"(?:target|tracking|relocalised) (\d+)", live["states"]))
            live_rows.append([name, f"{live['camera_fps']:.0f}", f"{live['processed']} of {live['frames']}",
                              f"{100 * (1 - live['processed'] / live['frames']):.1f} %",
                              f"{100 * posed / live['frames']:.1f} %", f"{live['ate_mm']:.2f}",
                              f"{live['max_mm']:.1f}", f"{live['busy_ms']:.1f}"])
            print("  live " + " | ".join(live_rows[-1]), flush=True)
    table = markdown_table(["scenario", "tracker", "coverage", "RMS mm", "max mm", "longest gap (frames)",
                            "inside 3 sigma (beyond 5)", "fps", "peak RSS MB"], rows)
    live_table = markdown_table(["scenario", "camera fps", "processed", "skipped", "frames with a pose",
                                 "RMS mm", "max mm", "median ms per frame"], live_rows)
    return (f"{machine_line()}. `cubeloc track` per scenario (seed 1, default length, 1280x1024), bundle "
            f"adjustment in the frame loop; **previous** = commit {baseline_commit(BASELINE_COMMIT)}. Errors are positions "
            "against the ground truth with no alignment; fps is the replay's own (PNG decoding excluded), on "
            "a shared machine.\n\n" + table + "\nLive, as the daemon runs it (new tracker; frames on the camera's "
            "clock into the newest-frame slot, bundle adjustment in its worker thread, images decoded "
            "beforehand):\n\n" + live_table)
