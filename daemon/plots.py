"""``cubeloc track``'s picture of a run (``OUT.png`` beside ``OUT.tum``), with matplotlib.

Left: the trajectory seen from above (the target's frame, x and y in metres), each pose
coloured by its state (target, tracking, relocalised; wheel-odometry bridges as tracking),
the ground truth in grey where the sequence has one, the target at the origin. Right: the
position error against the ground truth over time (mm), or without ground truth the state
over time. Written atomically (cubeloc.atomic).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from cubeloc.atomic import atomic_open
from cubeloc.positioning.trajectory_io import StampedPose

STATE_COLOURS = {"target": "tab:green", "tracking": "tab:blue", "relocalised": "tab:orange"}


def plot_track(path: Path, poses: list[StampedPose], states: list[str], groundtruth: list[StampedPose] | None,
               title: str, errors: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """``poses`` with their ``states`` (same length); ``errors``: (stamps ns, metres) of the
    poses that have a ground-truth pose, from positioning.evaluation."""
    import matplotlib

    matplotlib.use("Agg")  # no display on a robot or in CI
    from matplotlib.figure import Figure

    figure = Figure(figsize=(12, 5.5), dpi=100, layout="constrained")
    top, right = figure.subplots(1, 2, width_ratios=(1, 1.3))
    t0 = min([p.stamp_ns for p in poses] + [p.stamp_ns for p in groundtruth or []] or [0])
    if groundtruth:
        g = np.array([p.T_world_camera.translation for p in groundtruth])
        top.plot(g[:, 0], g[:, 1], color="0.6", linewidth=1.5, label="ground truth")
    xy = np.array([p.T_world_camera.translation[:2] for p in poses]).reshape(-1, 2)
    state_array = np.array(states)
    for state, colour in STATE_COLOURS.items():
        chosen = state_array == state
        if chosen.any():
            top.scatter(xy[chosen, 0], xy[chosen, 1], s=4, color=colour, label=f"{state} ({int(chosen.sum())})")
    top.plot([0.0], [0.0], "ks", markersize=5, label="the target")
    top.set_aspect("equal", adjustable="datalim")
    top.set_xlabel("x (m, target frame)")
    top.set_ylabel("y (m, target frame)")
    top.set_title("trajectory, top view")
    top.grid(True, alpha=0.3)
    top.legend(loc="best", fontsize=8, markerscale=2)
    if errors is not None and len(errors[0]):
        stamps, metres = errors
        seconds = (stamps - t0) / 1e9
        by_stamp = {p.stamp_ns: s for p, s in zip(poses, states, strict=True)}
        for state, colour in STATE_COLOURS.items():
            chosen = np.array([by_stamp.get(int(t)) == state for t in stamps])
            if chosen.any():
                right.scatter(seconds[chosen], metres[chosen] * 1000, s=4, color=colour, label=state)
        right.set_ylabel("position error (mm)")
        right.set_title(f"error against the ground truth: RMS {np.sqrt(np.mean(metres**2)) * 1000:.1f} mm, "
                        f"max {metres.max() * 1000:.1f} mm")
        right.legend(loc="best", fontsize=8, markerscale=2)
    else:
        names = list(STATE_COLOURS)
        seconds = (np.array([p.stamp_ns for p in poses]) - t0) / 1e9
        right.scatter(seconds, [names.index(s) if s in names else -1 for s in states], s=4,
                      c=[STATE_COLOURS.get(s, "black") for s in states])
        right.set_yticks(range(len(names)), names)
        right.set_ylabel("state")
        right.set_title("state of each pose (no ground truth in the sequence)")
    right.set_xlabel("time since the first frame (s)")
    right.grid(True, alpha=0.3)
    figure.suptitle(title)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    with atomic_open(path, "wb") as handle:
        handle.write(buffer.getvalue())
