"""The camera's pose from the detected tags of one target in one image (the paper's Fig. 7).

EPnP on all corners of the visible tags (distortion passed to the solver, so the corners
are undistorted with the calibration), then Levenberg-Marquardt on the pixel residuals.
No RANSAC: decoded ids are trustworthy, and a wrong pose shows in the residuals, which
gate it. Tags seen almost edge-on are weighted by their expected corner noise. A single
tag is ambiguous (two poses explain it almost equally well): no pose unless allowed, and
then only with a previous pose to choose between the two; a plane of several tags (a
board) is posed when its two solutions are told apart. The shared pieces (the result
record, LM, the covariance) are ``corner_pose``.

Pure: arrays in, frozen dataclasses out.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass

import cv2
import numpy as np

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.camera_model import project_pose, solver_pixels
from cubeloc.positioning.corner_pose import (
    TargetPose,
    corners_covariance,
    covariance_from_jacobian,
    make_pose,
    refine_lm,
)
from cubeloc.positioning.detection import TagDetection
from cubeloc.positioning.edge_alignment import EDGES, EdgeOptions
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.target import Target

# Tags whose normals are closer than this lie on one plane (a face) for counting planes.
SAME_PLANE_DEG = 10.0


@dataclass(frozen=True)
class PoseOptions:
    """How much of the target a pose needs, and when residuals reject it.

    The first three mirror ``[positioning]`` of the daemon configuration.
    """

    allow_two_faces: bool = True
    allow_one_face: bool = False  # only with a previous pose to resolve the ambiguity
    max_reproj_rms_px: float = 1.5
    max_one_face_jump_m: float = 0.25  # a one-face pose further than this from the last is refused
    # A tag seen more obliquely than this (normal to line of sight) and whose image is
    # narrower than ``min_oblique_edge_px`` has poor corners: its corners are weighted by
    # their expected uncertainty (``corner_sigma_scale``), and the pose is refused only
    # when its covariance puts the camera position beyond ``max_position_sigma_m``.
    max_tag_angle_deg: float = 70.0
    min_oblique_edge_px: float = 40.0
    max_position_sigma_m: float = 0.01
    # One plane: the corner noise is never taken below plane_noise_floor_px (refined corners
    # on sharp renders are 0.02-0.05 px off; a floor keeps a perfect fit from claiming
    # certainty). IPPE's two solutions, each refined, are one pose when the second lies
    # within the first's 99.73 % ellipsoid (plane_same_pose_chi2: chi-square, 6 degrees of
    # freedom); else the first is chosen when the second fits worse by plane_separation_chi2
    # (chi-square: a likelihood ratio of e^12.5), and the plane is ambiguous when it does not.
    plane_noise_floor_px: float = 0.1
    plane_same_pose_chi2: float = 20.06
    plane_separation_chi2: float = 25.0
    edges: EdgeOptions = EDGES  # the alignment of the pose to every cell edge (edge_alignment.py)


class Refusal(str, enum.Enum):
    """Why there is no pose (the ``status`` word of a FrameResult)."""

    NO_TARGET = "no_target"
    ONE_FACE = "one_face"
    TWO_FACES = "two_faces"  # two faces seen but allow_two_faces is off
    SOLVER = "solver"
    REPROJECTION = "reprojection"
    OBLIQUE = "oblique"  # the second plane is a tag seen almost edge-on: the pose is too uncertain


@dataclass(frozen=True)
class PoseOutcome:
    """A pose, or the reason there is none (``refusal``) with a human ``detail``."""

    pose: TargetPose | None
    refusal: Refusal | None = None
    detail: str = ""
    rejected: TargetPose | None = None  # the pose the residuals refused (REPROJECTION)


def count_planes(target: Target, tag_ids: tuple[int, ...] | list[int]) -> int:
    """Distinct planes among the given tags (tags with parallel normals share one)."""
    normals: list[np.ndarray] = []
    cos_limit = np.cos(np.radians(SAME_PLANE_DEG))
    for tag_id in tag_ids:
        normal = target.tag(tag_id).normal
        if all(float(normal @ other) < cos_limit for other in normals):
            normals.append(normal)
    return len(normals)


def unique_target_detections(detections: list[TagDetection], target: Target) -> list[TagDetection]:
    """The detections of the target's tags, one per id (the surest decode), by id.

    Anything else in view is ignored. A second copy of an id (a reflection, a stray
    print) loses to the surer decode; if it was the wrong one, the residuals gate it.
    """
    best: dict[int, TagDetection] = {}
    for detection in detections:
        if not target.has(detection.tag_id):
            continue
        kept = best.get(detection.tag_id)
        if kept is None or detection.decision_margin > kept.decision_margin:
            best[detection.tag_id] = detection
    return [best[tag_id] for tag_id in sorted(best)]


def _one_face(points_world: np.ndarray, pixels: np.ndarray, calibration: CameraCalibration,
              previous: Transform) -> tuple[np.ndarray, np.ndarray] | None:
    """The IPPE solution of a single plane nearest the previous pose (there are two)."""
    count, rvecs, tvecs, _ = cv2.solvePnPGeneric(points_world, *solver_pixels(pixels, calibration),
                                                 flags=cv2.SOLVEPNP_IPPE)
    if count == 0:
        return None

    def distance(index: int) -> float:
        T = Transform.from_rvec_tvec(rvecs[index], tvecs[index]).inverse()
        return float(np.linalg.norm(T.translation - previous.translation)) + 0.1 * previous.rotation_angle_to(T)

    best = min(range(count), key=distance)
    return np.asarray(rvecs[best], dtype=np.float64).reshape(3), np.asarray(tvecs[best], dtype=np.float64).reshape(3)


def plane_solutions(points_world: np.ndarray, pixels: np.ndarray,
                    calibration: CameraCalibration) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """IPPE's (up to two) poses of coplanar points, each refined by LM: (RMS px, rvec,
    tvec), best first."""
    count, rvecs, tvecs, _ = cv2.solvePnPGeneric(points_world, *solver_pixels(pixels, calibration),
                                                 flags=cv2.SOLVEPNP_IPPE)
    out = []
    for k in range(count):
        rvec, tvec = refine_lm(points_world, pixels, np.asarray(rvecs[k], np.float64).reshape(3),
                             np.asarray(tvecs[k], np.float64).reshape(3), calibration)
        residuals = pixels - project_pose(points_world, rvec, tvec, calibration)
        out.append((float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))), rvec, tvec))
    return sorted(out, key=lambda s: s[0])


def _separated_plane(points_world: np.ndarray, pixels: np.ndarray, calibration: CameraCalibration,
                     options: PoseOptions) -> tuple[np.ndarray, np.ndarray] | None:
    """The pose of one plane when it is not ambiguous, else None.

    IPPE gives two poses of a plane, each refined by LM. They are one pose when the second
    lies within the first's uncertainty (``plane_same_pose_chi2``: most views of a board,
    where both fall into one minimum). Two distinct minima are told apart by their fit:
    the second's sum of squared residuals exceeds the first's by ``plane_separation_chi2``
    times the corner noise squared (the first's residuals per degree of freedom, at least
    ``plane_noise_floor_px``). The decision rests on the noise and the covariance, so it
    holds at any distance, resolution and board size."""
    solutions = plane_solutions(points_world, pixels, calibration)
    if not solutions:
        return None
    rms, rvec, tvec = solutions[0]
    if len(solutions) == 1:
        return rvec, tvec
    other_rms, other_rvec, other_tvec = solutions[1]
    residuals = pixels - project_pose(points_world, rvec, tvec, calibration)
    covariance = corners_covariance(points_world, rvec, tvec, residuals, calibration)
    first = Transform.from_rvec_tvec(rvec, tvec).inverse()
    second = Transform.from_rvec_tvec(other_rvec, other_tvec).inverse()
    turn, _ = cv2.Rodrigues(second.rotation @ first.rotation.T)  # world frame, as the covariance
    difference = np.concatenate([second.translation - first.translation, turn.reshape(3)])
    if float(difference @ np.linalg.pinv(covariance) @ difference) <= options.plane_same_pose_chi2:
        return rvec, tvec
    count = len(pixels)
    noise2 = max(rms**2 * count / max(2 * count - 6, 1), options.plane_noise_floor_px**2)
    if (other_rms**2 - rms**2) * count / noise2 < options.plane_separation_chi2:
        return None
    return rvec, tvec


def quad_width_px(corners: np.ndarray) -> float:
    """The narrow width of a quad (area over its longest edge): how many pixels the tag
    really spans across its foreshortened direction."""
    x, y = corners[:, 0], corners[:, 1]
    area = 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))
    longest = float(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1).max())
    return area / longest if longest > 0 else 0.0


def corner_sigma_scale(pose: TargetPose, detections: list[TagDetection], target: Target,
                       options: PoseOptions) -> dict[int, float]:
    """Per tag of the pose, its corners' expected noise relative to a tag seen face-on:
    1 for most; for a tag seen more than ``max_tag_angle_deg`` from its normal whose image
    is narrower than ``min_oblique_edge_px``, that width over its own (the edges across
    the foreshortened direction are that much shorter, their lines that much less sure)."""
    cos_limit = np.cos(np.radians(options.max_tag_angle_deg))
    camera = pose.T_world_camera.translation
    scale = {}
    for detection in detections:
        if detection.tag_id not in pose.tag_ids:
            continue
        tag = target.tag(detection.tag_id)
        sight = camera - tag.center
        scale[detection.tag_id] = 1.0
        if float(tag.normal @ sight) < cos_limit * float(np.linalg.norm(sight)):  # oblique
            width = quad_width_px(detection.corners)
            if width < options.min_oblique_edge_px:
                scale[detection.tag_id] = options.min_oblique_edge_px / max(width, 1.0)
    return scale


def _agreeing(pose: TargetPose, steep: list[TagDetection], scale: dict[int, float], target: Target,
              calibration: CameraCalibration, options: PoseOptions) -> list[TagDetection]:
    """The steep tags whose corners ``pose`` predicts within 3 times their expected noise
    (the pose's own corner RMS, at least ``plane_noise_floor_px``, times their scale)."""
    noise = max(pose.reproj_rms_px, options.plane_noise_floor_px)
    out = []
    for detection in steep:
        predicted = project_pose(target.tag(detection.tag_id).corners, pose.rvec, pose.tvec, calibration)
        rms = float(np.sqrt(np.mean(np.sum((detection.corners - predicted) ** 2, axis=1))))
        if rms <= 3.0 * scale.get(detection.tag_id, 1.0) * noise:
            out.append(detection)
    return out


def _weighted_refine(pose: TargetPose, observed: np.ndarray, weights: np.ndarray, calibration: CameraCalibration,
                     iterations: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton on the corners ``observed`` (N, 2) whitened by ``weights`` (N,), from the
    pose's (rvec, tvec): (rvec, tvec, whitened Jacobian (2N, 6), whitened residuals (2N,))."""
    w = np.repeat(weights, 2)
    x = np.concatenate([pose.rvec, pose.tvec])
    best = None
    for _ in range(iterations):
        projected, jacobian = project_pose(pose.points_world, x[:3], x[3:], calibration, jacobian=True)
        residuals = (observed - projected).ravel() * w
        cost = float(residuals @ residuals)
        if best is not None and cost >= best[0]:
            break
        best = (cost, x.copy(), jacobian * w[:, None], residuals)
        step, *_ = np.linalg.lstsq(jacobian * w[:, None], residuals, rcond=None)
        if not np.all(np.isfinite(step)):
            break
        x = x + step
        if float(np.abs(step).max()) < 1e-12:
            break
    _, x, jacobian, residuals = best
    return x[:3], x[3:], jacobian, residuals


def _weigh_oblique(pose: TargetPose, scale: dict[int, float], calibration: CameraCalibration,
                   options: PoseOptions) -> PoseOutcome:
    """The pose with each tag's corners weighted by its ``scale`` (``corner_sigma_scale``),
    its covariance from the whitened Jacobian; refused (``OBLIQUE``) when that covariance
    puts the camera position beyond ``options.max_position_sigma_m`` (largest axis)."""
    oblique = sorted(t for t in pose.tag_ids if scale[t] > 1.0)
    weights = np.repeat([1.0 / scale[t] for t in pose.tag_ids], 4)
    observed = pose.residuals_px + project_pose(pose.points_world, pose.rvec, pose.tvec, calibration)
    rvec, tvec, jacobian, whitened = _weighted_refine(pose, observed, weights, calibration)
    if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return PoseOutcome(None, Refusal.SOLVER, "the weighted refinement diverged")
    weighted = make_pose(pose.points_world, observed, rvec, tvec, calibration, pose.planes, pose.tag_ids)
    covariance = covariance_from_jacobian(jacobian, whitened.reshape(-1, 2), rvec, tvec)
    sigma = float(np.sqrt(max(np.linalg.eigvalsh(covariance[:3, :3]).max(), 0.0)))
    if sigma > options.max_position_sigma_m:
        return PoseOutcome(None, Refusal.OBLIQUE,
                           f"tags {oblique} are seen almost edge-on and small: the pose's position sigma "
                           f"{sigma * 1000:.1f} mm exceeds {options.max_position_sigma_m * 1000:.1f} mm")
    return PoseOutcome(dataclasses.replace(weighted, covariance=covariance), None,
                       f"tags {oblique} weighted down: seen obliquely")


def _with_oblique(pose: TargetPose, ours: list[TagDetection], oblique: set[int], scale: dict[int, float],
                  target: Target, calibration: CameraCalibration, options: PoseOptions,
                  previous: Transform | None) -> PoseOutcome:
    """The pose when some of its tags are ``oblique``: weighted (``_weigh_oblique``), and
    where the others span two planes on their own, checked against their pose first."""
    kept = [d for d in ours if d.tag_id not in oblique]
    steeper = None
    if count_planes(target, [d.tag_id for d in kept]) >= 2:
        steeper = _solve(kept, target, calibration, options, previous).pose
    if steeper is not None:
        # A steep tag joins only if the others' pose predicts its corners within its
        # expected noise: a wrong corner there (1 px on a 25 px wide tag) would move the
        # weighted pose by millimetres.
        agreeing = _agreeing(steeper, [d for d in ours if d.tag_id in oblique], scale, target, calibration, options)
        if not agreeing:
            return PoseOutcome(steeper, None, f"tags {sorted(oblique)} left out: their corners disagree")
        if len(agreeing) < len(oblique):
            pose = _solve(kept + agreeing, target, calibration, options, previous).pose or steeper
    weighted = _weigh_oblique(pose, scale, calibration, options)
    if weighted.pose is None and steeper is not None:
        # too uncertain with the steep tags, and the others still span two planes
        return PoseOutcome(steeper, None, f"tags {sorted(oblique)} left out: {weighted.detail}")
    return weighted


def single_plane_candidates(detections: list[TagDetection], target: Target,
                            calibration: CameraCalibration) -> list[Transform]:
    """The (up to two) T_world_camera that explain tags on one plane: where to look for
    the other faces when only one was found."""
    ours = unique_target_detections(detections, target)
    if not ours:
        return []
    tag_ids = tuple(d.tag_id for d in ours)
    pixels = np.concatenate([d.corners for d in ours]).astype(np.float64)
    count, rvecs, tvecs, _ = cv2.solvePnPGeneric(target.corners_of(tag_ids), *solver_pixels(pixels, calibration),
                                                 flags=cv2.SOLVEPNP_IPPE)
    return [Transform.from_rvec_tvec(rvecs[k], tvecs[k]).inverse() for k in range(count)]


def estimate_target_pose(
    detections: list[TagDetection],
    target: Target,
    calibration: CameraCalibration,
    options: PoseOptions | None = None,
    previous: Transform | None = None,
    *,
    with_covariance: bool = True,
) -> PoseOutcome:
    """The camera pose from the detections of ``target``'s tags (others are ignored).

    ``previous`` (T_world_camera of an earlier frame) is used only to choose between the
    two poses of a single face when ``options.allow_one_face`` is set. The returned pose
    carries its 6x6 covariance (computed once, for the pose returned), unless
    ``with_covariance`` is False (a caller that refines the pose further computes its own).
    """
    outcome = _estimate(detections, target, calibration, options, previous)
    if outcome.pose is None or not with_covariance or outcome.pose.covariance is not None:
        return outcome  # a weighted pose (oblique tags) carries its covariance already
    pose = outcome.pose
    covariance = corners_covariance(pose.points_world, pose.rvec, pose.tvec, pose.residuals_px, calibration)
    return dataclasses.replace(outcome, pose=dataclasses.replace(pose, covariance=covariance))


def _estimate(
    detections: list[TagDetection],
    target: Target,
    calibration: CameraCalibration,
    options: PoseOptions | None = None,
    previous: Transform | None = None,
) -> PoseOutcome:
    options = options or PoseOptions()
    ours = unique_target_detections(detections, target)
    if not ours:
        return PoseOutcome(None, Refusal.NO_TARGET, "no tag of the target in view")
    outcome = _solve(ours, target, calibration, options, previous)
    if outcome.pose is not None:
        scale = corner_sigma_scale(outcome.pose, ours, target, options) if outcome.pose.planes >= 2 else {}
        oblique = {t for t, v in scale.items() if v > 1.0}
        if not oblique:
            return outcome
        return _with_oblique(outcome.pose, ours, oblique, scale, target, calibration, options, previous)
    if outcome.refusal is not Refusal.REPROJECTION or len(ours) < 3:
        return outcome
    # One bad quad (a grazing face, a partly hidden tag) should not cost the whole pose:
    # the best pose without one tag, if its residuals pass, with the planes it has left.
    retries = [_solve([d for d in ours if d is not left_out], target, calibration, options, previous)
               for left_out in ours]
    passed = [r for r in retries if r.pose is not None]
    if not passed:
        return outcome
    best = min(passed, key=lambda r: r.pose.reproj_rms_px)
    dropped = sorted(set(d.tag_id for d in ours) - set(best.pose.tag_ids))
    return PoseOutcome(best.pose, None, f"tag {dropped[0]} left out: {outcome.detail}")


def _solve(ours: list[TagDetection], target: Target, calibration: CameraCalibration, options: PoseOptions,
           previous: Transform | None) -> PoseOutcome:
    tag_ids = tuple(d.tag_id for d in ours)
    planes = count_planes(target, tag_ids)
    points_world = target.corners_of(tag_ids)
    pixels = np.concatenate([d.corners for d in ours]).astype(np.float64)

    if planes == 1:
        # One tag alone stays ambiguous: its 4 corners leave 2 degrees of freedom to the
        # residuals, too few to show a biased edge (measured: a face whose quiet zone met a
        # white background, 1.2 px off on one edge, gave a "separated" pose 20 mm off with
        # sigma 2 mm). Several tags on the plane (a board) are checked by each other.
        separated = _separated_plane(points_world, pixels, calibration, options) if len(ours) >= 2 else None
        if separated is not None:
            rvec, tvec = separated
        elif not options.allow_one_face:
            return PoseOutcome(None, Refusal.ONE_FACE,
                               f"only one face in view (tags {list(tag_ids)}): a plane is ambiguous")
        elif previous is None:
            return PoseOutcome(None, Refusal.ONE_FACE, "one face in view and no previous pose to resolve its ambiguity")
        else:
            solution = _one_face(points_world, pixels, calibration, previous)
            if solution is None:
                return PoseOutcome(None, Refusal.SOLVER, "no pose fits the single face")
            rvec, tvec = refine_lm(points_world, pixels, *solution, calibration)
    else:
        if planes == 2 and not options.allow_two_faces:
            return PoseOutcome(None, Refusal.TWO_FACES, "two faces in view and two-face poses are disabled")
        ok, rvec, tvec = cv2.solvePnP(points_world, *solver_pixels(pixels, calibration), flags=cv2.SOLVEPNP_EPNP)
        if not ok or not np.all(np.isfinite(rvec)) or not np.all(np.isfinite(tvec)):
            return PoseOutcome(None, Refusal.SOLVER, "EPnP found no pose")
        rvec, tvec = refine_lm(points_world, pixels, rvec.reshape(3), tvec.reshape(3), calibration)

    if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return PoseOutcome(None, Refusal.SOLVER, "the refinement diverged")
    if np.any(Transform.from_rvec_tvec(rvec, tvec).apply(points_world)[:, 2] <= 0):
        return PoseOutcome(None, Refusal.SOLVER, "the pose puts the target behind the camera")
    pose = make_pose(points_world, pixels, rvec, tvec, calibration, planes, tag_ids)
    if not pose.reproj_rms_px <= options.max_reproj_rms_px:
        return PoseOutcome(
            None, Refusal.REPROJECTION,
            f"reprojection RMS {pose.reproj_rms_px:.2f} px exceeds {options.max_reproj_rms_px} px",
            rejected=pose,
        )
    if planes == 1 and previous is not None:
        jump = float(np.linalg.norm(pose.T_world_camera.translation - previous.translation))
        if jump > options.max_one_face_jump_m:
            return PoseOutcome(None, Refusal.ONE_FACE, f"the one-face pose is {jump:.2f} m from the previous one")
    return PoseOutcome(pose)
