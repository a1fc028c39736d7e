"""GTSAM against our bundle adjustment on the same windows (not part of ``make bench``: it
needs ``pip install gtsam==4.3.0``, which cubeloc does not depend on).

The tracker runs on a rendered sequence (a family member, say) with bundle adjustment in
the frame loop, and every window it solves is kept. Each window is then solved again by
``bundle._solve`` (our Levenberg-Marquardt on the Schur complement, reweighted for Huber)
and by GTSAM's ``LevenbergMarquardtOptimizer`` on the same cost: reprojection errors in
pixels with a Huber loss of ``huber_px``, the target's corners ``target_weight`` times
stiffer and fixed, the keyframes the window holds fixed held exactly. Both are scored on
that one robust cost, so neither is judged by its own stopping rule.

    python -m bench.gtsam_window SEQUENCE [--frames N] [--iterations N]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from bench.common import without_gtsam


def windows(sequence: Path, frames: int | None, most: int = 300) -> list:
    """(problem, options, fx) of the bundle adjustments the tracker ran on ``sequence``."""
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.daemon.replay import track_sequence
    from cubeloc.positioning.tracking import bundle

    kept, original = [], bundle.solve

    def keeping(problem, options, fx, sigma_px=None):
        kept.append((problem, options, fx))
        return original(problem, options, fx, sigma_px)

    bundle.solve = keeping
    try:
        track_sequence(sequence, read_camera_info(sequence / "camera.yaml"), last=frames)
    finally:
        bundle.solve = original
    return kept[:: max(1, len(kept) // most)]


def robust_cost(problem, fx: float, poses_cw, points: np.ndarray, huber: float, target_weight: float
                ) -> tuple[float, float]:
    """(the Huber cost of the window's residuals in pixels, the RMS pixel error of its points)."""
    def residuals(kf, world, xn):
        rotation = np.array([poses_cw[k].rotation for k in kf])
        translation = np.array([poses_cw[k].translation for k in kf])
        q = np.einsum("nij,nj->ni", rotation, world) + translation
        return np.linalg.norm((q[:, :2] / q[:, 2:3] - xn) * fx, axis=1)

    r_obs = residuals(problem.obs_kf, points[problem.obs_pt], problem.obs_xn)
    r_tgt = residuals(problem.tgt_kf, problem.tgt_world, problem.tgt_xn) * target_weight if len(problem.tgt_kf) \
        else np.zeros(0)
    r = np.concatenate([r_obs, r_tgt])
    cost = np.where(r <= huber, 0.5 * r * r, huber * (r - 0.5 * huber)).sum()
    return float(cost), float(np.sqrt(np.mean(r_obs**2)))


def solve_with_gtsam(problem, options, fx: float, iterations: int):
    """The window solved by GTSAM: (camera-from-world poses, points, seconds optimising, seconds in all)."""
    import gtsam
    from gtsam.symbol_shorthand import C, L, X

    from cubeloc.positioning.geometry import Transform

    built = time.perf_counter()
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    calibration = gtsam.Cal3_S2(fx, fx, 0.0, 0.0, 0.0)
    huber = gtsam.noiseModel.mEstimator.Huber.Create(options.huber_px)
    observation = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(2, 1.0))
    corner = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(2, 1.0 / options.target_weight))
    for k, (T_cw, free) in enumerate(zip(problem.T_camera_world, problem.free, strict=True)):
        T_wc = T_cw.inverse()
        pose = gtsam.Pose3(gtsam.Rot3(T_wc.rotation), gtsam.Point3(*T_wc.translation))
        values.insert(X(k), pose)
        if not free:
            graph.add(gtsam.NonlinearEqualityPose3(X(k), pose))
    for p, point in enumerate(problem.points):
        values.insert(L(p), gtsam.Point3(*point))
    for k, p, xn in zip(problem.obs_kf, problem.obs_pt, problem.obs_xn, strict=True):
        graph.add(gtsam.GenericProjectionFactorCal3_S2(gtsam.Point2(*(xn * fx)), observation, X(int(k)), L(int(p)),
                                                       calibration))
    for c, (k, world, xn) in enumerate(zip(problem.tgt_kf, problem.tgt_world, problem.tgt_xn, strict=True)):
        values.insert(C(c), gtsam.Point3(*world))
        graph.add(gtsam.NonlinearEqualityPoint3(C(c), gtsam.Point3(*world)))
        graph.add(gtsam.GenericProjectionFactorCal3_S2(gtsam.Point2(*(xn * fx)), corner, X(int(k)), C(c),
                                                       calibration))
    parameters = gtsam.LevenbergMarquardtParams()
    parameters.setMaxIterations(iterations)
    started = time.perf_counter()
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, parameters).optimize()
    done = time.perf_counter()
    poses = []
    for k in range(len(problem.T_camera_world)):
        pose = result.atPose3(X(k))
        poses.append(Transform(pose.rotation().matrix(), np.asarray(pose.translation())).inverse())
    points = np.array([result.atPoint3(L(p)) for p in range(len(problem.points))]).reshape(-1, 3)
    return poses, points, done - started, done - built


def compare(kept: list, iterations: int) -> str:
    from cubeloc.positioning.tracking import bundle

    rows = []
    for problem, options, fx in kept:  # one after the other, on the same machine state
        ours = bundle._solve(problem, options, fx)
        ours_cw = [T.inverse() for T in ours.T_world_camera]
        theirs_cw, theirs_points, optimising, in_all = solve_with_gtsam(problem, options, fx, iterations)
        cost_ours, rms_ours = robust_cost(problem, fx, ours_cw, ours.points, options.huber_px, options.target_weight)
        cost_theirs, rms_theirs = robust_cost(problem, fx, theirs_cw, theirs_points, options.huber_px,
                                              options.target_weight)
        apart = max((np.linalg.norm(a.inverse().translation - b.inverse().translation)
                     for a, b, free in zip(ours_cw, theirs_cw, problem.free, strict=True) if free), default=0.0)
        rows.append((len(problem.points), len(problem.obs_kf), cost_ours / max(cost_theirs, 1e-12), rms_ours,
                     rms_theirs, ours.seconds, optimising, in_all, apart))
    a = np.array(rows)
    ratio = a[:, 2]
    return "\n".join([
        f"{len(a)} windows (median {np.median(a[:, 0]):.0f} points, {np.median(a[:, 1]):.0f} observations)",
        f"robust cost, ours / GTSAM: median {np.median(ratio):.4f}, 90th percentile {np.percentile(ratio, 90):.4f}, "
        f"worst {ratio.max():.4f}; ours more than 1 % higher in {int((ratio > 1.01).sum())}",
        f"RMS of the points' reprojection errors: ours {np.median(a[:, 3]):.4f} px, GTSAM {np.median(a[:, 4]):.4f} px "
        "(medians)",
        f"free keyframes, ours against GTSAM: median {1000 * np.median(a[:, 8]):.3f} mm, worst "
        f"{1000 * a[:, 8].max():.3f} mm apart",
        f"time per window (median / 90th percentile): ours {1000 * np.median(a[:, 5]):.1f} / "
        f"{1000 * np.percentile(a[:, 5], 90):.1f} ms; GTSAM optimising {1000 * np.median(a[:, 6]):.1f} / "
        f"{1000 * np.percentile(a[:, 6], 90):.1f} ms, with its graph built {1000 * np.median(a[:, 7]):.1f} / "
        f"{1000 * np.percentile(a[:, 7], 90):.1f} ms",
    ])


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequence", type=Path)
    parser.add_argument("--frames", type=int, default=None, help="the first N frames only")
    parser.add_argument("--iterations", type=int, default=100, help="GTSAM's iteration limit (default 100)")
    args = parser.parse_args(argv)
    if without_gtsam("bench.gtsam_window"):
        return 2
    print(compare(windows(args.sequence.resolve(), args.frames), args.iterations))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
