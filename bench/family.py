"""The tracker on the randomized family (``fakes.family``): distributions over seeds, never
one scenario, this tree and the tracker of ``BASELINE_COMMIT`` side by side on the same frames.

Each seed is rendered once into a cache (``CUBELOC_BENCH_FAMILY=DIR``, default
``.cache/family`` in the repository, ignored by git) and re-rendered only when the family's
frames would change (its ``render.key``). Each tree replays it with ``cubeloc track``
in a child process (bundle adjustment in the frame loop, so every run is the same).

Per seed: coverage, the share of frames lost where an earlier posed frame had seen the
place (within 0.7 m and 25 deg, on the truth: ``evaluation.lost_where_seen_before``, what
relocalisation could at best give back; the rest of the lost frames need the map to grow),
RMS and max position error with no alignment, the error per metre
travelled since the cube was last in view (median over the frames at least 1 m from it),
the longest stretch without a pose (seconds), the share of poses inside their 3-sigma
ellipsoid and those beyond 5 sigma, where the map's scale walks (``evaluation.scale_walk``
on the poses not from the target, over 0.5 m stretches: the RMS step of the scale across a
turn of 30 deg or more, the rate it walks at between stretches driven on (% per root metre),
the largest single step, and the median share by which the estimate turns less than the
camera in a turn),
fps (the replay's own), and whether the seed meets the
tracker issue's goals: coverage >= 99 %, RMS <= 5 mm + 1 % of the longest path driven with
the cube out of view, no pose beyond 5 sigma. On a seed the generator flags unobservable
the goal is the same coverage with the position held (its covariance growing), so the
flag is shown beside the figures, not taken off them.

``CUBELOC_BENCH_BASELINE_COMMIT`` another baseline commit (the tree before a change);
``CUBELOC_BENCH_FAMILY_SET``: ``half`` (default; 12 seeds at 640x512, for day-to-day
work) or ``full`` (40 seeds at 1280x1024). ``CUBELOC_BENCH_FAMILY_SEEDS=1,2,3`` picks seeds;
``CUBELOC_BENCH_BASELINE=DIR`` an existing checkout of the baseline instead of a worktree;
``CUBELOC_BENCH_FAMILY_BASELINE=0`` runs this tree alone; ``CUBELOC_BENCH_FAMILY_JOBS`` how many
runs go at once (default: the cores); ``CUBELOC_BENCH_FAMILY_DRAWS`` how many draws a seed
(default 3); ``CUBELOC_BENCH_FAMILY_ODOMETRY=1`` replays each seed with the robot's wheel
odometry (``fakes.family.wheel_odometry``: 1.5 % long, turns 1 % long, a heading drift).

**Draws.** One replay of a seed is one draw of its outcome: the tracker's path hangs on
thresholds that a drifting map crosses either way, and the same frames replayed from the
second frame, or with the target's poses moved by 0.1 um, lose or keep the map at other
frames (docs/family.md). So each seed is replayed from frame 0, 1, ... (``cubeloc track
--first``), each replay scored on its own frames, and the distributions are over all the
runs, with each seed's spread beside them.

``python -m bench.family SEQUENCE [--first N --last N --every N]`` traces one rendered
member frame by frame (status, error, claimed sigma, map, tracks, textured share).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from bench.common import REPO, baseline_commit, machine_line, markdown_table, previous_tree
from bench.scenarios import _track, read_poses

TITLE = "Tracker on the randomized family of scenes, robots and motions"
BASELINE_COMMIT = "47a9a9c"
SETS = {"half": tuple(range(12)), "full": tuple(range(40))}
WITH_WHEELS = " with the robot's wheel odometry (`CUBELOC_BENCH_FAMILY_ODOMETRY=1`)"
# the scale's walk over stretches this long: a room's drives between turns are 1-3 m
WALK_STRETCH_M = 0.5


def cached_case(root: Path, seed: int, resolution: str) -> Path:
    """The rendered sequence of family member ``seed``, rendered now if not cached or stale."""
    import shutil

    from cubeloc.atomic import atomic_write_text
    from cubeloc.fakes.family import make_case, render_case

    case = make_case(seed, resolution)
    out = root / resolution / f"seed-{seed}"
    key = out / "render.key"
    if key.is_file() and (out / "groundtruth.tum").is_file() and key.read_text().strip() == case.render_key():
        if (out / "family.json").read_text() != case.describe_json():  # the description alone changed
            atomic_write_text(out / "family.json", case.describe_json())
        return out
    if out.exists():
        shutil.rmtree(out)
    render_case(case, out)
    return out


def seed_figures(sequence: Path, per_frame: list, first: int = 0, sources: list | None = None) -> dict:
    """The per-seed figures of one run (see the module's docstring); a run replayed from
    frame ``first`` is scored on the frames from there. ``sources``: each frame's pose
    source (``read_poses``); the scale's walk leaves out the target's poses."""
    from cubeloc.fakes.family import make_case
    from cubeloc.positioning.evaluation import lost_where_seen_before, scale_walk, score_run
    from cubeloc.positioning.trajectory_io import read_tum

    truth = read_tum(sequence / "groundtruth.tum")[first:]
    per_frame = per_frame[first:]
    described = json.loads((sequence / "family.json").read_text())
    score = score_run(truth, per_frame)
    since = make_case(described["seed"], described["resolution"]).path_since_target()[first:]
    errors = np.array([np.nan if e is None else
                       float(np.linalg.norm(e[0].T_world_camera.translation - t.T_world_camera.translation))
                       for e, t in zip(per_frame, truth, strict=True)])
    far = (since >= 1.0) & np.isfinite(errors)
    per_metre = float(np.median(errors[far] / since[far])) * 1000 if far.any() else float("nan")
    away_m = float(since.max())
    bound_mm = 5.0 + 10.0 * away_m  # 5 mm + 1 % of the longest path away from the cube
    rms_mm = score.rmse_m * 1000
    away = None if sources is None else np.array([s != "target" for s in sources[first:]])
    walk = scale_walk(truth, [None if e is None else e[0] for e in per_frame], away, stretch_m=WALK_STRETCH_M)
    meets = score.coverage >= 0.99 and np.isfinite(rms_mm) and rms_mm <= bound_mm and score.beyond_5_sigma == 0
    return {"coverage": score.coverage, "rms_mm": rms_mm, "max_mm": score.max_m * 1000,
            "per_metre_mm": per_metre, "gap_s": score.longest_gap_frames / described["camera"]["fps"],
            "consistent": score.consistent, "beyond_5": score.beyond_5_sigma, "away_m": away_m,
            "bound_mm": bound_mm, "meets": bool(meets), "flagged": bool(described["unobservable"]),
            "frames": score.frames, "turn_step_pct": walk.turn_step_percent, "drive_walk_pct": walk.drive_walk_percent,
            "largest_step_pct": walk.largest_step_percent,
            "under_turn_pct": walk.under_turn_median_percent,
            "lost_seen": float(lost_where_seen_before(truth, [e is not None for e in per_frame]).mean())}


def wheels(sequence: Path, out: Path) -> tuple[str, ...]:
    """``cubeloc track`` arguments that replay the robot's wheel odometry with ``sequence``
    (``fakes.family.wheel_odometry``, written beside ``out``), the camera's mount exact, the
    odometry as bridge and motion prior (``[odometry]``'s defaults)."""
    from cubeloc.fakes.family import base_from_camera, make_case, wheel_odometry
    from cubeloc.fakes.odometry import write_odometry

    described = json.loads((sequence / "family.json").read_text())
    case = make_case(described["seed"], described["resolution"])
    odometry, config = out.with_name(f"{out.stem}-odometry.jsonl"), out.with_name(f"{out.stem}-odometry.toml")
    write_odometry(odometry, wheel_odometry(case))
    xyz, quaternion = base_from_camera(case)
    config.write_text(f"[frames.base_from_camera]\nxyz = {xyz}\nquaternion = {quaternion}\n[odometry]\nenabled = true\n")
    return "--odometry", str(odometry), "--config", str(config)


def run_tree(tree: Path, sequence: Path, work: Path, label: str, first: int = 0, odometry: bool = False) -> dict:
    """One ``cubeloc track`` of ``sequence`` from ``tree``, replayed from frame ``first``
    (``odometry``: with the robot's wheels, ``wheels``): its figures; a run that died is
    scored as no pose at all, with ``crashed`` its last words."""
    from cubeloc.drivers.sequence import read_sequence_index

    out = work / f"{sequence.name}-{label}-from-{first}.tum"
    extra = ("--no-plot",) + (("--first", str(first)) if first else ())  # (a baseline tree may lack --first)
    extra += wheels(sequence, out) if odometry else ()
    try:
        figures = _track(tree, sequence, out, poses=True, extra=extra)
    except RuntimeError as exc:
        nothing = [None] * len(read_sequence_index(sequence))
        return {**seed_figures(sequence, nothing, first), "fps": float("nan"),
                "crashed": str(exc).splitlines()[-1][-160:]}
    sources: list = []
    per_frame = read_poses(sequence, out.with_suffix(".jsonl"), sources)
    return {**seed_figures(sequence, per_frame, first, sources), "fps": figures["fps"]}


def distribution(values: list[float], higher_is_better: bool = False) -> str:
    """Median / 90th percentile / worst over seeds (for a figure where higher is better, the
    10th percentile and the lowest)."""
    finite = np.array([v for v in values if np.isfinite(v)])
    if len(finite) == 0:
        return "-"
    if higher_is_better:
        return f"{np.median(finite):.2f} / {np.percentile(finite, 10):.2f} / {np.min(finite):.2f}"
    return f"{np.median(finite):.2f} / {np.percentile(finite, 90):.2f} / {np.max(finite):.2f}"


def replays_from(tree: Path) -> bool:
    """Whether ``tree``'s ``cubeloc track`` has ``--first`` (a tree older than the draws
    replays each seed once, from its first frame)."""
    return "--first" in (tree / "daemon" / "commands" / "track.py").read_text()


def measure(seeds: list[int], which: str, root: Path, baseline: bool, jobs: int,
            draws: int = 1, odometry: bool = False) -> list[tuple[int, str, int, dict, dict]]:
    """(seed, tracker, first frame, figures, family.json) for each seed, each tree and each
    draw (the replay from frame 0, 1, ... ``draws - 1``), ``jobs`` child processes at once
    (``odometry``: each with the robot's wheel odometry); renders what the cache lacks first."""
    from concurrent.futures import ThreadPoolExecutor

    sequences = {seed: cached_case(root, seed, which) for seed in seeds}
    with tempfile.TemporaryDirectory(prefix="cubeloc-bench-family-") as tmp:
        work = Path(tmp)
        # the baseline's checkout only when it runs
        checkout = previous_tree(baseline_commit(BASELINE_COMMIT), work, os.environ.get("CUBELOC_BENCH_BASELINE")) \
            if baseline \
            else contextlib.nullcontext(None)
        with checkout as previous:
            trees = [("this tree", REPO)] + ([("baseline", previous)] if previous else [])
            runs = [(seed, label, tree, first) for first in range(draws) for seed in seeds for label, tree in trees
                    if first == 0 or replays_from(tree)]
            with ThreadPoolExecutor(max(1, jobs)) as pool:
                figures = list(pool.map(lambda r: run_tree(r[2], sequences[r[0]], work, r[1].replace(" ", "-"), r[3],
                                                                 odometry),
                                        runs))
    return [(seed, label, first, f, json.loads((sequences[seed] / "family.json").read_text()))
            for (seed, label, _, first), f in zip(runs, figures, strict=True)]


def report(results: list[tuple[int, str, int, dict, dict]], which: str, jobs: int, odometry: bool = False) -> str:
    """The bench's section: the distributions over seeds (and draws), the spread of each
    seed over its draws, then each run (``odometry``: the runs had the robot's wheels)."""
    rows, by_tree, by_seed = [], {}, {}
    for seed, label, first, f, described in sorted(results, key=lambda r: (r[0], r[1] != "this tree", r[2])):
        by_tree.setdefault(label, []).append(f)
        by_seed.setdefault((seed, label), []).append(f)
        cam, motion = described["camera"], described["motion"]
        rows.append([seed, label, first, f"{described['kind']} {described['room_m'][0]:.0f}x{described['room_m'][1]:.0f}",
                     f"{cam['hfov_deg']:.0f} deg, {cam['fps']:g} fps, lever {cam['lever_m']:.2f}",
                     f"{motion['speed_m_s']:.2f} m/s, {motion['turn_deg_s']:.0f} deg/s, {motion['seconds']:.0f} s",
                     ", ".join(described["unobservable"]) or "-",
                     f"{100 * f['coverage']:.1f} %", f"{100 * f['lost_seen']:.1f} %", f"{f['rms_mm']:.1f}",
                     f"{f['max_mm']:.0f}",
                     f"{f['per_metre_mm']:.1f}", f"{f['gap_s']:.1f}",
                     f"{100 * f['consistent']:.1f} % ({f['beyond_5']})",
                     f"{f['turn_step_pct']:.1f} / {f['drive_walk_pct']:.2f} / {f['largest_step_pct']:.1f}",
                     f"{f['under_turn_pct']:+.2f}",
                     f"{f['fps']:.1f}",
                     "crashed" if f.get("crashed") else "yes" if f["meets"] else "no"])
    table = markdown_table(["seed", "tracker", "from frame", "scene", "camera", "motion", "unobservable", "coverage",
                            "lost where seen before", "RMS mm",
                            "max mm", "mm per m away", "longest gap s", "inside 3 sigma (beyond 5)",
                            "scale: step a turn % / walk driving % per m^0.5 / largest step %", "under-turn %", "fps",
                            "meets goals"], rows)
    summary_rows = []
    for label, group in by_tree.items():
        for subset, chosen in (("all", group), ("observable", [f for f in group if not f["flagged"]])):
            if not chosen:
                continue
            summary_rows.append([label, subset, len(chosen), f"{sum(f['meets'] for f in chosen)}",
                                 distribution([100 * f["coverage"] for f in chosen], True),
                                 distribution([100 * f["lost_seen"] for f in chosen]),
                                 distribution([f["rms_mm"] for f in chosen]),
                                 distribution([f["max_mm"] for f in chosen]),
                                 distribution([f["per_metre_mm"] for f in chosen]),
                                 distribution([f["gap_s"] for f in chosen]),
                                 distribution([100 * f["consistent"] for f in chosen], True),
                                 distribution([f["beyond_5"] for f in chosen]),
                                 distribution([f["turn_step_pct"] for f in chosen]),
                                 distribution([f["drive_walk_pct"] for f in chosen]),
                                 distribution([f["largest_step_pct"] for f in chosen]),
                                 distribution([abs(f["under_turn_pct"]) for f in chosen]),
                                 distribution([f["fps"] for f in chosen], True)])
    summary = markdown_table(["tracker", "seeds", "count", "meet the goals", "coverage % (median / p10 / worst)",
                              "lost where seen before %", "RMS mm (median / p90 / worst)", "max mm", "mm per m away", "longest gap s",
                              "inside 3 sigma % (median / p10 / worst)", "beyond 5 sigma", "scale step a turn %",
                              "scale walk driving % per m^0.5", "largest scale step %", "under-turn % (size)", "fps (median / p10 / worst)"],
                             summary_rows)
    seeds = sorted({seed for seed, *_ in results})
    draws = max(first for _, _, first, *_ in results) + 1
    spread = ""
    if draws > 1:
        spread_rows = [[seed, label, len(group),
                        f"{100 * min(f['coverage'] for f in group):.1f} - {100 * max(f['coverage'] for f in group):.1f}",
                        f"{min(f['rms_mm'] for f in group):.1f} - {max(f['rms_mm'] for f in group):.1f}",
                        f"{min(f['beyond_5'] for f in group)} - {max(f['beyond_5'] for f in group)}",
                        sum(f["meets"] for f in group)]
                       for (seed, label), group in sorted(by_seed.items(), key=lambda kv: (kv[0][0], kv[0][1] != "this tree"))]
        spread = ("\nEach seed over its draws (lowest - highest):\n\n" + markdown_table(
            ["seed", "tracker", "draws", "coverage %", "RMS mm", "beyond 5 sigma", "draws meeting the goals"],
            spread_rows))
    return (f"{machine_line()}. Family set `{which}` (seeds {', '.join(map(str, seeds))}), `cubeloc track` per "
            f"seed{WITH_WHEELS if odometry else ''}, "
            f"bundle adjustment in the frame loop, {jobs} runs at once (fps is each run's own, on a loaded "
            f"machine); " + (f"**baseline** = commit {baseline_commit(BASELINE_COMMIT)}. " if "baseline" in by_tree else
                         f"this tree alone (`CUBELOC_BENCH_FAMILY_BASELINE=0`; the baseline, commit {BASELINE_COMMIT}, "
                         "on the same frames: [family.md](family.md)). ")
            + (f"{draws} draws a seed: the replay from frame 0 to {draws - 1} (a tree without `cubeloc track "
               "--first` replays from frame 0 only); each draw is scored on the frames it replayed. "
               if draws > 1 else "")
            + "Errors are positions against the ground truth with "
            "no alignment; RMS and max over the frames with a pose. Distributions are median / 90th percentile / "
            f"worst over the {'runs (every seed and draw)' if draws > 1 else 'seeds'}; *observable* leaves out the "
            "seeds the generator flags (`blank_view`, `rotation_on_axis`).\n\n" + summary + spread
            + "\nPer run:\n\n" + table)


def run() -> str:
    which = os.environ.get("CUBELOC_BENCH_FAMILY_SET", "half")
    seeds = [int(s) for s in os.environ.get("CUBELOC_BENCH_FAMILY_SEEDS", "").split(",") if s] or list(SETS[which])
    root = Path(os.environ.get("CUBELOC_BENCH_FAMILY", REPO / ".cache" / "family")).resolve()
    baseline = os.environ.get("CUBELOC_BENCH_FAMILY_BASELINE", "1") != "0"
    jobs = int(os.environ.get("CUBELOC_BENCH_FAMILY_JOBS", os.cpu_count() or 1))
    draws = int(os.environ.get("CUBELOC_BENCH_FAMILY_DRAWS", "3"))
    odometry = os.environ.get("CUBELOC_BENCH_FAMILY_ODOMETRY", "0") == "1"
    if draws < 1:
        raise SystemExit(f"CUBELOC_BENCH_FAMILY_DRAWS={draws}: at least 1")
    return report(measure(seeds, which, root, baseline, jobs, draws, odometry), which, jobs, odometry)


def trace(sequence: Path, first: int = 0, last: int | None = None, every: int = 1) -> None:
    """Print, frame by frame, what the tracker did on a rendered family member: status and
    detail, position error and claimed standard deviation (mm), keyframes, map points,
    live tracks and how many of them have a map point, and the textured share of the view."""
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.daemon.replay import track_sequence
    from cubeloc.positioning.trajectory_io import read_tum

    calibration = read_camera_info(sequence / "camera.yaml")
    truth = read_tum(sequence / "groundtruth.tum")
    described = json.loads((sequence / "family.json").read_text())
    from cubeloc.fakes.family import make_case

    textured = make_case(described["seed"], described["resolution"]).textured

    def row(frame, image, processor) -> None:
        i, result = frame.seq, frame.result
        if i < first or (i - first) % every:
            return
        tracker, estimate = processor.tracker, result.estimate
        error = sigma = "-"
        if estimate is not None:
            error = f"{1000 * np.linalg.norm(estimate.T_world_camera.translation - truth[i].T_world_camera.translation):.1f}"
            if estimate.covariance is not None:
                sigma = f"{1000 * np.sqrt(np.trace(estimate.covariance[:3, :3])):.1f}"
        ids = processor.front_end.ids
        mapped = int(tracker.map.mapped(ids).sum())
        print(f"{i} {result.status} [{result.detail[:48]}] err {error} sigma {sigma} kf {len(tracker.map.keyframes)} "
              f"points {len(tracker.map.points)} tracks {len(ids)} mapped {mapped} textured {textured[i]:.2f}",
              flush=True)

    track_sequence(sequence, calibration, last=last, on_frame=row)


def target_recall(sequences: list[Path], every: int = 15) -> None:
    """Print, per rendered family member and in all, on how many frames the AprilTag library
    finds a tag of the cube over the full frame, for each way of searching it: decimation 3
    then 2 when empty; with a pass at 2 blurred (the library's ``quadSigma`` 0.8); with a
    pass at 1; with a pass at 1 and then at 1 blurred. Every ``every``-th frame where the
    truth puts the cube's centre in the image (40 px from its edges) within 3.5 m."""
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.drivers.sequence import read_image, read_sequence_index
    from cubeloc.positioning.detection import TagDetector
    from cubeloc.positioning.target import make_cube
    from cubeloc.positioning.trajectory_io import read_tum

    ids = set(make_cube().ids)
    detector = TagDetector()
    names = ("decimation 3, then 2", "+ 2 blurred", "+ 1", "+ 1, then 1 blurred")
    total = np.zeros(len(names) + 1, int)
    for sequence in sequences:
        calibration = read_camera_info(sequence / "camera.yaml")
        truth = read_tum(sequence / "groundtruth.tum")
        entries = read_sequence_index(sequence)
        counts = np.zeros(len(names) + 1, int)
        for i in range(0, len(entries), every):
            centre = truth[i].T_world_camera.inverse().apply(np.zeros((1, 3)))[0]
            if centre[2] <= 0.05 or np.linalg.norm(centre) > 3.5:
                continue
            pixel = calibration.camera_matrix @ (centre / centre[2])
            if not (40 <= pixel[0] <= calibration.width - 40 and 40 <= pixel[1] <= calibration.height - 40):
                continue
            image = read_image(entries[i].path)

            def found(decimate: float, sigma: float = 0.0, image=image) -> bool:
                return any(d.tag_id in ids for d in detector.detect(image, None, decimate, sigma))

            plain = found(3.0) or found(2.0)
            blurred, fine = found(2.0, 0.8), found(1.0)
            counts += [1, plain, plain or blurred, plain or fine, plain or fine or found(1.0, 0.8)]
        total += counts
        print(f"{sequence.name}: {counts[0]} frames; " + ", ".join(f"{n} {c}" for n, c in zip(names, counts[1:], strict=True)),
              flush=True)
    print(f"all: {total[0]} frames; " + ", ".join(f"{n} {c}" for n, c in zip(names, total[1:], strict=True)))


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="trace the tracker frame by frame on a rendered family member "
                                                 "(or, with --recall, how often the cube in view is found)")
    parser.add_argument("sequence", type=Path, nargs="+",
                        help="a family member's sequence directory (cubeloc simulate --family); several with --recall")
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--last", type=int, default=None)
    parser.add_argument("--every", type=int, default=None, help="every N-th frame (default 1; 15 with --recall)")
    parser.add_argument("--recall", action="store_true",
                        help="on how many frames with the cube in view each full-frame search finds it")
    arguments = parser.parse_args()
    if arguments.recall:
        target_recall([s.resolve() for s in arguments.sequence], arguments.every or 15)
    else:
        trace(arguments.sequence[0].resolve(), arguments.first, arguments.last, arguments.every or 1)
