"""Structure-only bundle adjustment (FDMO 4.3, eqs. 3-6): the map points move, the keyframe poses stay.

FDMO replaces the local bundle adjustment of the feature map by this cheaper one, since the keyframe poses come
from the direct optimization and are already locally optimal. With the poses fixed the points decouple: each
point X_j minimizes its own sum over the keyframes observing it (eq. 3),

    argmin_X sum_i rho(e_ij^T W_i e_ij),  e_ij = pi(R_i X + t_i) - x_ij,

by Gauss-Newton with the closed-form 3x3 update X <- X - (J^T W J)^-1 J^T W e (eq. 4), J stacking the 2x3
reprojection Jacobians pi'(R_i X + t_i) R_i (eq. 5) and W the level weights (eq. 6). All points are solved at
once: per-observation blocks summed per point with bincount, then one batched 3x3 solve.

Robustness and outliers follow ORB-SLAM2's local bundle adjustment (Optimizer::LocalBundleAdjustment, which
FDMO's structure-only step replaces): the first half of the iterations under a Huber kernel, then observations
with a level-normalized squared error above the chi-square 95 % bound (5.991, 2 DOF) or with the point behind
the camera become outliers, and the second half runs on the inliers without the kernel (they are no longer
contaminated). A final check classifies every observation at the final positions.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.reprojection import (
    CHI2_2D_95,
    ORB_SCALE_FACTOR,
    huber_costs,
    level_information,
    project_points,
    projection_jacobians,
    sum_by,
)

ITERATIONS = 10  # FDMO 4.3: "limited the number of iterations ... to ten", no gain beyond
HUBER_PX = float(np.sqrt(CHI2_2D_95))  # ORB-SLAM2 thHuber2D = sqrt(5.991), on the level-normalized error
MIN_OBSERVATIONS = 2  # a point seen once is free along its ray: its 3x3 system is singular
DAMPING_START = 1e-3  # Marquardt damping (relative to the diagonal) for a point whose plain step failed
DAMPING_UP = 10.0
DAMPING_DOWN = 0.1
DIAGONAL_FLOOR = 1e-12  # relative to the trace: keeps the batched solve defined for a near-degenerate point


class PointRefinement(NamedTuple):
    points: np.ndarray  # (M, 3) world positions after the adjustment
    inlier: np.ndarray  # (L,) bool: observation within the chi-square bound, in front of its camera
    errors_px: np.ndarray  # (L,) reprojection error of each observation at the final positions (level-0 pixels)
    in_front: np.ndarray  # (M,) bool: False for a point behind (or at) the centre of a camera that observes it


class _Observations:
    """The fixed half of the problem: each observation's camera (world-to-camera), pixel and weight."""

    def __init__(self, camera, T_world_cams, obs_point, obs_pose, obs_uv, obs_level, scale_factor, num_points):
        T_world_cams = np.asarray(T_world_cams, float)
        R_cam_world = T_world_cams[:, :3, :3].transpose(0, 2, 1)
        t_cam_world = -np.einsum("fij,fj->fi", R_cam_world, T_world_cams[:, :3, 3])
        self.camera = camera
        self.R = R_cam_world[obs_pose]  # (L, 3, 3): R_KF_i of eq. 5, one per observation
        self.t = t_cam_world[obs_pose]
        self.point = np.asarray(obs_point)
        self.uv = np.asarray(obs_uv, float)
        self.information = level_information(obs_level, scale_factor)  # eq. 6, see level_information
        self.num_points = num_points

    def residuals(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(camera-frame points (L, 3), residuals e = pi(R X + t) - x (L, 2))."""
        p = np.einsum("lij,lj->li", self.R, points[self.point]) + self.t
        return p, project_points(self.camera, p) - self.uv

    def normalized_squared(self, p: np.ndarray, e: np.ndarray) -> np.ndarray:
        """e^T W e of each observation (chi-square units); inf behind the camera or where not finite."""
        chi2 = self.information * np.sum(e**2, axis=1)
        return np.where((p[:, 2] > 0) & np.isfinite(chi2), chi2, np.inf)

    def point_costs(self, p: np.ndarray, e: np.ndarray, active: np.ndarray, huber: float | None) -> np.ndarray:
        """Per point, the (robust) cost of its active observations: (M,)."""
        chi2 = self.normalized_squared(p, e)
        terms = chi2 if huber is None else huber_costs(np.sqrt(chi2), huber)
        terms = np.where(active, terms, 0.0)
        # A point gone behind a camera has an infinite cost; summed by bincount it is counted apart, not as inf.
        infinite = np.bincount(self.point, weights=~np.isfinite(terms), minlength=self.num_points)
        costs = np.bincount(self.point, weights=np.where(np.isfinite(terms), terms, 0.0), minlength=self.num_points)
        return np.where(infinite > 0, np.inf, costs)

    def normal_equations(
        self, p: np.ndarray, e: np.ndarray, active: np.ndarray, huber: float | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """J^T W J (M, 3, 3) and J^T W e (M, 3) of eq. 4 per point, W = level information x Huber's IRLS weight."""
        J = projection_jacobians(self.camera, p) @ self.R  # eq. 5
        # Behind the camera the projection's derivative points nowhere useful: such an observation adds nothing.
        weight = np.where(active & (p[:, 2] > 0), self.information, 0.0)
        if huber is not None:
            error = np.sqrt(self.normalized_squared(p, e))
            weight = weight * np.where(error <= huber, 1.0, huber / np.maximum(error, 1e-12))
        weight = np.where(np.isfinite(weight), weight, 0.0)
        JtW = J.transpose(0, 2, 1) * weight[:, None, None]
        H = sum_by(self.point, JtW @ J, self.num_points)
        g = sum_by(self.point, (JtW @ np.nan_to_num(e)[:, :, None])[:, :, 0], self.num_points)
        return H, g


def refine_points(
    camera: PinholeCamera,
    T_world_cams: np.ndarray,
    points_world: np.ndarray,
    obs_point: np.ndarray,
    obs_pose: np.ndarray,
    obs_uv: np.ndarray,
    obs_level: np.ndarray,
    *,
    scale_factor: float = ORB_SCALE_FACTOR,
    iterations: int = ITERATIONS,
    huber_px: float = HUBER_PX,
    chi2: float = CHI2_2D_95,
) -> PointRefinement:
    """Refine the M ``points_world`` seen by the fixed keyframes ``T_world_cams`` (F, 4, 4) through L observations:
    observation l sees point ``obs_point[l]`` from keyframe ``obs_pose[l]`` at pixel ``obs_uv[l]``, detected at
    pyramid level ``obs_level[l]``. ``huber_px`` and ``chi2`` apply to the level-normalized error (level-0 pixels).

    A point moves only while it has two or more observations in use (all of them in the robust first half, its
    inliers in the second): seen once, its position along the ray is not determined."""
    observations = _Observations(
        camera, T_world_cams, obs_point, obs_pose, obs_uv, obs_level, scale_factor, len(points_world)
    )
    points = np.array(points_world, dtype=float)
    active = np.ones(len(observations.point), bool)
    robust_iterations = (iterations + 1) // 2  # ORB-SLAM2 local BA: robust first, then the inliers alone
    points = _gauss_newton(observations, points, active, robust_iterations, huber_px)
    active = _inliers(observations, points, chi2)
    points = _gauss_newton(observations, points, active, iterations - robust_iterations, None)
    p, e = observations.residuals(points)
    behind = np.bincount(observations.point, weights=(p[:, 2] <= 0).astype(float), minlength=len(points))
    return PointRefinement(points, _inliers(observations, points, chi2), np.linalg.norm(e, axis=1), behind == 0)


def _inliers(observations: _Observations, points: np.ndarray, chi2: float) -> np.ndarray:
    """ORB-SLAM2's test of a monocular observation: e^T W e <= 5.991 and the point in front of the camera."""
    p, e = observations.residuals(points)
    return observations.normalized_squared(p, e) <= chi2


def _gauss_newton(
    observations: _Observations, points: np.ndarray, active: np.ndarray, iterations: int, huber: float | None
) -> np.ndarray:
    """``iterations`` steps of eq. 4 for every point at once. A point whose step does not lower its cost stays
    and retries with Marquardt damping (Gauss-Newton alone may overshoot on a point seen under little
    parallax); the fixed point is the same, only the path is safer."""
    counts = np.bincount(observations.point, weights=active.astype(float), minlength=len(points))
    solvable = counts >= MIN_OBSERVATIONS
    damping = np.zeros(len(points))  # 0: the plain Gauss-Newton update of eq. 4
    p, e = observations.residuals(points)
    cost = observations.point_costs(p, e, active, huber)
    for _ in range(iterations):
        H, g = observations.normal_equations(p, e, active, huber)
        step = _solve_3x3(H, g, damping, solvable)
        candidate = points - step  # eq. 4: X <- X - (J^T W J)^-1 J^T W e
        candidate_p, candidate_e = observations.residuals(candidate)
        candidate_cost = observations.point_costs(candidate_p, candidate_e, active, huber)
        better = solvable & (candidate_cost < cost)
        points = np.where(better[:, None], candidate, points)
        cost = np.where(better, candidate_cost, cost)
        damping = np.where(better, damping * DAMPING_DOWN, np.maximum(damping * DAMPING_UP, DAMPING_START))
        p, e = observations.residuals(points)
    return points


def _solve_3x3(H: np.ndarray, g: np.ndarray, damping: np.ndarray, solvable: np.ndarray) -> np.ndarray:
    """(H + damping diag(H))^-1 g for every solvable point, zero for the others: one batched solve."""
    step = np.zeros_like(g)
    if not solvable.any():
        return step
    H, g, damping = H[solvable], g[solvable], damping[solvable]
    diagonal = np.einsum("mii->mi", H)
    floor = DIAGONAL_FLOOR * diagonal.sum(axis=1, keepdims=True) + np.finfo(float).tiny
    H = H + (damping[:, None] * diagonal + floor)[:, :, None] * np.eye(3)
    step[solvable] = np.linalg.solve(H, g[:, :, None])[:, :, 0]
    return step
