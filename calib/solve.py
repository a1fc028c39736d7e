"""Zhang calibration with OpenCV, dropping views whose error is far above the rest.

``solve(views, image_size, options)`` runs ``cv2.calibrateCameraExtended`` (or
``cv2.fisheye.calibrate`` for the ``equidistant`` model, whose parameter standard deviations
are then computed here as OpenCV computes the pinhole's), looks at the per-view RMS
reprojection errors, drops the worst view while it stands far above the
median (a wrong board, a blurred or badly detected view bends every parameter), and
solves again. Dropped views are named in the result.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cubeloc.errors import CubelocError

MIN_VIEWS = 5  # Zhang needs 3; five keep the standard deviations meaningful
PARAMETER_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
FISHEYE_PARAMETER_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
MODELS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
FISHEYE_STARTS = (0.3, 0.45, 0.65)  # a fisheye solve also starts from f = these x the larger side


class CalibrationError(CubelocError):
    """The calibration cannot be done from these views (the message says why and what to do)."""


@dataclass(frozen=True)
class SolveOptions:
    model: str = "plumb_bob"  # or "rational_polynomial", or "equidistant" (fisheye)
    fix_principal_point: bool = False  # keep (cx, cy) at the image centre
    fix_aspect_ratio: bool = False  # fx = fy
    outlier_factor: float = 3.0  # a view is dropped above factor x median RMS ...
    outlier_floor_px: float = 0.3  # ... and above median + this (so tiny errors stay)
    max_dropped_fraction: float = 0.3  # never drop more than this share of the views

    def flags(self) -> int:
        if self.model == "equidistant":
            flags = _fisheye_flag("CALIB_RECOMPUTE_EXTRINSIC") | _fisheye_flag("CALIB_FIX_SKEW")
            if self.fix_principal_point:
                flags |= _fisheye_flag("CALIB_FIX_PRINCIPAL_POINT")
            return flags
        flags = 0
        if self.model == "rational_polynomial":
            flags |= cv2.CALIB_RATIONAL_MODEL
        if self.fix_principal_point:
            flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
        if self.fix_aspect_ratio:
            flags |= cv2.CALIB_FIX_ASPECT_RATIO
        return flags


def parameter_names(model: str) -> tuple[str, ...]:
    """fx fy cx cy and the distortion coefficients' names of ``model``, in its order."""
    return FISHEYE_PARAMETER_NAMES if model == "equidistant" else PARAMETER_NAMES[: 4 + MODELS[model]]


def _fisheye_flag(name: str) -> int:
    """cv2.fisheye's flag ``name``: its own namespace in OpenCV 4, the common one in 5."""
    return int(getattr(cv2.fisheye, name, None) or getattr(cv2, name))


@dataclass(frozen=True)
class View:
    """One view to solve with: the board points it shows."""

    name: str  # image file name, for messages
    image_points: np.ndarray  # (N, 2) float32
    object_points: np.ndarray  # (N, 3) float32


@dataclass(frozen=True)
class ViewFit:
    name: str
    rms_px: float
    points: int
    rvec: np.ndarray  # (3,) board -> camera rotation (Rodrigues)
    tvec: np.ndarray  # (3,) metres
    residuals: np.ndarray  # (N, 2) observed - projected, px
    image_points: np.ndarray  # (N, 2) observed, px


@dataclass(frozen=True)
class DroppedView:
    name: str
    rms_px: float
    reason: str


@dataclass(frozen=True)
class Solution:
    image_size: tuple[int, int]  # (width, height)
    model: str
    camera_matrix: np.ndarray  # (3, 3)
    distortion: np.ndarray  # (5,) or (8,)
    rms_px: float  # over all points of the kept views
    std: dict[str, float]  # one standard deviation of each estimated parameter
    views: tuple[ViewFit, ...]  # the kept views
    dropped: tuple[DroppedView, ...]
    options: SolveOptions

    @property
    def points(self) -> int:
        return sum(v.points for v in self.views)


def _calibrate(views: list[View], image_size: tuple[int, int], options: SolveOptions):
    """(rms, K, D, rvecs, tvecs, std of the intrinsics, -, per-view RMS), as
    ``cv2.calibrateCameraExtended`` returns them, for every model."""
    camera_matrix = np.eye(3)
    distortion = np.zeros(MODELS[options.model])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    try:
        if options.model == "equidistant":
            return _calibrate_fisheye(views, image_size, options, criteria)
        return cv2.calibrateCameraExtended(
            [v.object_points.astype(np.float32) for v in views],
            [v.image_points.astype(np.float32).reshape(-1, 1, 2) for v in views],
            image_size, camera_matrix, distortion, flags=options.flags(), criteria=criteria,
        )
    except cv2.error as exc:
        first = str(exc).strip().splitlines()[-1]
        raise CalibrationError(
            f"OpenCV could not solve the calibration from {len(views)} views ({first}); "
            "add views with the board tilted and in different parts of the image"
        ) from None


def _calibrate_fisheye(views: list[View], image_size: tuple[int, int], options: SolveOptions, criteria):
    objects = [v.object_points.astype(np.float64).reshape(1, -1, 3) for v in views]
    images = [v.image_points.astype(np.float64).reshape(1, -1, 2) for v in views]
    # The solve is not convex, and OpenCV starts from f = (larger side) / pi: the five real
    # TUM-VI views with a grid out to 78 deg off axis ended at 281 px RMS from there and at
    # 0.20 px from 0.45 of the side; a 200 px fisheye at 640x480, at 72 px (tests/
    # test_fisheye.py). So it also starts from each of FISHEYE_STARTS and keeps the best.
    solves = []
    for fraction in (None, *FISHEYE_STARTS):
        flags, guess = options.flags(), np.eye(3)
        if fraction is not None:
            f = fraction * max(image_size)
            flags |= cv2.CALIB_USE_INTRINSIC_GUESS
            guess = np.array([[f, 0.0, (image_size[0] - 1) / 2], [0.0, f, (image_size[1] - 1) / 2], [0.0, 0.0, 1.0]])
        try:
            solves.append(cv2.fisheye.calibrate(objects, images, image_size, guess, np.zeros(4), flags=flags,
                                                criteria=criteria))
        except cv2.error:
            continue
    solves = [s for s in solves if np.isfinite(s[0])]
    if not solves:
        raise cv2.error("cv2.fisheye.calibrate failed from every start")
    rms, k, d, rvecs, tvecs = min(solves, key=lambda s: s[0])
    # The intrinsics' covariance as OpenCV's pinhole calibration gives it: the residual
    # variance times the inverse of J^T J, each view's pose eliminated (Schur complement).
    information = np.zeros((8, 8))
    squares, count = 0.0, 0
    per_view = []
    free = [0, 1] + ([] if options.fix_principal_point else [2, 3]) + [4, 5, 6, 7]
    for obj, img, rvec, tvec in zip(objects, images, rvecs, tvecs, strict=True):
        projected, jacobian = cv2.fisheye.projectPoints(obj, rvec, tvec, k, d)
        residuals = img.reshape(-1, 2) - projected.reshape(-1, 2)
        per_view.append(float(np.sqrt((residuals**2).sum(axis=1).mean())))
        squares, count = squares + float((residuals**2).sum()), count + residuals.size
        intrinsic, pose = jacobian[:, free], jacobian[:, 8:14]  # f (2), c (2), k (4), rvec, tvec, skew
        cross = intrinsic.T @ pose
        information[np.ix_(free, free)] += intrinsic.T @ intrinsic - cross @ np.linalg.pinv(pose.T @ pose) @ cross.T
    dof = max(count - len(free) - 6 * len(views), 1)
    std = np.zeros(8)
    std[free] = np.sqrt(np.clip(np.diag(np.linalg.pinv(information[np.ix_(free, free)])), 0, None) * squares / dof)
    return rms, k, d, rvecs, tvecs, std, None, np.array(per_view)


def solve(views: list[View], image_size: tuple[int, int], options: SolveOptions | None = None) -> Solution:
    """Calibrate from ``views``; drop outlier views one at a time and solve again."""
    options = options or SolveOptions()
    if options.model not in MODELS:
        raise CalibrationError(f"unknown distortion model {options.model!r}; known: {', '.join(MODELS)}")
    if options.model == "equidistant" and options.fix_aspect_ratio:
        raise CalibrationError("the fisheye model solves fx and fy apart: drop --fix-aspect-ratio")
    if len(views) < MIN_VIEWS:
        raise CalibrationError(f"{len(views)} usable views; at least {MIN_VIEWS} are needed (20 or more is better)")
    kept = list(views)
    dropped: list[DroppedView] = []
    max_dropped = int(options.max_dropped_fraction * len(views))
    while True:
        rms, k, d, rvecs, tvecs, std_intrinsics, _, per_view = _calibrate(kept, image_size, options)
        errors = np.asarray(per_view, dtype=np.float64).reshape(-1)
        median = float(np.median(errors))
        threshold = max(options.outlier_factor * median, median + options.outlier_floor_px)
        worst = int(np.argmax(errors))
        if errors[worst] <= threshold or len(dropped) >= max_dropped or len(kept) <= MIN_VIEWS:
            break
        dropped.append(
            DroppedView(
                kept[worst].name, float(errors[worst]),
                f"RMS {errors[worst]:.2f} px against a median of {median:.2f} px",
            )
        )
        del kept[worst]
    if not np.all(np.isfinite(k)) or not np.all(np.isfinite(d)) or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise CalibrationError("the solve diverged; add views with the board tilted and in different parts of the image")
    d = np.asarray(d, dtype=np.float64).reshape(-1)[: MODELS[options.model]]
    std_values = np.asarray(std_intrinsics, dtype=np.float64).reshape(-1)
    names = parameter_names(options.model)
    std = {name: float(std_values[i]) for i, name in enumerate(names)}
    fits = []
    for view, rvec, tvec in zip(kept, rvecs, tvecs, strict=True):
        if options.model == "equidistant":
            projected, _ = cv2.fisheye.projectPoints(view.object_points.astype(np.float64).reshape(-1, 1, 3),
                                                     rvec, tvec, k, d)
        else:
            projected, _ = cv2.projectPoints(view.object_points.astype(np.float64), rvec, tvec, k, d)
        residuals = view.image_points.astype(np.float64) - projected.reshape(-1, 2)
        fits.append(
            ViewFit(
                view.name, float(np.sqrt((residuals**2).sum(axis=1).mean())), len(residuals),
                np.asarray(rvec).reshape(3), np.asarray(tvec).reshape(3), residuals,
                view.image_points.astype(np.float64),
            )
        )
    return Solution(
        image_size=tuple(image_size), model=options.model, camera_matrix=np.asarray(k, dtype=np.float64),
        distortion=d, rms_px=float(rms), std=std, views=tuple(fits), dropped=tuple(dropped), options=options,
    )
