"""Windowed bundle adjustment: keyframe poses and landmark positions that minimize the robust sum of squared
reprojection errors (Triggs et al. 2000). The KLT baseline runs it over a sliding window (paper 003 II-C proposes
it against scale drift, holding the first poses of the window) and on its two bootstrap views; the feature
initializer over its initialization window (paper 004 section 3.2). With every pose fixed, FDMO's structure-only
adjustment (4.3) is vo_core/geometry/structure_only.py, which solves each point alone.

Levenberg-Marquardt on the normal equations with the Schur complement of the points (Triggs et al. 2000,
section 6.1; what g2o and Ceres do for bundle adjustment), and the Huber loss by iteratively reweighted
least squares. Each point has at most one observation per keyframe, so the point-pose coupling is a dense
(points x keyframes) table of 6x3 blocks and the reduced camera system is a small dense matrix.

Why not scipy.optimize.least_squares: its trust-region solver with a sparse Jacobian (LSMR inner solves)
stalled on perturbed windows with a robust loss (4.5 px RMS left after 50 evaluations on a window that this
solver brings to the 0.5 px noise floor in a few iterations; see tests/test_geometry_bundle_adjustment.py).

The dense point-pose table grows as keyframes x points; a local adjustment of ORB-SLAM2's kind (tens of keyframes,
thousands of points, each seen by a few of them) builds the reduced camera system from the pairs of observations
that share a point instead (``sparse_schur``): the same equations, in memory and time linear in those pairs.
Observations may carry an information (1 / sigma^2 of the pyramid level they were detected at, ORB-SLAM2's
invSigma2): residuals and the Huber threshold are then in units of sigma.

Poses are world-to-camera transforms updated on the left, T_cam_world <- exp(delta) T_cam_world.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import block_diag

from vo_core.compiled import kernel
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_exp, se3_inverse
from vo_core.geometry.reprojection import (
    huber_cost_and_weights,
    pose_jacobians,
    project_points,
    projection_jacobians,
    sum_by,
)

LAMBDA_INITIAL = 1e-4  # Levenberg-Marquardt damping, relative to the diagonal of the normal equations
LAMBDA_DOWN = 1.0 / 3.0  # after an accepted step
LAMBDA_UP = 4.0  # after a rejected one
MAX_REJECTED_STEPS = 8  # in a row: the minimum is reached (to the solver's precision)
MIN_RELATIVE_DECREASE = 1e-6  # stop when an accepted step lowers the cost by less than this fraction
DIAGONAL_FLOOR = 1e-9


@dataclass
class BundleAdjustmentSettings:
    """The solver's settings (the KLT baseline's window adjustment extends them with its window; the feature
    initializer's geometric adjustment sets its own)."""

    huber_px: float = 2.0  # Huber threshold of the reprojection residuals (px)
    max_iterations: int = 10  # Levenberg-Marquardt iterations (each a solve of the reduced camera system)
    # The reduced camera system from the pairs of observations of each point instead of a dense keyframes x points
    # table: the same step, for windows of many points (the features method's local bundle adjustment).
    sparse_schur: bool = False


@dataclass
class WindowProblem:
    """Keyframe poses, landmark positions and the observations that tie them together."""

    poses_world_cam: np.ndarray  # (F, 4, 4) T_world_cam of each keyframe
    fixed: np.ndarray  # (F,) bool: poses held constant (the oldest ones: gauge and scale)
    points_world: np.ndarray  # (M, 3)
    observation_pose: np.ndarray  # (L,) index into poses; at most one observation per (pose, point)
    observation_point: np.ndarray  # (L,) index into points
    observation_uv: np.ndarray  # (L, 2) measured pixel
    # (L,) 1 / sigma^2 of each observation (its pyramid level's); None: every observation weighs 1 (pixels)
    observation_information: np.ndarray | None = None


@dataclass
class WindowSolution:
    poses_world_cam: np.ndarray
    points_world: np.ndarray
    errors_before: np.ndarray  # (L,) reprojection error of each observation before (px, or sigmas with information)
    errors_after: np.ndarray  # (L,) and after
    iterations: int


class _Window:
    """The reprojection model of a window, evaluated at given poses and points."""

    def __init__(self, camera: PinholeCamera, problem: WindowProblem, sparse_schur: bool = False):
        self.camera = camera
        self.problem = problem
        self.num_poses = len(problem.fixed)
        self.num_points = len(problem.points_world)
        information = problem.observation_information
        self.sqrt_information = None if information is None else np.sqrt(np.asarray(information, float))
        self.by_point = _observations_by_point(problem.observation_point, self.num_points) if sparse_schur else None

    def project(self, T_cam_world: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(camera-frame points (L, 3), residuals (L, 2)) of every observation."""
        problem = self.problem
        R = T_cam_world[problem.observation_pose, :3, :3]
        t = T_cam_world[problem.observation_pose, :3, 3]
        p = np.einsum("nij,nj->ni", R, points[problem.observation_point]) + t
        residuals = project_points(self.camera, p) - problem.observation_uv
        if self.sqrt_information is not None:
            residuals *= self.sqrt_information[:, None]
        return p, residuals

    def jacobians(self, T_cam_world: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """d(residual)/d(pose increment) (L, 2, 6) and d(residual)/d(point) (L, 2, 3)."""
        J_proj = projection_jacobians(self.camera, p)
        d_pose = pose_jacobians(p)
        if self.sqrt_information is not None:
            J_proj = J_proj * self.sqrt_information[:, None, None]
        R = T_cam_world[self.problem.observation_pose, :3, :3]
        return J_proj @ d_pose, J_proj @ R

    def step(
        self, T_cam_world: np.ndarray, p: np.ndarray, residuals: np.ndarray, weights: np.ndarray, damping: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The damped Gauss-Newton step (pose increments (F, 6), point increments (M, 3)) by the Schur
        complement: S dp = b_p - W V^-1 b_l, then dl = V^-1 (b_l - W^T dp)."""
        problem = self.problem
        J_pose, J_point = self.jacobians(T_cam_world, p)
        J_pose[problem.fixed[problem.observation_pose]] = 0.0
        wJp = weights[:, None, None] * J_pose
        wJl = weights[:, None, None] * J_point
        F, M = self.num_poses, self.num_points
        a, j = problem.observation_pose, problem.observation_point

        wJp_T = wJp.transpose(0, 2, 1)
        wJl_T = wJl.transpose(0, 2, 1)
        H_pp = sum_by(a, wJp_T @ J_pose, F)  # (F, 6, 6)
        V = sum_by(j, wJl_T @ J_point, M)  # (M, 3, 3)
        b_p = -sum_by(a, (wJp_T @ residuals[:, :, None])[:, :, 0], F)  # (F, 6)
        b_l = -sum_by(j, (wJl_T @ residuals[:, :, None])[:, :, 0], M)  # (M, 3)

        # Marquardt's damping scales the diagonal; the floor keeps a block regular that no residual reaches.
        H_pp += (damping * np.einsum("fii->fi", H_pp) + DIAGONAL_FLOOR)[:, :, None] * np.eye(6)
        V += (damping * np.einsum("mii->mi", V) + DIAGONAL_FLOOR)[:, :, None] * np.eye(3)
        V_inv = np.linalg.inv(V)
        W_obs = wJp_T @ J_point  # (L, 6, 3): the point-pose block of each observation
        if self.by_point is not None:
            return self._sparse_step(H_pp, b_p, b_l, V_inv, W_obs)
        # W and W V^-1 laid out as (pose, 6) x (point, 3) matrices so that the sums over points become matrix
        # products.
        W_rows = np.zeros((F, 6, M, 3))
        W_rows[a, :, j, :] = W_obs
        Y_rows = np.zeros((F, 6, M, 3))
        Y_rows[a, :, j, :] = W_obs @ V_inv[j]
        W_rows = W_rows.reshape(6 * F, 3 * M)
        Y_rows = Y_rows.reshape(6 * F, 3 * M)
        # einsum rather than a BLAS product: this (6F x 3M) x (3M x 6F) product is small enough that a
        # multithreaded BLAS spends more on waking threads than on work, and stalls on a busy machine
        # (measured: 40 ms per adjustment either way when idle, up to 180 ms with BLAS under load).
        S = block_diag(*H_pp) - np.einsum("ik,jk->ij", Y_rows, W_rows)
        rhs = b_p.reshape(-1) - Y_rows @ b_l.reshape(-1)
        delta_pose = self._free_poses_step(S, rhs)
        W_T_delta = (delta_pose @ W_rows).reshape(M, 3)
        delta_point = (V_inv @ (b_l - W_T_delta)[:, :, None])[:, :, 0]
        delta_pose = delta_pose.reshape(F, 6)
        return delta_pose, delta_point

    def _free_poses_step(self, S: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """S dp = rhs over the free poses' 6 rows each; the fixed poses' increments stay zero ((6F,))."""
        free = np.repeat(~self.problem.fixed, 6)
        delta_pose = np.zeros(len(rhs))
        delta_pose[free] = np.linalg.solve(S[np.ix_(free, free)], rhs[free])
        return delta_pose

    def _sparse_step(self, H_pp, b_p, b_l, V_inv, W_obs) -> tuple[np.ndarray, np.ndarray]:
        """The Schur complement step from the observations: S_ab = H_aa [a = b] - sum over the points j seen by
        both a and b of W_aj V_j^-1 W_bj^T, one 6x6 product per pair of observations of a point."""
        problem = self.problem
        F, M = self.num_poses, self.num_points
        a, j = problem.observation_pose, problem.observation_point
        Y_obs = W_obs @ V_inv[j]  # (L, 6, 3)
        by_point, point_start = self.by_point
        S = block_diag(*H_pp) - _schur_coupling(Y_obs, W_obs, a, by_point, point_start, F)
        rhs = (b_p - sum_by(a, (Y_obs @ b_l[j][:, :, None])[:, :, 0], F)).reshape(-1)
        delta_pose = self._free_poses_step(S, rhs).reshape(F, 6)
        W_T_delta = sum_by(j, (W_obs.transpose(0, 2, 1) @ delta_pose[a][:, :, None])[:, :, 0], M)
        delta_point = (V_inv @ (b_l - W_T_delta)[:, :, None])[:, :, 0]
        return delta_pose, delta_point


def _observations_by_point(point_index: np.ndarray, num_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The observations ordered by point, and where each point's run starts in that order ((M + 1,), CSR-like)."""
    by_point = np.argsort(point_index, kind="stable")
    point_start = np.concatenate([[0], np.cumsum(np.bincount(point_index, minlength=num_points))])
    return by_point, point_start


@kernel
def _schur_coupling(Y_obs, W_obs, pose, by_point, point_start, num_poses):
    """sum_j W_aj V_j^-1 W_bj^T as a (6F, 6F) matrix: for each point, every pair of its observations (a, j),
    (b, j) adds Y_aj W_bj^T at block (a, b). Compiled: a 6x6 product per pair, ~10^5 pairs per adjustment step
    (numpy's batched products and their bincount took 45 ms a step on teddy)."""
    coupling = np.zeros((6 * num_poses, 6 * num_poses))
    for j in range(len(point_start) - 1):
        for first in range(point_start[j], point_start[j + 1]):
            row = 6 * pose[by_point[first]]
            Y = Y_obs[by_point[first]]
            for second in range(point_start[j], point_start[j + 1]):
                column = 6 * pose[by_point[second]]
                W = W_obs[by_point[second]]
                for r in range(6):
                    for c in range(6):
                        coupling[row + r, column + c] += Y[r, 0] * W[c, 0] + Y[r, 1] * W[c, 1] + Y[r, 2] * W[c, 2]
    return coupling


def adjust_window(camera: PinholeCamera, problem: WindowProblem, settings: BundleAdjustmentSettings) -> WindowSolution:
    """Minimize sum rho_Huber(|pi(T_cam_world X) - uv|) over the free poses and all points."""
    window = _Window(camera, problem, sparse_schur=settings.sparse_schur)
    T_cam_world = np.stack([se3_inverse(T) for T in problem.poses_world_cam])
    points = problem.points_world.copy()
    p, residuals = window.project(T_cam_world, points)
    errors_before = np.linalg.norm(residuals, axis=1)
    cost, weights = huber_cost_and_weights(errors_before, settings.huber_px)
    damping = LAMBDA_INITIAL
    rejected = 0
    iterations = 0
    while iterations < settings.max_iterations and rejected < MAX_REJECTED_STEPS:
        iterations += 1
        delta_pose, delta_point = window.step(T_cam_world, p, residuals, weights, damping)
        candidate_T = np.stack([se3_exp(d) @ T for d, T in zip(delta_pose, T_cam_world)])
        candidate_points = points + delta_point
        candidate_p, candidate_residuals = window.project(candidate_T, candidate_points)
        errors = np.linalg.norm(candidate_residuals, axis=1)
        if np.any(~(candidate_p[:, 2] > 0)) or not np.all(np.isfinite(errors)):
            candidate_cost = np.inf  # a point crossed behind a camera: too long a step
        else:
            candidate_cost, candidate_weights = huber_cost_and_weights(errors, settings.huber_px)
        if candidate_cost >= cost:
            damping *= LAMBDA_UP
            rejected += 1
            continue
        decrease = (cost - candidate_cost) / cost
        T_cam_world, points, p, residuals = candidate_T, candidate_points, candidate_p, candidate_residuals
        cost, weights = candidate_cost, candidate_weights
        damping *= LAMBDA_DOWN
        rejected = 0
        if decrease < MIN_RELATIVE_DECREASE:
            break
    poses = np.stack([se3_inverse(T) for T in T_cam_world])
    return WindowSolution(poses, points, errors_before, np.linalg.norm(residuals, axis=1), iterations)
