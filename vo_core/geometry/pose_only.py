"""Motion-only bundle adjustment: the pose of one camera from fixed map points and their observed pixels, with the
outliers among the matches found and set aside (ORB-SLAM2 Optimizer::PoseOptimization; FDMO 4.2.2 refines the
recovered pose "through the traditional feature-based optimization", i.e. this one).

Rounds of Levenberg-Marquardt on SE(3): each round minimizes sum rho(e_l^T W_l e_l) over the observations that
are currently inliers, W_l = Sf^(-2 n_l) the level weight (vo_core/geometry/reprojection.level_information) and
rho Huber's kernel on the normalized error (delta = sqrt(5.991)). After each round every observation, outliers
included, is classified again against the chi-square 95 % bound (5.991, 2 DOF): an outlier is left out of the
next round, and comes back if the better pose explains it. The last round runs without the kernel, its inliers
being clean (ORB-SLAM2 removes the kernel after its third of four rounds).

One difference from ORB-SLAM2: each round starts from the previous round's pose, not from the initial guess again
(ORB-SLAM2 re-reads the frame's unchanged pose); with the outliers gone the next round only has less to correct.

Poses are world-to-camera while solving, updated on the left, T_cam_world <- exp(delta) T_cam_world.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vo_core.compiled import kernel
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_exp_compiled, se3_inverse
from vo_core.geometry.reprojection import CHI2_2D_95, ORB_SCALE_FACTOR, level_information

ROUNDS = 4  # ORB-SLAM2 PoseOptimization: 4 optimizations, inliers and outliers classified after each
ITERATIONS = 10  # ORB-SLAM2 PoseOptimization: its[4] = {10, 10, 10, 10}
MIN_OBSERVATIONS = 3  # ORB-SLAM2: fewer than 3 correspondences, no optimization (6 unknowns, 2 per point)
LAMBDA_INITIAL = 1e-4  # Levenberg-Marquardt damping relative to the diagonal (as the window adjustment)
LAMBDA_DOWN = 1.0 / 3.0
LAMBDA_UP = 4.0
MAX_REJECTED_STEPS = 8  # in a row: the minimum is reached to the solver's precision


class PoseRefinement(NamedTuple):
    T_world_cam: np.ndarray  # (4, 4)
    inlier: np.ndarray  # (N,) bool: e^T W e <= chi2 and in front of the camera at the returned pose
    errors_px: np.ndarray  # (N,) reprojection error at the returned pose (level-0 pixels)


def refine_pose(
    camera: PinholeCamera,
    T_world_cam_guess: np.ndarray,
    points_world: np.ndarray,
    uv: np.ndarray,
    level: np.ndarray,
    *,
    scale_factor: float = ORB_SCALE_FACTOR,
    rounds: int = ROUNDS,
    iterations: int = ITERATIONS,
    chi2: float = CHI2_2D_95,
) -> PoseRefinement:
    """The camera pose that best explains the N observations ``uv`` of ``points_world`` (features detected at
    pyramid ``level``), from ``T_world_cam_guess``, and which observations are inliers."""
    points_world, uv = np.asarray(points_world, float), np.asarray(uv, float)
    information = level_information(level, scale_factor)  # FDMO eq. 6 / ORB-SLAM2 invSigma2
    intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy], float)
    T_cam_world = se3_inverse(np.asarray(T_world_cam_guess, float))
    inlier = np.ones(len(uv), bool)
    huber = float(np.sqrt(chi2))  # ORB-SLAM2 deltaMono = sqrt(5.991)
    if len(uv) >= MIN_OBSERVATIONS:
        for round_index in range(rounds):
            last = round_index == rounds - 1
            T_cam_world = _levenberg_marquardt(intrinsics, points_world[inlier], uv[inlier], information[inlier],
                                               T_cam_world, iterations, np.inf if last else huber)
            _, _, error = _residuals(intrinsics, points_world, uv, information, T_cam_world)
            inlier = error**2 <= chi2
            if inlier.sum() < MIN_OBSERVATIONS:
                break
    _, e, error = _residuals(intrinsics, points_world, uv, information, T_cam_world)
    return PoseRefinement(se3_inverse(T_cam_world), error**2 <= chi2, np.linalg.norm(e, axis=1))


@kernel
def _levenberg_marquardt(intrinsics, points_world, uv, information, T_cam_world, iterations, huber):
    """Minimize the (robust) weighted reprojection cost of the observations over the pose, Huber's kernel at
    ``huber`` (inf: none). Compiled: 40 steps of numpy on a few hundred points cost a recovery ~10 ms."""
    p, e, error = _residuals(intrinsics, points_world, uv, information, T_cam_world)
    cost, weights = _huber(error, information, huber)
    if not np.isfinite(cost):
        return T_cam_world  # a point in use lies behind the guess: nothing sensible to descend
    damping, rejected = LAMBDA_INITIAL, 0
    for _ in range(iterations):
        H, g = _normal_equations(intrinsics, p, e, weights)
        H_damped = H + damping * np.diag(np.diag(H))
        try:
            delta = -np.linalg.solve(H_damped, g)
        except Exception:  # noqa: BLE001 (numba catches no narrower class): e.g. all points on one ray
            break  # degenerate configuration: keep the last pose
        candidate = se3_exp_compiled(delta) @ T_cam_world
        candidate_p, candidate_e, candidate_error = _residuals(intrinsics, points_world, uv, information, candidate)
        candidate_cost, candidate_weights = _huber(candidate_error, information, huber)
        if candidate_cost >= cost:
            damping *= LAMBDA_UP
            rejected += 1
            if rejected >= MAX_REJECTED_STEPS:
                break
            continue
        T_cam_world, p, e, cost, weights = candidate, candidate_p, candidate_e, candidate_cost, candidate_weights
        damping *= LAMBDA_DOWN
        rejected = 0
    return T_cam_world


@kernel
def _residuals(intrinsics, points_world, uv, information, T_cam_world):
    """Camera-frame points (N, 3), residuals pi(T X) - x (N, 2) and normalized errors sqrt(e^T W e) (N,), inf
    behind the camera."""
    fx, fy, cx, cy = intrinsics
    n = len(points_world)
    p, e, error = np.empty((n, 3)), np.empty((n, 2)), np.empty(n)
    for i in range(n):
        for r in range(3):
            p[i, r] = (T_cam_world[r, 0] * points_world[i, 0] + T_cam_world[r, 1] * points_world[i, 1]
                       + T_cam_world[r, 2] * points_world[i, 2] + T_cam_world[r, 3])
        e[i, 0] = fx * p[i, 0] / p[i, 2] + cx - uv[i, 0]
        e[i, 1] = fy * p[i, 1] / p[i, 2] + cy - uv[i, 1]
        error[i] = np.sqrt(information[i] * (e[i, 0] ** 2 + e[i, 1] ** 2))
        if not (p[i, 2] > 0 and np.isfinite(error[i])):
            error[i] = np.inf
    return p, e, error


@kernel
def _huber(error, information, k):
    """Huber's cost sum rho(e) (geometry/reprojection.huber_cost_and_weights; k = inf: squares) and the weights
    W_l x IRLS weight; an infinite cost where an error is."""
    cost, weights = 0.0, np.empty(len(error))
    for i in range(len(error)):
        if not np.isfinite(error[i]):
            return np.inf, weights
        if error[i] <= k:
            cost += error[i] ** 2
            weights[i] = information[i]
        else:
            cost += 2.0 * k * error[i] - k**2
            weights[i] = information[i] * k / error[i]
    return cost, weights


@kernel
def _normal_equations(intrinsics, p, e, weights):
    """H = sum J^T W J and g = sum J^T W e, J = d pi(exp(delta) p) / d delta (2 x 6): the pinhole's derivative
    (geometry/reprojection.projection_jacobians) times [I, -[p]x] (pose_jacobians), multiplied out."""
    fx, fy = intrinsics[0], intrinsics[1]
    H, g, J = np.zeros((6, 6)), np.zeros(6), np.zeros((2, 6))
    for i in range(len(p)):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        a0, a2 = fx / z, -fx * x / (z * z)  # du / d(x, y, z) = (a0, 0, a2)
        b1, b2 = fy / z, -fy * y / (z * z)  # dv / d(x, y, z) = (0, b1, b2)
        J[0, 0], J[0, 1], J[0, 2], J[0, 3], J[0, 4], J[0, 5] = a0, 0.0, a2, a2 * y, a0 * z - a2 * x, -a0 * y
        J[1, 0], J[1, 1], J[1, 2], J[1, 3], J[1, 4], J[1, 5] = 0.0, b1, b2, b2 * y - b1 * z, -b2 * x, b1 * x
        for r in range(6):
            g[r] += weights[i] * (J[0, r] * e[i, 0] + J[1, r] * e[i, 1])
            for c in range(6):
                H[r, c] += weights[i] * (J[0, r] * J[0, c] + J[1, r] * J[1, c])
    return H, g
