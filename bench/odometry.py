"""Wheel odometry in: the tracker with and without it, on the same frames.

For each scenario the frames are the scenario bench's (``CUBELOC_BENCH_SCENARIOS=DIR``
keeps them); the odometry is simulated along the same trajectory (fakes/odometry.py):
50 Hz on its own clock phase (7 ms off the camera's), 30 ms late, distances 1.5 % long,
turns 1 % long, a heading drift of 0.2 deg/s and white noise (0.1 mm, 0.1 mrad a sample), for a camera mounted 0.2 m
ahead of the base's axis (on it for ``spin_on_axis``, as that scenario says; the mount,
exact, goes to ``cubeloc track`` in ``[frames]``).
``cubeloc track`` runs three times per scenario (vision alone; ``--odometry`` as the
bridge while the camera has no pose only, ``as_prior = false``; and also as the motion
prior, held position and relative-motion factor, ``as_prior``, the default), in the frame loop (no thread timing), scored as the scenario bench
scores them.

One robot's wheels are one draw: the same frames then go another way with other wheels
(blank_wall's map after the wall: 3 to 13 mm RMS). So the two runs with odometry are
repeated for ``CUBELOC_BENCH_ODOMETRY_DRAWS`` robots (default 5: draw 0 the wheels above,
the others ``fakes.odometry.drawn_errors``: distances +-2 %, turns +-1.5 %, heading drift
+-0.3 deg/s), and the second table gives the distribution over them."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from bench.common import REPO, markdown_table, renders_root
from bench.scenarios import _render, _score, _track
from cubeloc.fakes.odometry import LEVER_M, mount_of

TITLE = "Wheel odometry in: vision alone and vision + wheel odometry on the same frames"
SCENARIOS = ("spin_in_place", "blank_wall", "spin_on_axis", "passers_by")
# map -> odom (REP 105) and its steps: a lap with the cube out of view for most of it, and
# a blank wall; the spread of [frames] map_odom_spread_s (0: none)
JUMP_SCENARIOS = ("long_lap", "blank_wall")
SPREADS_S = (0.0, 0.5, 1.0)
LEVER_OF = {"spin_on_axis": 0.0}  # the camera's lever where a scenario puts it elsewhere (fakes/scenarios.py)


def _config(path: Path, xyz, quaternion, as_prior: bool) -> None:
    path.write_text(f"[frames.base_from_camera]\nxyz = {xyz}\nquaternion = {quaternion}\n"
                    f"[odometry]\nenabled = true\nas_prior = {str(as_prior).lower()}\n")


def run() -> str:
    from cubeloc.fakes.odometry import drawn_errors, simulate_odometry, write_odometry
    from cubeloc.fakes.trajectories import DEFAULT_SECONDS, make_trajectory
    from cubeloc.positioning.geometry import Transform

    draws = range(max(1, int(os.environ.get("CUBELOC_BENCH_ODOMETRY_DRAWS", "5"))))
    rows, spread_rows = [], []
    with renders_root("odometry", "CUBELOC_BENCH_SCENARIOS") as (root, tmp):
        for name in SCENARIOS:
            sequence = _render(root, name)
            seconds = DEFAULT_SECONDS[name]
            xyz, quaternion = mount_of(make_trajectory(name, seconds)[0].T_world_camera, LEVER_OF.get(name, LEVER_M))
            configs = {}
            for mode, as_prior in (("bridge", False), ("bridge + prior", True)):
                configs[mode] = Path(tmp) / f"{name}-{as_prior}.toml"
                _config(configs[mode], xyz, quaternion, as_prior)
            runs = {("vision", 0): ()}
            for draw in draws:
                odometry = Path(tmp) / f"{name}-{draw}-odometry.jsonl"
                write_odometry(odometry, simulate_odometry(name, seconds, Transform.from_quaternion(xyz, quaternion),
                                                           **drawn_errors(draw)))
                for mode, config in configs.items():
                    runs[mode, draw] = ("--odometry", str(odometry), "--config", str(config))

            def one(key, name=name, sequence=sequence, runs=runs):
                mode, draw = key
                out = Path(tmp) / f"{name}-{mode.replace(' ', '').replace('+', '_')}-{draw}.tum"
                _track(REPO, sequence, out, True, runs[key])
                return _score(sequence, out, True)

            with ThreadPoolExecutor(2) as pool:  # each run a child process of its own
                scores = dict(zip(runs, pool.map(one, runs), strict=True))
            cells = []
            for mode in ("vision", "bridge", "bridge + prior"):
                s = scores[mode, 0]
                cells.append(f"{100 * s.coverage:.1f} %, RMS {s.rmse_m * 1000:.2f} mm, max {s.max_m * 1000:.1f}, "
                             f"inside 3 sigma {100 * s.consistent:.1f} %")
            rows.append([name, *cells])
            for mode in ("bridge", "bridge + prior"):
                each = [scores[mode, draw] for draw in draws]
                rms = np.array([s.rmse_m * 1000 for s in each])
                spread_rows.append([name, mode, f"{np.median(rms):.2f} / {np.percentile(rms, 90):.2f} / {rms.max():.2f}",
                                    f"{max(s.max_m for s in each) * 1000:.1f}",
                                    f"{100 * min(s.coverage for s in each):.1f} %",
                                    f"{100 * min(s.consistent for s in each):.1f} %"])
        jumps = [_jumps(root, Path(tmp), name) for name in JUMP_SCENARIOS]
    table = markdown_table(["scenario", "vision alone: frames with a pose, error",
                            "+ odometry as a bridge only (as_prior = false)", "+ odometry as bridge and motion prior (as_prior, the default)"],
                           rows)
    spread_table = markdown_table(
        ["scenario", "odometry", f"RMS mm over {len(draws)} robots: median / p90 / worst", "max mm, worst",
         "frames with a pose, worst", "inside 3 sigma, worst"], spread_rows)
    jump_table = markdown_table(
        ["scenario", "map -> base_link: largest step beyond the true motion",
         *(f"map -> odom, spread {s:g} s: largest step" if s else "map -> odom: largest step" for s in SPREADS_S)],
        jumps)
    return "\n".join([__doc__.split("\n\n", 1)[1].strip(), "", "Draw 0:", "", table, "",
                      "Over the robots (draws):", "", spread_table, "", JUMPS_TEXT, "", jump_table])


JUMPS_TEXT = """**map -> odom (REP 105).** The same odometry, `cubeloc track --odometry --poses` (as
bridge and prior); per frame with a pose, map -> base_link from the camera's pose, and
map -> odom = map -> base_link after the inverse of the odometry's odom -> base_link at the
frame's stamp (interpolated as the daemon does), raw and spread over a time constant
(`[frames] map_odom_spread_s`). A step is the change from one frame to the next, mm and
deg; for map -> base_link, beyond the truth's own motion over that frame. Each cell: the
largest, and the frame's state and source."""


def _jumps(root: Path, tmp: Path, name: str) -> list[str]:
    """One row of the map -> odom table (JUMPS_TEXT)."""
    import json

    from cubeloc.fakes.odometry import simulate_odometry, write_odometry
    from cubeloc.fakes.trajectories import DEFAULT_SECONDS, make_trajectory
    from cubeloc.positioning.frames import RobotFrames, SpreadCorrection
    from cubeloc.positioning.geometry import Transform
    from cubeloc.positioning.tracking.odometry import OdometryBuffer
    from cubeloc.positioning.trajectory_io import read_tum

    sequence = _render(root, name)
    seconds = DEFAULT_SECONDS[name]
    xyz, quaternion = mount_of(make_trajectory(name, seconds)[0].T_world_camera, LEVER_OF.get(name, LEVER_M))
    mount = Transform.from_quaternion(xyz, quaternion)
    rows = simulate_odometry(name, seconds, mount)
    odometry = tmp / f"{name}-jumps-odometry.jsonl"
    write_odometry(odometry, rows)
    config = tmp / f"{name}-jumps.toml"
    _config(config, xyz, quaternion, True)
    out = tmp / f"{name}-jumps.tum"
    _track(REPO, sequence, out, True, ("--odometry", str(odometry), "--config", str(config)))
    buffer = OdometryBuffer(max_extrapolation_s=1.0)
    for row in rows:
        buffer.add(row["stamp_ns"], row["position"], row["orientation"])
    frames = RobotFrames(mount, Transform.identity())
    truth = {p.stamp_ns: p.T_world_camera for p in read_tum(sequence / "groundtruth.tum")}
    order = {stamp: i for i, stamp in enumerate(sorted(truth))}
    poses = [json.loads(line) for line in out.with_suffix(".jsonl").read_text().splitlines()]
    spreads = [SpreadCorrection(s) for s in SPREADS_S]
    largest = [(0.0, 0.0, "")] * (1 + len(SPREADS_S))
    last = None
    for doc in poses:
        stamp = doc["stamp_ns"]
        T_odom_base = buffer.pose_at(stamp)
        if T_odom_base is None:
            continue
        camera = Transform.from_quaternion(np.array(doc["position"]), np.array(doc["orientation"]))
        base = frames.base_in_map(camera, None)[0]
        true_base = frames.base_in_map(truth[stamp], None)[0]
        values = [spread.update(stamp, base @ T_odom_base.inverse()) for spread in spreads]
        if last is not None and order[stamp] == order[last[0]] + 1:  # consecutive frames
            moved, true_moved = last[1].inverse() @ base, last[2].inverse() @ true_base
            steps = [(1000 * float(np.linalg.norm(moved.translation - true_moved.translation)),
                      float(np.degrees(moved.rotation_angle_to(true_moved))))]
            steps += [(1000 * float(np.linalg.norm(v.translation - w.translation)), float(np.degrees(v.rotation_angle_to(w))))
                      for v, w in zip(values, last[3], strict=True)]
            where = f"{doc['state']}/{doc.get('source', '')}"
            largest = [(max(a[0], s[0]), max(a[1], s[1]), where if s[0] > a[0] else a[2])
                       for a, s in zip(largest, steps, strict=True)]
        last = (stamp, base, true_base, values)
    return [name, *(f"{mm:.1f} mm, {deg:.2f} deg ({where})" for mm, deg, where in largest)]
