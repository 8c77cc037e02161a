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
that share a point instead (``sparse_schur``): the same equations, in memory and time linear in those pairs, in
one compiled pass (the features method's local adjustment on teddy: 120 -> 47 ms, 2.5x).
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
    adjugate_3x3,
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
        if self.by_point is not None:
            return self._sparse_step(T_cam_world, p, residuals, weights, damping)
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

    def _sparse_step(self, T_cam_world, p, residuals, weights, damping) -> tuple[np.ndarray, np.ndarray]:
        """The same step from the observations, compiled (``_sparse_normal_equations``): S_ab = H_aa [a = b] - the
        sum over the points j seen by both a and b of W_aj V_j^-1 W_bj^T, one 6x6 product per pair of observations
        of a point whose poses are both free (a held pose's rows are dropped from S, and its W blocks are zero)."""
        problem = self.problem
        by_point, point_start = self.by_point
        sqrt_information = (np.ones(len(p)) if self.sqrt_information is None else self.sqrt_information)
        S, rhs, V_inv, W_obs, b_l = _sparse_normal_equations(
            np.ascontiguousarray(T_cam_world[:, :3, :3]), p, residuals, weights, sqrt_information, problem.fixed,
            problem.observation_pose, problem.observation_point, self.num_points, self.camera.intrinsics, damping,
            DIAGONAL_FLOOR, by_point, point_start)
        delta_pose = self._free_poses_step(S, rhs).reshape(self.num_poses, 6)
        delta_point = _back_substituted(delta_pose, V_inv, W_obs, b_l, problem.observation_pose,
                                        problem.observation_point)
        return delta_pose, delta_point


def _observations_by_point(point_index: np.ndarray, num_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The observations ordered by point, and where each point's run starts in that order ((M + 1,), CSR-like)."""
    by_point = np.argsort(point_index, kind="stable")
    point_start = np.concatenate([[0], np.cumsum(np.bincount(point_index, minlength=num_points))])
    return by_point, point_start


@kernel
def _sparse_normal_equations(R, p, residuals, weights, sqrt_information, fixed, pose, point, num_points, intrinsics,
                             damping, floor, by_point, point_start):
    """The reduced camera system of one damped step from the observations: (S (6F, 6F), its right-hand side (6F,),
    V^-1 (M, 3, 3), the point-pose blocks W (L, 6, 3), b_l (M, 3)). Compiled as a whole: numpy's batched products,
    bincounts and inverses took 111 ms a local adjustment of teddy (3 steps, 19,567 observations), these 27."""
    H, b_p, V, b_l, W = _observation_blocks(R, p, residuals, weights, sqrt_information, fixed, pose, point,
                                            num_points, intrinsics)
    # Marquardt's damping scales the diagonal; the floor keeps a block regular that no residual reaches.
    _damp(H, damping, floor)
    _damp(V, damping, floor)
    V_inv = np.empty_like(V)
    for j in range(num_points):
        V_inv[j] *= 1.0 / adjugate_3x3(V[j], V_inv[j])
    coupling, rhs = _point_coupling(W, V_inv, b_l, b_p, fixed, pose, by_point, point_start)
    S = np.zeros((6 * len(H), 6 * len(H)))
    for a in range(len(H)):
        for b in range(a, len(H)):
            for r in range(6):
                for c in range(6):
                    S[6 * a + r, 6 * b + c] = H[a, r, c] - coupling[a, b, r, c] if a == b else -coupling[a, b, r, c]
                    S[6 * b + c, 6 * a + r] = S[6 * a + r, 6 * b + c]
    return S, rhs.reshape(-1), V_inv, W, b_l


@kernel
def _observation_blocks(R, p, residuals, weights, sqrt_information, fixed, pose, point, num_points, intrinsics):
    """The Gauss-Newton blocks summed over the observations (H_pp (F, 6, 6), b_p (F, 6), V (M, 3, 3), b_l (M, 3)) and
    each observation's W = J_pose^T w J_point (L, 6, 3). An observation's Jacobians are the pinhole's
    (``reprojection.projection_jacobians``, times its sqrt information) through [I, -[p]x] for the pose's left
    increment (``reprojection.pose_jacobians``) and through R for the point; a held pose's are zero."""
    num_poses, num_obs = len(R), len(pose)
    fx, fy = intrinsics[0], intrinsics[1]
    H, b_p = np.zeros((num_poses, 6, 6)), np.zeros((num_poses, 6))
    V, b_l = np.zeros((num_points, 3, 3)), np.zeros((num_points, 3))
    W = np.zeros((num_obs, 6, 3))
    J_point, J_pose = np.zeros((2, 3)), np.zeros((2, 6))
    for i in range(num_obs):
        a, j, w = pose[i], point[i], weights[i]
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        inv_z, s = 1.0 / z, sqrt_information[i]
        # The pinhole's Jacobian rows are (gx, 0, hx) and (0, gy, hy).
        gx, gy = fx * inv_z * s, fy * inv_z * s
        hx, hy = -fx * x * inv_z * inv_z * s, -fy * y * inv_z * inv_z * s
        for c in range(3):
            J_point[0, c] = gx * R[a, 0, c] + hx * R[a, 2, c]
            J_point[1, c] = gy * R[a, 1, c] + hy * R[a, 2, c]
        r0, r1 = residuals[i, 0], residuals[i, 1]
        for c in range(3):
            u0, u1 = w * J_point[0, c], w * J_point[1, c]
            b_l[j, c] -= u0 * r0 + u1 * r1
            for d in range(c, 3):
                V[j, c, d] += u0 * J_point[0, d] + u1 * J_point[1, d]
        if fixed[a]:
            continue
        J_pose[0, 0], J_pose[0, 1], J_pose[0, 2] = gx, 0.0, hx
        J_pose[1, 0], J_pose[1, 1], J_pose[1, 2] = 0.0, gy, hy
        J_pose[0, 3], J_pose[0, 4], J_pose[0, 5] = hx * y, gx * z - hx * x, -gx * y
        J_pose[1, 3], J_pose[1, 4], J_pose[1, 5] = -gy * z + hy * y, -hy * x, gy * x
        for c in range(6):
            u0, u1 = w * J_pose[0, c], w * J_pose[1, c]
            b_p[a, c] -= u0 * r0 + u1 * r1
            for d in range(c, 6):
                H[a, c, d] += u0 * J_pose[0, d] + u1 * J_pose[1, d]
            for d in range(3):
                W[i, c, d] = u0 * J_point[0, d] + u1 * J_point[1, d]
    _mirror_upper(H)
    _mirror_upper(V)
    return H, b_p, V, b_l, W


@kernel
def _point_coupling(W, V_inv, b_l, b_p, fixed, pose, by_point, point_start):
    """Point by point, over its observations by free poses (a held pose's rows leave S): Y_aj = W_aj V_j^-1, the
    right-hand side b_p - sum_j Y_aj b_l_j, and each pair's Y_aj W_bj^T summed into the block (a, b), a <= b
    ((F, F, 6, 6); the block (b, a) is its transpose). The point's blocks are gathered first: a local adjustment's
    ~10^5 pairs then read neighbouring memory."""
    num_poses = len(b_p)
    coupling = np.zeros((num_poses, num_poses, 6, 6))
    rhs = b_p.copy()
    most = 0
    for j in range(len(point_start) - 1):
        most = max(most, point_start[j + 1] - point_start[j])
    Y_j, W_j, pose_j = np.empty((most, 6, 3)), np.empty((most, 6, 3)), np.empty(most, np.int64)
    for j in range(len(point_start) - 1):
        n = 0
        for first in range(point_start[j], point_start[j + 1]):
            i = by_point[first]
            a = pose[i]
            if fixed[a]:
                continue
            for c in range(6):
                for d in range(3):
                    W_j[n, c, d] = W[i, c, d]
                    Y_j[n, c, d] = (W[i, c, 0] * V_inv[j, 0, d] + W[i, c, 1] * V_inv[j, 1, d]
                                    + W[i, c, 2] * V_inv[j, 2, d])
                rhs[a, c] -= Y_j[n, c, 0] * b_l[j, 0] + Y_j[n, c, 1] * b_l[j, 1] + Y_j[n, c, 2] * b_l[j, 2]
            pose_j[n] = a
            n += 1
        for x in range(n):
            for y in range(x, n):
                transposed = pose_j[x] > pose_j[y]
                block = coupling[pose_j[y], pose_j[x]] if transposed else coupling[pose_j[x], pose_j[y]]
                for r in range(6):
                    for c in range(6):
                        value = Y_j[x, r, 0] * W_j[y, c, 0] + Y_j[x, r, 1] * W_j[y, c, 1] + Y_j[x, r, 2] * W_j[y, c, 2]
                        if transposed:
                            block[c, r] += value
                        else:
                            block[r, c] += value
    return coupling, rhs


@kernel
def _damp(blocks, damping, floor):
    """Marquardt's damping of each square block's diagonal, plus a floor."""
    for b in range(len(blocks)):
        for c in range(blocks.shape[1]):
            blocks[b, c, c] += damping * blocks[b, c, c] + floor


@kernel
def _mirror_upper(blocks):
    """Each square block's lower triangle from its upper one (the sums above filled only the upper)."""
    for b in range(len(blocks)):
        for c in range(blocks.shape[1]):
            for d in range(c + 1, blocks.shape[1]):
                blocks[b, d, c] = blocks[b, c, d]


@kernel
def _back_substituted(delta_pose, V_inv, W, b_l, pose, point):
    """The points' increments once the poses' are known: dl_j = V_j^-1 (b_l_j - sum_a W_aj^T dp_a)."""
    rhs = b_l.copy()
    for i in range(len(pose)):
        a, j = pose[i], point[i]
        for d in range(3):
            for c in range(6):
                rhs[j, d] -= W[i, c, d] * delta_pose[a, c]
    delta_point = np.empty_like(b_l)
    for j in range(len(b_l)):
        for d in range(3):
            delta_point[j, d] = V_inv[j, d, 0] * rhs[j, 0] + V_inv[j, d, 1] * rhs[j, 1] + V_inv[j, d, 2] * rhs[j, 2]
    return delta_point


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
