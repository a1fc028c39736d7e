"""Levenberg-Marquardt for bundle adjustment, solved by eliminating the points (Schur complement).

Each residual pair (one image observation) depends on at most one pose (6 parameters) and
one point (3); a target-corner pair depends on one pose only. The normal equations then
have a block-diagonal point part, so the points are eliminated exactly, 3 x 3 block by
block, leaving a dense system of 6 x (free poses) unknowns: ~60 for our windows, against
the ~1000 points. One step costs a few vectorised NumPy products, where SciPy's
``least_squares`` ran an iterative LSMR in Python on the whole sparse Jacobian
(docs/tracker.md has the timings).

The damping update follows Nielsen (Madsen, Nielsen & Tingleff, "Methods for non-linear
least squares problems", 2004, section 3.2). The damping is Levenberg's (``damping * I``,
not Marquardt's diagonal of J^T J) and has a floor, ``min_damping`` (pixels^2 per
(metre or radian)^2): the directions no observation constrains (the scale of points seen
from one camera centre) are held by it instead of taking the solver's arbitrary step.

The same blocks, undamped, give the variance of a function of the points at the solution
(``weighted_mean_variance``: the window's scale).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.linalg import block_diag
from scipy.sparse import csr_matrix


@dataclass(frozen=True)
class BlockStructure:
    """Which pose and point each residual pair depends on. Residuals are laid out as
    ``2 * n_obs`` observation rows, then ``2 * n_tgt`` pose-only rows."""

    n_poses: int  # free poses (6 parameters each), first in the parameter vector
    n_points: int  # points (3 parameters each), after the poses
    obs_pose: np.ndarray  # (O,) free-pose index of each observation, -1 when its pose is fixed
    obs_point: np.ndarray  # (O,) point index of each observation
    tgt_pose: np.ndarray  # (C,) free-pose index of each pose-only pair


# The Jacobian as blocks: (O_free, 2, 6) of the observations whose pose is free, with
# respect to it; (O, 2, 3) of every observation with respect to its point; (C, 2, 6) of
# the pose-only pairs.
JacobianBlocks = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class LmResult:
    x: np.ndarray
    cost: float  # 0.5 * sum of squared residuals at x
    evaluations: int  # residual evaluations, rejected steps included


def levenberg_marquardt(residuals: Callable[[np.ndarray], np.ndarray],
                        jacobian: Callable[[np.ndarray], JacobianBlocks], structure: BlockStructure,
                        x0: np.ndarray, max_evaluations: int, min_damping: float,
                        relative_tolerance: float = 1e-8) -> LmResult:
    """Minimise 0.5 |residuals(x)|^2 from ``x0``, with at most ``max_evaluations``
    residual evaluations after the first; stops early when a step lowers the cost by less
    than ``relative_tolerance`` of it. The damping (added to J^T J as ``damping * I``)
    starts at ``min_damping`` or 1, whichever is more, and never goes below ``min_damping``."""
    normal = _NormalEquations(structure)
    x = np.asarray(x0, dtype=np.float64).copy()
    r = residuals(x)
    cost = 0.5 * float(r @ r)
    damping, growth = max(min_damping, 1.0), 2.0  # 1 px^2 per unit: next to Gauss-Newton
    evaluations = 0
    built = False
    while evaluations < max_evaluations and cost > 0.0:
        if not built:
            normal.build(jacobian(x), r)
            built = True
        step = normal.solve(damping)
        if step is None:  # singular even with damping: damp harder
            damping, growth = damping * growth, growth * 2.0
            evaluations += 1
            continue
        candidate = x + step
        r_new = residuals(candidate)
        evaluations += 1
        cost_new = 0.5 * float(r_new @ r_new)
        predicted = normal.predicted_decrease(step, damping)
        if np.isfinite(cost_new) and cost_new < cost and predicted > 0:
            gain = (cost - cost_new) / predicted
            decrease = cost - cost_new
            x, r, cost, built = candidate, r_new, cost_new, False
            damping = max(min_damping, damping * max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3))
            growth = 2.0
            if decrease < relative_tolerance * cost:
                break
        else:
            damping, growth = damping * growth, growth * 2.0
    return LmResult(x, cost, evaluations)


def weighted_mean_variance(residuals: np.ndarray, blocks: JacobianBlocks, structure: BlockStructure,
                           directions: np.ndarray) -> float | None:
    """The variance, for unit residual noise, of the mean of the points' changes along
    ``directions`` ((P, 3) rows g_j: the change g_j . dX_j of point j), each point weighed
    by how well its own observations fix that change (inversely to g_j^T V_j^-1 g_j, its
    variance with the poses held): a point a single short baseline places counts for little,
    as it does in a pose measured on all of them. The variance is the whole of it, the
    poses free: from the inverse of J^T J by blocks, w^T V^-1 w + z^T S^-1 z with z = W V^-1 w
    and S the reduced camera system. None when the system is singular."""
    normal = _NormalEquations(structure)
    normal.build(blocks, residuals)
    return normal.weighted_mean_variance(np.asarray(directions, np.float64).reshape(-1, 3))


class _NormalEquations:
    """J^T J and J^T r in blocks: U (poses), V (points, 3 x 3 each), W (pose-point)."""

    def __init__(self, structure: BlockStructure) -> None:
        self.s = structure
        has_pose = structure.obs_pose >= 0
        self._has_pose = has_pose
        n_obs = len(structure.obs_point)
        # sum over observations as sparse products: one row per pose (point), one column per observation
        self._sum_pose = _indicator(structure.obs_pose[has_pose], structure.n_poses)
        self._sum_point = _indicator(structure.obs_point, structure.n_points)
        self._sum_tgt = _indicator(structure.tgt_pose, structure.n_poses)
        self._n_obs = n_obs

    def build(self, blocks: JacobianBlocks, r: np.ndarray) -> None:
        s = self.s
        j_pose, j_point, j_tgt = blocks
        n_obs = self._n_obs
        r_obs = r[: 2 * n_obs].reshape(n_obs, 2)
        r_tgt = r[2 * n_obs:].reshape(-1, 2)
        r_obs_posed = r_obs[self._has_pose]
        u = self._sum_pose @ _gram(j_pose, j_pose).reshape(-1, 36) + self._sum_tgt @ _gram(j_tgt, j_tgt).reshape(-1, 36)
        self.u = np.asarray(u).reshape(s.n_poses, 6, 6)
        self.v = np.asarray(self._sum_point @ _gram(j_point, j_point).reshape(-1, 9)
                            ).reshape(s.n_points, 3, 3)
        g_pose = (self._sum_pose @ _gram(j_pose, r_obs_posed[:, :, None])[:, :, 0]
                  + self._sum_tgt @ _gram(j_tgt, r_tgt[:, :, None])[:, :, 0])
        self.g_pose = np.asarray(g_pose).reshape(s.n_poses, 6)
        self.g_point = np.asarray(self._sum_point @ _gram(j_point, r_obs[:, :, None])[:, :, 0]).reshape(s.n_points, 3)
        # W as a dense (6 n_poses, n_points, 3) array: small (n_poses is a window's worth)
        w_blocks = _gram(j_pose, j_point[self._has_pose])  # (O_free, 6, 3)
        w = np.zeros((s.n_poses, 6, s.n_points, 3))
        np.add.at(w, (s.obs_pose[self._has_pose], slice(None), s.obs_point[self._has_pose]), w_blocks)
        self.w = w.reshape(6 * s.n_poses, 3 * s.n_points)

    def solve(self, damping: float) -> np.ndarray | None:
        """The damped Gauss-Newton step (poses first, then points); None when singular."""
        s = self.s
        u = self.u + damping * np.eye(6)
        v = self.v + damping * np.eye(3)
        try:
            v_inv = np.linalg.inv(v)
        except np.linalg.LinAlgError:
            return None
        g_point = self.g_point
        if s.n_poses:
            y, schur = self._eliminate(u, v_inv)
            rhs = -self.g_pose.ravel() + y @ g_point.ravel()
            try:
                d_pose = np.linalg.solve(schur, rhs)
            except np.linalg.LinAlgError:
                return None
            back = (self.w.T @ d_pose).reshape(s.n_points, 3)
        else:
            d_pose = np.zeros(0)
            back = np.zeros((s.n_points, 3))
        d_point = -(v_inv @ (g_point + back)[:, :, None])[:, :, 0]
        step = np.concatenate([d_pose, d_point.ravel()])
        return step if np.all(np.isfinite(step)) else None

    def _eliminate(self, u: np.ndarray, v_inv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The points eliminated: (W V^-1, the reduced camera system U - W V^-1 W^T) for the
        pose blocks ``u`` and the inverted point blocks ``v_inv``."""
        s = self.s
        y = (self.w.reshape(-1, s.n_points, 3).transpose(1, 0, 2) @ v_inv).transpose(1, 0, 2)
        y = y.reshape(6 * s.n_poses, -1)
        return y, block_diag(*u) - y @ self.w.T

    def weighted_mean_variance(self, directions: np.ndarray) -> float | None:
        """See ``weighted_mean_variance``. A point no observation places (one ray) is
        eliminated with a vanishing prior on its position: it weighs nothing."""
        s = self.s
        scale = max(float(np.max(np.abs(self.v))) if self.v.size else 1.0, 1.0)
        try:
            v_inv = np.linalg.inv(self.v + 1e-12 * scale * np.eye(3))
        except np.linalg.LinAlgError:
            return None
        own = np.einsum("pi,pij,pj->p", directions, v_inv, directions)
        weights = 1.0 / np.maximum(own, 1e-300)
        w = directions * (weights / np.sum(weights))[:, None]
        v_w = (v_inv @ w[:, :, None])[:, :, 0]  # V^-1 w, (P, 3)
        variance = float(np.sum(w * v_w))
        if s.n_poses:
            _, schur = self._eliminate(self.u, v_inv)
            z = self.w @ v_w.ravel()
            try:
                variance += float(z @ np.linalg.solve(schur, z))
            except np.linalg.LinAlgError:
                return None
        return variance if np.isfinite(variance) and variance > 0 else None

    def predicted_decrease(self, step: np.ndarray, damping: float) -> float:
        """L(0) - L(step) of the linear model: 0.5 step . (damping step - g)."""
        gradient = np.concatenate([self.g_pose.ravel(), self.g_point.ravel()])
        return 0.5 * float(step @ (damping * step - gradient))


def _gram(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per row n: a[n]^T b[n], for (N, k, i) and (N, k, j) with small k (2 here): as a sum
    of k broadcast outer products, several times faster than batched matmul or einsum."""
    out = a[:, 0, :, None] * b[:, 0, None, :]
    for row in range(1, a.shape[1]):
        out += a[:, row, :, None] * b[:, row, None, :]
    return out


def _indicator(index: np.ndarray, n_rows: int) -> csr_matrix:
    """(n_rows, len(index)) with a one in (index[k], k): ``M @ values`` sums values by index."""
    return csr_matrix((np.ones(len(index)), (index, np.arange(len(index)))), shape=(n_rows, len(index)))

