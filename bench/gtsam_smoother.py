"""GTSAM's iSAM2 as the tracker's whole back end, beside today's tracker on the same frames
(not part of ``make bench``: it needs ``pip install gtsam==4.3.0``, which cubeloc does not
depend on).

The tracker issue asks for a factor-graph back end measured against the hand-written one on
the family. This is the smallest such back end that runs a whole sequence, so that the two
designs can be compared on the same frames before either is rebuilt around the other:

- **Front end, no tracker.** The processor's own KLT front end and target observer, driven
  without a pose: each track's guess is where its last step would take it (constant image
  flow), and fresh corners are found on every frame with fewer than ``refill`` live tracks,
  whatever happened to the pose (today's processor asks for them only with a pose).
- **Keyframes** ``hz`` a second (every frame at 10 fps), and a frame with a trusted target
  pose whenever half that time has passed.
- **Factors.** Each track is a ``SmartProjectionPoseFactorCal3_S2`` (its point eliminated,
  never a variable) from the keyframe at which its rays, turned into the world by the
  estimates, part by ``parallax_deg``; it holds the track's last ``window`` keyframes.
  A trusted target pose (two faces or more, at most ``target_max_m`` unsure) is a prior on
  its keyframe with its covariance (own and systematic share), floored at ``floor_m`` and
  ``floor_rad``. Consecutive keyframes are tied by the last relative motion scaled to the
  step (constant velocity), ``speed_m_s`` and ``turn_rad_s`` unsure per second.
- **Each keyframe's first guess** is PnP on the points its live tracks' smart factors
  triangulate now, taken when within ``gate_m`` and ``gate_deg`` of the constant-velocity
  guess; only the tracks PnP agrees with get a measurement at that keyframe.
- **Output, causal:** each keyframe's estimate and marginal covariance right after its own
  update (what a live system would publish), against the ground truth with no alignment.

    python -m bench.gtsam_smoother SEQUENCE [SEQUENCE ...] [--frames N] [--px 0.5]

Each sequence prints one table row: the smoother over its keyframes, and today's tracker
(``ProcessorOptions.in_frame_loop()``) on the same keyframes' frames.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.common import without_gtsam


@dataclass(frozen=True)
class SmootherOptions:
    hz: float = 10.0  # keyframes a second
    refill: int = 240  # fresh corners on every frame with fewer live tracks than this
    px: float = 0.5  # a track's noise (pixels), each observation independent
    outlier_px: float = 5.0  # a smart factor whose point reprojects this far off is left out
    parallax_deg: float = 1.0  # a track becomes a factor once its rays part by this much
    window: int = 40  # the keyframes a track's factor holds (its newest)
    speed_m_s: float = 0.3  # constant velocity: how far the motion may stray, per second
    turn_rad_s: float = 1.0
    pnp_px: float = 2.0  # PnP's RANSAC threshold
    gate_m: float = 0.3  # PnP's pose taken only this close to the constant-velocity guess
    gate_deg: float = 10.0
    target_max_m: float = 0.010  # a target pose less sure than this is not used
    floor_m: float = 0.001  # the target prior's floor (its rotation and position are so
    floor_rad: float = 0.0005  # correlated that its information is ~1e10 along one direction)


@dataclass(frozen=True)
class Recorded:
    """One frame as the front end and the observer saw it."""

    stamp_ns: int
    ids: np.ndarray  # (N,) live track ids
    xn: np.ndarray  # (N, 2) undistorted normalised coordinates
    target: object | None  # the observer's TargetObservation, None without one


def record(sequence: Path, frames: int | None, options: SmootherOptions) -> tuple[object, list[Recorded | None]]:
    """The calibration and every frame's tracks and target pose (None for an unreadable frame)."""
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.drivers.sequence import read_image, read_sequence_index
    from cubeloc.positioning.camera_model import undistort
    from cubeloc.positioning.observer import image_problem
    from cubeloc.positioning.target import make_cube
    from cubeloc.positioning.tracking.processor import ProcessorOptions, TrackingProcessor

    calibration = read_camera_info(sequence / "camera.yaml")
    processor = TrackingProcessor(make_cube(), calibration, ProcessorOptions.in_frame_loop())
    front_end, previous, recorded = processor.front_end, {}, []
    for i, entry in enumerate(read_sequence_index(sequence)[:frames]):
        image = read_image(entry.path)
        if image_problem(image, calibration) is not None:
            recorded.append(None)
            continue
        guesses = front_end.pixels.astype(np.float64)
        for k, track in enumerate(front_end.ids):
            if int(track) in previous:  # constant image flow
                guesses[k] += guesses[k] - previous[int(track)]
        before = {int(t): p.astype(np.float64) for t, p in zip(front_end.ids, front_end.pixels, strict=True)}
        tracks = front_end.track(image, guesses if len(guesses) else None)
        previous = {int(t): before[int(t)] for t in tracks.ids if int(t) in before}
        target, _, _ = processor.observe_target(image, entry.stamp_ns, i)
        if len(front_end.ids) < options.refill:
            front_end.detect(image, processor.target_outline(target.T_world_camera if target else None))
        tracks = front_end.tracks
        recorded.append(Recorded(entry.stamp_ns, tracks.ids, undistort(tracks.pixels, calibration), target))
    processor.close()
    return calibration, recorded


class Smoother:
    """iSAM2 over keyframes (module docstring). ``add`` takes each frame in turn."""

    def __init__(self, fx: float, options: SmootherOptions, fps: float) -> None:
        import gtsam

        self.gtsam, self.fx, self.options = gtsam, fx, options
        self.every = max(1, int(round(fps / options.hz)))
        self.calibration = gtsam.Cal3_S2(fx, fx, 0.0, 0.0, 0.0)  # pixels about the principal point
        self.noise = gtsam.noiseModel.Isotropic.Sigma(2, options.px)
        self.smart = gtsam.SmartProjectionParams()
        self.smart.setDegeneracyMode(gtsam.DegeneracyMode.ZERO_ON_DEGENERACY)
        # Jacobian factors and QR: with Hessian factors and Cholesky iSAM2 called nearly
        # indeterminate systems singular (condition ~1e10) where Levenberg-Marquardt solved them
        self.smart.setLinearizationMode(gtsam.LinearizationMode.JACOBIAN_SVD)
        self.smart.setDynamicOutlierRejectionThreshold(options.outlier_px)
        self.smart.setLandmarkDistanceThreshold(40.0)
        parameters = gtsam.ISAM2Params()
        parameters.setRelinearizeThreshold(0.01)
        parameters.relinearizeSkip = 1
        parameters.setOptimizationParams(gtsam.ISAM2DoglegParams())
        parameters.setFactorization("QR")
        parameters.cacheLinearizedFactors = False
        parameters.findUnusedFactorSlots = True
        self.isam = gtsam.ISAM2(parameters)
        self.estimate = None  # gtsam.Values after the last update
        self.k = -1
        self.last_frame = -(10**9)
        self.last: tuple | None = None  # (pose, stamp_ns)
        self.velocity: tuple | None = None  # (relative pose, seconds)
        self.observations: dict[int, list] = {}  # live track -> [(key, measurement)]
        self.factors: dict[int, tuple] = {}  # live track with a factor -> (iSAM2 index, factor)

    def _key(self, k: int) -> int:
        return self.gtsam.symbol("x", k)

    def _pose(self, rotation: np.ndarray, translation: np.ndarray):
        return self.gtsam.Pose3(self.gtsam.Rot3(rotation), self.gtsam.Point3(*translation))

    def _trusted(self, target) -> bool:
        if target is None or target.planes < 2 or target.published_covariance is None:
            return False
        return float(np.sqrt(np.max(np.linalg.eigvalsh(target.published_covariance[:3, :3])))) <= \
            self.options.target_max_m

    def _target_noise(self, rotation: np.ndarray, covariance: np.ndarray):
        """ROS order (x y z roll pitch yaw), world frame -> GTSAM's (rotation, translation), camera frame."""
        o = self.options
        c = np.block([[covariance[3:, 3:], covariance[3:, :3]], [covariance[:3, 3:], covariance[:3, :3]]])
        j = np.kron(np.eye(2), rotation.T)
        floor = np.diag([o.floor_rad**2] * 3 + [o.floor_m**2] * 3)
        return self.gtsam.noiseModel.Gaussian.Covariance(j @ c @ j.T + floor)

    def _step(self, seconds: float):
        """The constant-velocity motion over ``seconds``."""
        if self.velocity is None or self.velocity[1] <= 0:
            return self.gtsam.Pose3()
        relative, over = self.velocity
        return self.gtsam.Pose3.Expmap(self.gtsam.Pose3.Logmap(relative) * (seconds / over))

    def _pnp(self, frame: Recorded, guess):
        """(PnP's pose or the guess, the tracks PnP disagrees with)."""
        import cv2

        o, points, pixels, ids = self.options, [], [], []
        for track, xn in zip(frame.ids, frame.xn, strict=True):
            held = self.factors.get(int(track))
            if held is None:
                continue
            triangulated = held[1].point(self.estimate)
            if triangulated.valid():
                points.append(triangulated.get())
                pixels.append(self.fx * xn)
                ids.append(int(track))
        if len(points) < 12:
            return guess, set()
        camera_world = guess.inverse()
        rvec, _ = cv2.Rodrigues(camera_world.rotation().matrix())
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            np.array(points), np.array(pixels), np.diag([self.fx, self.fx, 1.0]), None, rvec,
            camera_world.translation().reshape(3, 1).copy(), useExtrinsicGuess=True, reprojectionError=o.pnp_px,
            iterationsCount=100)
        if not ok or inliers is None or len(inliers) < 12:
            return guess, set()
        pose = self._pose(cv2.Rodrigues(rvec)[0], tvec.ravel()).inverse()
        apart = guess.between(pose)
        if np.linalg.norm(apart.translation()) > o.gate_m or \
                np.degrees(np.linalg.norm(self.gtsam.Rot3.Logmap(apart.rotation()))) > o.gate_deg:
            return guess, set()
        agree = {int(j) for j in inliers.ravel()}
        return pose, {t for j, t in enumerate(ids) if j not in agree}

    def _parted(self, track_observations: list, xn: np.ndarray, guess) -> bool:
        """Do the track's first ray and this one, in the world, part by ``parallax_deg``?"""
        first_key, first = track_observations[0]
        if self.estimate is None or not self.estimate.exists(first_key):
            return False
        a = self.estimate.atPose3(first_key).rotation().matrix() @ np.r_[first / self.fx, 1.0]
        b = guess.rotation().matrix() @ np.r_[xn, 1.0]
        cosine = a @ b / np.linalg.norm(a) / np.linalg.norm(b)
        return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))) >= self.options.parallax_deg

    def add(self, i: int, frame: Recorded) -> tuple | None:
        """Frame ``i``: (rotation, translation, 6x6 covariance in ROS order, world frame) when it
        is a keyframe and the smoother has begun (on the first trusted target pose), else None."""
        gtsam, o = self.gtsam, self.options
        trusted = self._trusted(frame.target)
        if self.k < 0 and not trusted:
            return None
        if i % self.every and not (trusted and i - self.last_frame >= max(1, self.every // 2)):
            return None
        self.k += 1
        key = self._key(self.k)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        seconds = (frame.stamp_ns - self.last[1]) / 1e9 if self.last is not None else 0.0
        if trusted:
            guess = self._pose(frame.target.T_world_camera.rotation, frame.target.T_world_camera.translation)
        else:
            guess = self.last[0].compose(self._step(seconds))
        disagree = set()
        if self.k > 0:
            pnp, disagree = self._pnp(frame, guess)
            guess = guess if trusted else pnp
        values.insert(key, guess)
        if trusted:
            graph.add(gtsam.PriorFactorPose3(key, guess, self._target_noise(frame.target.T_world_camera.rotation,
                                                                            frame.target.published_covariance)))
        if self.k > 0:
            sigmas = np.r_[np.full(3, o.turn_rad_s * seconds), np.full(3, o.speed_m_s * seconds)] + 1e-4
            graph.add(gtsam.BetweenFactorPose3(self._key(self.k - 1), key, self._step(seconds),
                                               gtsam.noiseModel.Diagonal.Sigmas(sigmas)))
        fixed = graph.size()
        remove, added, live = [], [], set()
        for track, xn in zip(frame.ids, frame.xn, strict=True):
            track = int(track)
            live.add(track)
            if track in disagree:
                continue
            seen = self.observations.setdefault(track, [])
            seen.append((key, self.fx * xn))
            del seen[:-o.window]
            if len(seen) < 2 or (track not in self.factors and not self._parted(seen, xn, guess)):
                continue
            factor = gtsam.SmartProjectionPoseFactorCal3_S2(self.noise, self.calibration, self.smart)
            for k, measured in seen:
                factor.add(gtsam.Point2(*measured), k)
            if track in self.factors:  # the track's factor again, with this keyframe's measurement
                remove.append(self.factors[track][0])
            graph.add(factor)
            added.append((track, factor))
        for track in [t for t in self.observations if t not in live]:
            del self.observations[track]
            self.factors.pop(track, None)  # its factor stays in the graph
        update = gtsam.ISAM2UpdateParams()
        update.removeFactorIndices = remove
        result = self.isam.update(graph, values, update)
        for (track, factor), index in zip(added, list(result.getNewFactorsIndices())[fixed:], strict=True):
            self.factors[track] = (index, factor)
        self.isam.update()
        self.estimate = self.isam.calculateEstimate()
        pose = self.estimate.atPose3(key)
        local = self.isam.marginalCovariance(key)  # (rotation, translation), camera frame
        rotation = pose.rotation().matrix()
        j = np.kron(np.eye(2), rotation)
        c = j @ local @ j.T
        covariance = np.block([[c[3:, 3:], c[3:, :3]], [c[:3, 3:], c[:3, :3]]])
        if self.last is not None and seconds > 0:
            self.velocity = (self.last[0].between(pose), seconds)
        self.last, self.last_frame = (pose, frame.stamp_ns), i
        return rotation, np.asarray(pose.translation()), covariance


def tracker_positions(sequence: Path, frames: int | None) -> list[np.ndarray | None]:
    """Today's tracker on the same frames (bundle adjustment in the frame loop): each frame's position."""
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.daemon.replay import track_sequence

    run = track_sequence(sequence, read_camera_info(sequence / "camera.yaml"), last=frames)
    return [None if e is None else e.T_world_camera.translation.copy() for e in run.estimates]


def measure(sequence: Path, frames: int | None, options: SmootherOptions, with_tracker: bool) -> str:
    """One table row: the smoother over its keyframes, today's tracker on the same frames
    (both scored by ``evaluation.score_run``)."""
    from cubeloc.positioning.evaluation import score_run
    from cubeloc.positioning.geometry import Transform
    from cubeloc.positioning.trajectory_io import StampedPose, read_tum

    calibration, recorded = record(sequence, frames, options)
    stamps = np.array([r.stamp_ns for r in recorded if r is not None])
    smoother = Smoother(calibration.fx, options, 1e9 / float(np.median(np.diff(stamps))))
    started, out = time.perf_counter(), []
    for i, frame in enumerate(recorded):
        estimate = None if frame is None else smoother.add(i, frame)
        if estimate is not None:
            out.append((i, *estimate))
    seconds = time.perf_counter() - started
    truth_all = read_tum(sequence / "groundtruth.tum")
    truth = [truth_all[i] for i, *_ in out]
    ours = [(StampedPose(t.stamp_ns, Transform(rotation, position)), covariance)
            for t, (_, rotation, position, covariance) in zip(truth, out, strict=True)]

    def rms(entries: list) -> str:
        kept = [(t, e) for t, e in zip(truth, entries, strict=True) if e is not None]
        if not kept:
            return "-"
        return f"{1000 * score_run([t for t, _ in kept], [e for _, e in kept]).rmse_m:.1f}"

    score = score_run(truth, ours)
    row = [sequence.name, str(len(out)), rms(ours), f"{1000 * score.max_m:.0f}", f"{100 * score.consistent:.1f}",
           str(score.beyond_5_sigma), f"{1000 * seconds / max(len(out), 1):.0f}"]
    if with_tracker:
        positions = tracker_positions(sequence, frames)
        theirs = [None if positions[i] is None else (StampedPose(t.stamp_ns, Transform(np.eye(3), positions[i])), None)
                  for t, (i, *_) in zip(truth, out, strict=True)]
        posed = [entry is not None for entry in theirs]
        row += [f"{100 * score_run(truth, theirs).coverage:.1f}", rms(theirs),
                rms([o if p else None for o, p in zip(ours, posed, strict=True)]),
                rms([None if p else o for o, p in zip(ours, posed, strict=True)])]
    return "| " + " | ".join(row) + " |"


HEADER = ("| sequence | keyframes | smoother RMS mm | max mm | inside 3 sigma % | beyond 5 sigma | ms a keyframe "
          "| tracker posed % | tracker RMS mm | smoother RMS mm where the tracker posed | where it did not |")


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequences", type=Path, nargs="+")
    parser.add_argument("--frames", type=int, default=None, help="the first N frames only")
    parser.add_argument("--px", type=float, default=SmootherOptions.px, help="a track's noise in pixels")
    parser.add_argument("--hz", type=float, default=SmootherOptions.hz, help="keyframes a second")
    parser.add_argument("--no-tracker", action="store_true", help="the smoother alone")
    args = parser.parse_args(argv)
    if without_gtsam("bench.gtsam_smoother"):
        return 2
    from cubeloc.daemon.logs import configure_logging

    configure_logging("warning", "console", stream=sys.stderr)  # the tracker's debug lines are not the bench's
    options = SmootherOptions(px=args.px, hz=args.hz)
    header = HEADER if not args.no_tracker else "|".join(HEADER.split("|")[:8]) + "|"
    print(header)
    print("|" + "---|" * (header.count("|") - 1), flush=True)
    for sequence in args.sequences:
        print(measure(sequence.resolve(), args.frames, options, not args.no_tracker), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
