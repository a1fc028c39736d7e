"""Sliding-window bundle adjustment: Huber-weighted reprojection error over a window of keyframes.

Two solvers (``BundleOptions.solver``), both on the analytic Jacobian (``_jacobian_blocks``):

- ``"schur"``, the default: our Levenberg-Marquardt on the Schur complement
  (``schur_lm``). Each observation touches one pose and one point, so the points are
  eliminated block by block and a step costs a few vectorised NumPy products. Offline it
  is 1.2-4x faster than SciPy's on the same windows; live, in the worker thread, ~20x
  (SciPy's many small calls wait for the frame loop to release the GIL), and there a
  solution that lands frames late costs accuracy.
- ``"scipy"``: SciPy's ``least_squares`` (trf, LSMR on the sparse Jacobian), the former
  solver, kept as the reference the tests compare ours with (docs/tracker.md has the
  comparisons).

GTSAM's Levenberg-Marquardt on the same windows and the same cost reaches the same
solution in several times the time (``python -m bench.gtsam_window``; README,
"Dependencies and why"), so it is not a dependency.

Poses are parametrised as a small update on their starting value (``R = exp(w) R0``,
``t = t0 + dt``, camera-from-world), points as world positions. The target's corners seen
by anchored keyframes are fixed world points: they hold the window in the target frame
(metric, no gauge freedom). Without any anchored keyframe the two oldest keyframes of the
window are held fixed instead (position, orientation and scale gauge).

The problem is a frozen snapshot of the map, so the solve can run in a worker thread
while the frame loop goes on; the result says which map epoch it belongs to. Asked with an
observation's noise, a solution also says how well its window fixes the map's scale
against what holds it (``_scale_var``): the drift a tracking pose claims grows by it
(``hold.Drift``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix
from scipy.spatial.transform import Rotation
from threadpoolctl import ThreadpoolController

from cubeloc.positioning.camera_model import normalised_jacobian
from cubeloc.positioning.geometry import Transform, robust_sigma, skew
from cubeloc.positioning.tracking import schur_lm
from cubeloc.positioning.tracking.floor import Floor, FloorRows, on_the_floor
from cubeloc.positioning.tracking.map import Map
from cubeloc.positioning.tracking.options import BundleOptions, FloorOptions


@dataclass(frozen=True)
class BundleProblem:
    epoch: int
    points_added: int  # the map's ``points_added`` at the snapshot: points added later are not in it
    kf_ids: np.ndarray  # (K,) keyframes taking part
    T_camera_world: tuple[Transform, ...]  # (K,) starting poses
    free: np.ndarray  # (K,) bool: optimised, or held fixed
    point_ids: np.ndarray  # (P,)
    points: np.ndarray  # (P, 3) starting positions
    obs_kf: np.ndarray  # (O,) index into kf_ids
    obs_pt: np.ndarray  # (O,) index into point_ids
    obs_xn: np.ndarray  # (O, 2) observed normalised coordinates
    tgt_kf: np.ndarray  # (C,) index into kf_ids of the target corner observations
    tgt_world: np.ndarray  # (C, 3) fixed world corners
    tgt_xn: np.ndarray  # (C, 2)
    # The floor, when it holds the window (the target does not): points held to its height
    # (index into point_ids), free keyframes held to the camera's, and the older keyframes
    # sharing the window's points, free in height and held where they are otherwise (index
    # into kf_ids)
    floor: Floor | None = None
    floor_pt: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    height_kf: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    older_kf: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def held_by_target(self) -> bool:
        """The target's corners (or a loaded map's points) hold the window."""
        return bool(len(self.tgt_kf))


@dataclass(frozen=True)
class BundleSolution:
    epoch: int
    points_added: int
    kf_ids: np.ndarray
    T_world_camera: tuple[Transform, ...]  # optimised poses of kf_ids (fixed ones unchanged)
    point_ids: np.ndarray
    points: np.ndarray  # (P, 3)
    bad_point_ids: np.ndarray  # points with an observation worse than max_residual_px
    initial_rms_px: float
    final_rms_px: float
    evaluations: int
    seconds: float
    # the variance of the relative scale of the window's points against what holds the
    # window (``_scale_var``), None when not asked for or not observable
    scale_var: float | None = None
    held_by_target: bool = False  # the target's corners hold the window (its scale is the target's)


def build_problem(world_map: Map, options: BundleOptions, recent: int | None = None,
                  floor: Floor | None = None) -> BundleProblem | None:
    """The last ``window_keyframes`` keyframes and their points, the newest
    ``anchored_keyframes`` older anchored keyframes seeing those points (also adjusted, held
    by the target's corners) among the newest ``recent`` keyframes the tracker made (None:
    among all; a loaded map's keyframes always count), and every other keyframe seeing those
    points (held fixed). Keyframes kept beyond ``recent`` (places kept for loop closure,
    ``Map.places``) hold no window by the target (their few long-lived points would tie it
    to the target long after it left), and none at all until a loop has closed. A window
    neither the target nor a loaded map holds is held by the ``floor`` when there is one
    (floor.py): its points near the floor to the floor's height, its keyframes to the
    camera's, and the older keyframes sharing its points adjusted with it in height. None
    when there is nothing to adjust."""
    keyframes = list(world_map.keyframes.values())
    window = keyframes[-options.window_keyframes:]
    if len(window) < 2:
        return None
    point_ids_set: set[int] = set()
    for kf in window:
        point_ids_set.update(int(t) for t in kf.track_ids if int(t) in world_map.points)
    # a loaded map's points, and the places kept followed after a loop closed, are the
    # reference, as the target's corners are: fixed world points (held only by one fixed
    # keyframe's ray each, free ones slid along them and the keyframes after a boot
    # relocalisation with them; the window's scale with them)
    reference = {p for p in point_ids_set if world_map.point_birth.get(p) in world_map.fixed} | \
        (point_ids_set & world_map.place_points)
    point_ids_set -= reference
    if not point_ids_set:
        return None
    older = keyframes[: -options.window_keyframes]
    places = world_map.places(recent) if recent is not None else set()
    extra = [kf for kf in older if kf.anchored and kf.kf_id not in places
             and any(int(t) in point_ids_set for t in kf.track_ids)]
    extra = extra[len(extra) - options.anchored_keyframes:] if options.anchored_keyframes else []
    window = extra + window
    window_ids = {kf.kf_id for kf in window}
    point_ids = np.array(sorted(point_ids_set), dtype=np.int64)
    point_index = {int(p): i for i, p in enumerate(point_ids)}
    # older keyframes that see the window's points join as fixed constraints
    idle = set() if world_map.places_agree else places
    fixed_outside = [
        kf for kf in older if kf.kf_id not in window_ids and kf.kf_id not in idle
        if any(int(t) in point_index for t in kf.track_ids)
    ][-options.window_keyframes:]
    used = fixed_outside + window
    # a loaded map's keyframes (world_map.fixed) are the reference: held, never adjusted
    free = np.array([kf.kf_id in window_ids and kf.kf_id not in world_map.fixed for kf in used])
    if not any(kf.anchored for kf in window) and free.all():
        # no target and no older keyframe: hold the two oldest of the window (gauge)
        free[: min(2, len(used) - 1)] = False
    on_floor = (floor is not None and options.floor.enabled and not reference
                and not any(kf.anchored for kf, f in zip(used, free, strict=True) if f))
    # the older keyframes that move with the window in height (anchored ones stay: the target's)
    older = np.array([k < len(fixed_outside) and on_floor and not kf.anchored and kf.kf_id not in world_map.fixed
                      for k, kf in enumerate(used)], dtype=bool)
    free = free | older
    obs_kf, obs_pt, obs_xn = [], [], []
    tgt_kf, tgt_world, tgt_xn = [], [], []
    for k, kf in enumerate(used):
        for i, t in enumerate(kf.track_ids):
            p = point_index.get(int(t))
            if p is not None:
                obs_kf.append(k)
                obs_pt.append(p)
                obs_xn.append(kf.xn[i])
        if kf.anchored and free[k]:
            tgt_kf.extend([k] * len(kf.target_world))
            tgt_world.append(kf.target_world)
            tgt_xn.append(kf.target_xn)
        if reference and free[k]:
            rows = [i for i, t in enumerate(kf.track_ids) if int(t) in reference]
            if rows:
                tgt_kf.extend([k] * len(rows))
                tgt_world.append(np.array([world_map.points[int(kf.track_ids[i])] for i in rows]))
                tgt_xn.append(kf.xn[rows])
    points = np.array([world_map.points[int(p)] for p in point_ids])
    floor_pt = height_kf = older_kf = np.zeros(0, np.int64)
    if on_floor:
        floor_pt = on_the_floor(points[:, 2], floor, options.floor)
        height_kf, older_kf = np.flatnonzero(free), np.flatnonzero(older)
    return BundleProblem(
        floor=floor if on_floor else None, floor_pt=floor_pt, height_kf=height_kf, older_kf=older_kf,
        epoch=world_map.epoch,
        points_added=world_map.points_added,
        kf_ids=np.array([kf.kf_id for kf in used], dtype=np.int64),
        T_camera_world=tuple(kf.T_world_camera.inverse() for kf in used),
        free=free,
        point_ids=point_ids,
        points=points,
        obs_kf=np.array(obs_kf, dtype=np.int64),
        obs_pt=np.array(obs_pt, dtype=np.int64),
        obs_xn=np.array(obs_xn).reshape(-1, 2),
        tgt_kf=np.array(tgt_kf, dtype=np.int64),
        tgt_world=np.concatenate(tgt_world) if tgt_world else np.zeros((0, 3)),
        tgt_xn=np.concatenate(tgt_xn) if tgt_xn else np.zeros((0, 2)),
    )


# The matrices here are small: OpenBLAS's threads gain nothing on them, and between calls
# they spin, taking a core from the frame loop (live at 10 fps: 160 ms of CPU per frame
# with them, 80 ms without). Made once: it looks up the loaded BLAS libraries.
_BLAS = ThreadpoolController()


def solve(problem: BundleProblem, options: BundleOptions, fx: float, sigma_px: float | None = None
          ) -> BundleSolution:
    """Huber-weighted least squares over the free poses and all points of the problem;
    with ``sigma_px`` (an observation's noise) also the window's scale variance."""
    with _BLAS.limit(limits=1, user_api="blas"):
        return _solve(problem, options, fx, sigma_px)


def _solve(problem: BundleProblem, options: BundleOptions, fx: float, sigma_px: float | None = None
           ) -> BundleSolution:
    started = time.perf_counter()
    model = _Model(problem, fx, options.target_weight, options.floor)
    x = np.zeros(6 * model.n_free + 3 * model.n_points)
    initial = model.residuals(x)
    # Robustness by iteratively reweighted least squares: SciPy's own Huber loss converges
    # slowly from a few pixels off (measured: ~100 evaluations against ~10), so each round
    # solves a plain weighted problem with Huber weights from the previous round's residuals.
    evaluations = 0
    weighted_round = _round_with_scipy if options.solver == "scipy" else _round_with_schur
    for _ in range(options.robust_rounds):
        per_pair = np.linalg.norm(model.residuals(x).reshape(-1, 2), axis=1)
        weights = np.sqrt(np.minimum(1.0, options.huber_px / np.maximum(per_pair, 1e-12)))
        x, used = weighted_round(model, x, weights, options)
        evaluations += used
    n_obs = model.n_obs
    rotations, translations, points = model.unpack(x)
    final = model.residuals(x)
    per_obs = np.linalg.norm(final[: 2 * n_obs].reshape(-1, 2), axis=1)
    depth = np.einsum("nij,nj->ni", rotations[problem.obs_kf], points[problem.obs_pt])[:, 2] + translations[
        problem.obs_kf, 2]
    finite = np.isfinite(per_obs)
    spread = robust_sigma(per_obs[finite], 0.0, times=3.0) if finite.any() else options.max_residual_px
    limit = min(options.max_residual_px, max(options.min_residual_px, spread))
    bad = (per_obs > limit) | (depth <= 0) | ~finite
    poses = tuple(Transform(r, t).inverse() for r, t in zip(rotations, translations, strict=True))
    scale_var = _scale_var(model, x, options, rotations, translations, points, sigma_px) \
        if sigma_px is not None and model.n_free and model.n_points else None
    return BundleSolution(
        epoch=problem.epoch,
        points_added=problem.points_added,
        kf_ids=problem.kf_ids,
        T_world_camera=poses,
        point_ids=problem.point_ids,
        points=points,
        bad_point_ids=np.unique(problem.point_ids[problem.obs_pt[bad]]),
        initial_rms_px=float(np.sqrt(np.mean(initial**2))) if len(initial) else 0.0,
        final_rms_px=float(np.sqrt(np.mean(final**2))) if len(final) else 0.0,
        evaluations=evaluations,
        seconds=time.perf_counter() - started,
        scale_var=scale_var,
        held_by_target=problem.held_by_target,
    )


def _scale_var(model: _Model, x: np.ndarray, options: BundleOptions, rotations: np.ndarray,
               translations: np.ndarray, points: np.ndarray, sigma_px: float) -> float | None:
    """The variance of the window's scale against what holds it (the keyframes held fixed,
    the target's corners): of the mean relative change of its points' distances from the
    newest free keyframe, each point weighed by how well its own observations place it
    (``schur_lm.weighted_mean_variance``), with the observations' noise (``sigma_px``, the
    target's corners ``target_weight`` times less, outliers down-weighted as in the last
    robust round) and everything free adjusting. A depth that only a short baseline measures is as unsure
    here as it is; a turn on the spot, its points held by the keyframes that made them,
    measures no new scale and adds none."""
    p = model.problem
    residuals = model.residuals(x)
    per_pair = np.linalg.norm(residuals.reshape(-1, 2), axis=1)
    weights = np.sqrt(np.minimum(1.0, options.huber_px / np.maximum(per_pair, 1e-12)))
    n = model.n_point_pairs
    obs_w, tgt_w = weights[:n, None, None], weights[n:, None, None]
    j_pose, j_point, j_tgt = model.jacobian_blocks(x)
    blocks = (j_pose * obs_w[: model.n_obs][p.free[p.obs_kf]], j_point * obs_w, j_tgt * tgt_w)
    k = int(np.flatnonzero(p.free)[-1])
    centre = -rotations[k].T @ translations[k]
    rays = points - centre
    distance = np.maximum(np.linalg.norm(rays, axis=1), 1e-9)
    directions = rays / distance[:, None] ** 2  # d(relative distance) / dX
    variance = schur_lm.weighted_mean_variance(residuals * np.repeat(weights, 2), blocks, model.structure,
                                               directions)
    return None if variance is None else variance * sigma_px**2


class _Model:
    """The problem's residuals (pixels) and Jacobian as functions of the update ``x``:
    6 per free pose (rotation vector, translation), then 3 per point.

    Residual pairs, in order: the observations; the floor's pairs on a point alone; the
    target's corners; the floor's pairs on a pose alone (``floor.FloorRows``)."""

    def __init__(self, problem: BundleProblem, fx: float, target_weight: float,
                 floor: FloorOptions | None = None) -> None:
        self.problem, self.fx, self.target_weight = problem, fx, target_weight
        self.n_free = int(problem.free.sum())
        self.n_points = len(problem.point_ids)
        self.n_obs = len(problem.obs_kf)
        self.n_point_pairs = self.n_obs + len(problem.floor_pt)  # the pairs on a point
        self.free_index = -np.ones(len(problem.kf_ids), dtype=np.int64)
        self.free_index[problem.free] = np.arange(self.n_free)
        self.r0 = np.array([t.rotation for t in problem.T_camera_world])  # (K, 3, 3)
        self.t0 = np.array([t.translation for t in problem.T_camera_world])  # (K, 3)
        self.floor = FloorRows(problem, self.free_index, self.r0, self.t0, floor or FloorOptions()) \
            if problem.floor is not None else None

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rotations, translations, points) at ``x``."""
        p, n_free = self.problem, self.n_free
        deltas = x[: 6 * n_free].reshape(n_free, 6)
        rotations, translations = self.r0.copy(), self.t0.copy()
        if n_free:
            rotations[p.free] = Rotation.from_rotvec(deltas[:, :3]).as_matrix() @ self.r0[p.free]
            translations[p.free] = self.t0[p.free] + deltas[:, 3:]
        return rotations, translations, p.points + x[6 * n_free:].reshape(self.n_points, 3)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Observation pairs (pixels), then target-corner pairs (weighted pixels)."""
        p = self.problem
        rotations, translations, points = self.unpack(x)
        pc = np.einsum("nij,nj->ni", rotations[p.obs_kf], points[p.obs_pt]) + translations[p.obs_kf]
        z = np.where(np.abs(pc[:, 2]) < 1e-9, 1e-9, pc[:, 2])
        r_obs = (pc[:, :2] / z[:, None] - p.obs_xn) * self.fx
        tc = np.einsum("nij,nj->ni", rotations[p.tgt_kf], p.tgt_world) + translations[p.tgt_kf]
        zt = np.where(np.abs(tc[:, 2]) < 1e-9, 1e-9, tc[:, 2])
        r_tgt = (tc[:, :2] / zt[:, None] - p.tgt_xn) * self.fx * self.target_weight
        if self.floor is None:
            return np.concatenate([r_obs.ravel(), r_tgt.ravel()])
        on_points, on_poses = self.floor.residuals(x[: 6 * self.n_free].reshape(-1, 6), rotations, translations,
                                                   points)
        return np.concatenate([r_obs.ravel(), on_points.ravel(), r_tgt.ravel(), on_poses.ravel()])

    @cached_property
    def structure(self) -> schur_lm.BlockStructure:
        """Which free pose and point each residual pair depends on (our solver's view)."""
        p = self.problem
        points, poses = (self.floor.points, self.floor.poses) if self.floor is not None else \
            (np.zeros(0, np.int64), np.zeros(0, np.int64))
        return schur_lm.BlockStructure(
            self.n_free, self.n_points, np.concatenate([self.free_index[p.obs_kf], -np.ones(len(points), np.int64)]),
            np.concatenate([p.obs_pt, points]), np.concatenate([self.free_index[p.tgt_kf], poses]))

    @cached_property
    def jacobian_pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns of the Jacobian's entries (SciPy's sparse view)."""
        return _jacobian_pattern(self.structure)

    def jacobian_blocks(self, x: np.ndarray) -> schur_lm.JacobianBlocks:
        p = self.problem
        deltas = x[: 6 * self.n_free].reshape(self.n_free, 6)
        rotations, translations, points = self.unpack(x)
        blocks = _jacobian_blocks(p, deltas, rotations, translations, points, self.fx, self.target_weight)
        if self.floor is None:
            return blocks
        j_pose, j_point, j_tgt = blocks
        on_points, on_poses = self.floor.jacobian(rotations, translations)
        return j_pose, np.concatenate([j_point, on_points]), np.concatenate([j_tgt, on_poses])


def _round_with_schur(model: _Model, x: np.ndarray, weights: np.ndarray, options: BundleOptions
                      ) -> tuple[np.ndarray, int]:
    """One weighted round with our Levenberg-Marquardt (schur_lm): (x, evaluations)."""
    p = model.problem
    n = model.n_point_pairs
    obs_w, tgt_w = weights[:n, None, None], weights[n:, None, None]
    posed = p.free[p.obs_kf]
    row_weights = np.repeat(weights, 2)

    def weighted_blocks(v: np.ndarray) -> schur_lm.JacobianBlocks:
        j_pose, j_point, j_tgt = model.jacobian_blocks(v)
        return j_pose * obs_w[: model.n_obs][posed], j_point * obs_w, j_tgt * tgt_w

    result = schur_lm.levenberg_marquardt(lambda v: model.residuals(v) * row_weights, weighted_blocks,
                                          model.structure, x, options.max_iterations, options.min_damping)
    return result.x, result.evaluations


def _round_with_scipy(model: _Model, x: np.ndarray, weights: np.ndarray, options: BundleOptions
                      ) -> tuple[np.ndarray, int]:
    """One weighted round with SciPy's least_squares (trf, LSMR): (x, evaluations)."""
    rows, cols = model.jacobian_pattern
    row_weights = np.repeat(weights, 2)
    shape = (len(row_weights), len(x))

    def jacobian(v: np.ndarray) -> csr_matrix:
        values = np.concatenate([b.ravel() for b in model.jacobian_blocks(v)])
        return csr_matrix((values * row_weights[rows], (rows, cols)), shape=shape)

    result = least_squares(lambda v: model.residuals(v) * row_weights, x, jac=jacobian, method="trf",
                           tr_solver="lsmr", x_scale=1.0, max_nfev=options.max_iterations)
    return result.x, int(result.nfev)


def _jacobian_pattern(structure: schur_lm.BlockStructure) -> tuple[np.ndarray, np.ndarray]:
    """Row and column of every structurally non-zero Jacobian entry, in the order
    ``_Model.jacobian_blocks`` gives them: per pair on a point, its pose's 6 columns (when
    the pose is free) and its point's 3; per pair on a pose alone, its pose's 6."""
    n_obs, n_tgt = len(structure.obs_point), len(structure.tgt_pose)
    obs_rows = np.arange(2 * n_obs).reshape(n_obs, 2)
    pose_cols = 6 * structure.obs_pose[:, None] + np.arange(6)  # (O, 6)
    point_cols = 6 * structure.n_poses + 3 * structure.obs_point[:, None] + np.arange(3)  # (O, 3)
    has_pose = structure.obs_pose >= 0
    rows = [np.broadcast_to(obs_rows[has_pose][:, :, None], (int(has_pose.sum()), 2, 6)).ravel(),
            np.broadcast_to(obs_rows[:, :, None], (n_obs, 2, 3)).ravel()]
    cols = [np.broadcast_to(pose_cols[has_pose][:, None, :], (int(has_pose.sum()), 2, 6)).ravel(),
            np.broadcast_to(point_cols[:, None, :], (n_obs, 2, 3)).ravel()]
    tgt_rows = 2 * n_obs + np.arange(2 * n_tgt).reshape(n_tgt, 2)
    tgt_cols = 6 * structure.tgt_pose[:, None] + np.arange(6)
    rows.append(np.broadcast_to(tgt_rows[:, :, None], (n_tgt, 2, 6)).ravel())
    cols.append(np.broadcast_to(tgt_cols[:, None, :], (n_tgt, 2, 6)).ravel())
    return np.concatenate(rows), np.concatenate(cols)


def _jacobian_blocks(problem: BundleProblem, deltas: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                     points: np.ndarray, fx: float, target_weight: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The analytic Jacobian's blocks: (O_free, 2, 6) of the observations by free keyframes
    with respect to their pose, (O, 2, 3) of every observation with respect to its point,
    (C, 2, 6) of the target corners with respect to their keyframe's pose."""
    left = np.zeros((len(rotations), 3, 3))
    left[:] = np.eye(3)
    left[problem.free] = _so3_left_jacobian(deltas[:, :3])
    has_pose = problem.free[problem.obs_kf]
    pc = np.einsum("nij,nj->ni", rotations[problem.obs_kf], points[problem.obs_pt]) + translations[problem.obs_kf]
    d_pc = _projection_jacobian(pc, fx)  # (O, 2, 3)
    d_pose = _pose_block(d_pc, pc - translations[problem.obs_kf], left[problem.obs_kf])
    d_point = d_pc @ rotations[problem.obs_kf]  # (O, 2, 3)
    tc = np.einsum("nij,nj->ni", rotations[problem.tgt_kf], problem.tgt_world) + translations[problem.tgt_kf]
    d_tc = _projection_jacobian(tc, fx * target_weight)
    d_tgt = _pose_block(d_tc, tc - translations[problem.tgt_kf], left[problem.tgt_kf])
    return d_pose[has_pose], d_point, d_tgt


def _projection_jacobian(pc: np.ndarray, scale: float) -> np.ndarray:
    """(N, 2, 3): d(scale * (x / z, y / z)) / d(x, y, z), z clamped as the residuals clamp it."""
    return normalised_jacobian(pc, np.where(np.abs(pc[:, 2]) < 1e-9, 1e-9, pc[:, 2]), scale)


def _pose_block(d_pc: np.ndarray, rotated: np.ndarray, left: np.ndarray) -> np.ndarray:
    """(N, 2, 6) for the pose update (R = exp(w) R0, t = t0 + dt): d pc = -[R p]x J_l(w) dw + dt."""
    out = np.empty((len(d_pc), 2, 6))
    out[:, :, :3] = -(d_pc @ skew(rotated) @ left)
    out[:, :, 3:] = d_pc
    return out


def _so3_left_jacobian(w: np.ndarray) -> np.ndarray:
    """(N, 3, 3): exp(w + d) = exp(J_l(w) d) exp(w) to first order in d."""
    theta = np.linalg.norm(w, axis=1)
    k = skew(w)
    small = theta < 1e-6
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0, (t - np.sin(t)) / t**3)
    return np.eye(3) + a[:, None, None] * k + b[:, None, None] * (k @ k)


def apply_solution(world_map: Map, solution: BundleSolution) -> bool:
    """Write a solution into the map unless the map moved since (its epoch changed).
    Keyframes and points culled meanwhile are skipped."""
    if solution.epoch != world_map.epoch:
        return False
    newest, moved = -1, None  # the newest adjusted keyframe and how the adjustment moved it
    for kf_id, pose in zip(solution.kf_ids, solution.T_world_camera, strict=True):
        kf = world_map.keyframes.get(int(kf_id))
        if kf is not None:
            if kf.kf_id > newest:
                newest, moved = kf.kf_id, pose @ kf.T_world_camera.inverse()
            kf.T_world_camera = pose
    if moved is not None:
        _carry_along(world_map, newest, moved, solution.points_added)
    bad = set(int(p) for p in solution.bad_point_ids)
    for point_id, position in zip(solution.point_ids, solution.points, strict=True):
        pid = int(point_id)
        if pid not in world_map.points or world_map.point_serial[pid] > solution.points_added:
            continue  # culled, or dropped and triangulated anew since the snapshot
        if pid in bad or not np.all(np.isfinite(position)):
            world_map.remove_point(pid)
        else:
            world_map.points[pid] = position
    return True


def _carry_along(world_map: Map, newest: int, moved: Transform, points_added: int) -> None:
    """A solution computed in the background lands after more keyframes and points were
    built on the old poses: move those with the newest adjusted keyframe, so the map stays
    consistent (old and new parts otherwise disagree by the whole correction). A point is
    new when it was added after the snapshot, whichever keyframe it was triangulated
    against (one triangulated against an old keyframe is still placed by the new ones)."""
    for kf in world_map.keyframes.values():
        if kf.kf_id > newest and not kf.anchored:
            kf.T_world_camera = moved @ kf.T_world_camera
    for track_id, serial in world_map.point_serial.items():
        if serial > points_added:
            kf = world_map.keyframes.get(world_map.point_birth[track_id])
            if kf is None or not kf.anchored:
                world_map.points[track_id] = moved.apply(world_map.points[track_id][None])[0]
