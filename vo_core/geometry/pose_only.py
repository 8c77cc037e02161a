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

from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_exp, se3_inverse, transform_points
from vo_core.geometry.reprojection import (
    CHI2_2D_95,
    ORB_SCALE_FACTOR,
    huber_cost_and_weights,
    level_information,
    pose_jacobians,
    project_points,
    projection_jacobians,
)

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


class _Matches:
    """Map points, their observed pixels and level weights."""

    def __init__(self, camera: PinholeCamera, points_world, uv, level, scale_factor: float):
        self.camera = camera
        self.points_world = np.asarray(points_world, float)
        self.uv = np.asarray(uv, float)
        self.information = level_information(level, scale_factor)  # FDMO eq. 6 / ORB-SLAM2 invSigma2

    def residuals(self, T_cam_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(camera-frame points (N, 3), residuals pi(T X) - x (N, 2))."""
        p = transform_points(T_cam_world, self.points_world)
        return p, project_points(self.camera, p) - self.uv

    def normalized_errors(self, p: np.ndarray, e: np.ndarray) -> np.ndarray:
        """sqrt(e^T W e) (N,): the error in units of its level's sigma; inf behind the camera."""
        error = np.sqrt(self.information * np.sum(e**2, axis=1))
        return np.where((p[:, 2] > 0) & np.isfinite(error), error, np.inf)


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
    matches = _Matches(camera, points_world, uv, level, scale_factor)
    T_cam_world = se3_inverse(np.asarray(T_world_cam_guess, float))
    inlier = np.ones(len(matches.uv), bool)
    huber = float(np.sqrt(chi2))  # ORB-SLAM2 deltaMono = sqrt(5.991)
    if len(matches.uv) >= MIN_OBSERVATIONS:
        for round_index in range(rounds):
            last = round_index == rounds - 1
            T_cam_world = _levenberg_marquardt(matches, T_cam_world, inlier, iterations, None if last else huber)
            p, e = matches.residuals(T_cam_world)
            inlier = matches.normalized_errors(p, e) ** 2 <= chi2
            if inlier.sum() < MIN_OBSERVATIONS:
                break
    p, e = matches.residuals(T_cam_world)
    inlier = matches.normalized_errors(p, e) ** 2 <= chi2
    return PoseRefinement(se3_inverse(T_cam_world), inlier, np.linalg.norm(e, axis=1))


def _cost_and_weights(matches: _Matches, p, e, active, huber: float | None) -> tuple[float, np.ndarray]:
    """The (robust) cost of the active observations and their weights W_l x IRLS weight (N,)."""
    error = matches.normalized_errors(p, e)[active]
    if not np.all(np.isfinite(error)):
        return np.inf, np.zeros(len(e))
    if huber is None:
        cost, robust = float(np.sum(error**2)), np.ones(len(error))
    else:
        cost, robust = huber_cost_and_weights(error, huber)
    weights = np.zeros(len(e))
    weights[active] = matches.information[active] * robust
    return cost, weights


def _levenberg_marquardt(
    matches: _Matches, T_cam_world: np.ndarray, active: np.ndarray, iterations: int, huber: float | None
) -> np.ndarray:
    """Minimize the (robust) weighted reprojection cost of the ``active`` observations over the pose."""
    p, e = matches.residuals(T_cam_world)
    cost, weights = _cost_and_weights(matches, p, e, active, huber)
    if not np.isfinite(cost):
        return T_cam_world  # a point in use lies behind the guess: nothing sensible to descend
    damping, rejected = LAMBDA_INITIAL, 0
    for _ in range(iterations):
        J = projection_jacobians(matches.camera, p[active]) @ pose_jacobians(p[active])  # (n, 2, 6)
        JtW = J.transpose(0, 2, 1) * weights[active][:, None, None]
        H = np.einsum("nij,njk->ik", JtW, J)
        g = np.einsum("nij,nj->i", JtW, e[active])
        H_damped = H + damping * np.diag(np.diag(H))
        try:
            delta = -np.linalg.solve(H_damped, g)
        except np.linalg.LinAlgError:
            break  # degenerate configuration (e.g. all points on one ray): keep the last pose
        candidate = se3_exp(delta) @ T_cam_world
        candidate_p, candidate_e = matches.residuals(candidate)
        candidate_cost, candidate_weights = _cost_and_weights(matches, candidate_p, candidate_e, active, huber)
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
