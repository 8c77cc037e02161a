"""Structure-only bundle adjustment (FDMO 4.3, eqs. 3-6): the map points move, the keyframe poses stay.

FDMO replaces the local bundle adjustment of the feature map by this cheaper one, since the keyframe poses come
from the direct optimization and are already locally optimal. With the poses fixed the points decouple: each
point X_j minimizes its own sum over the keyframes observing it (eq. 3),

    argmin_X sum_i rho(e_ij^T W_i e_ij),  e_ij = pi(R_i X + t_i) - x_ij,

by Gauss-Newton with the closed-form 3x3 update X <- X - (J^T W J)^-1 J^T W e (eq. 4), J stacking the 2x3
reprojection Jacobians pi'(R_i X + t_i) R_i (eq. 5) and W the level weights (eq. 6). The points are solved one
after another by a compiled kernel over each point's observations (they share nothing): a few hundred floating
point operations per observation, where array code spent its time allocating (L, 3, 3) temporaries, and free of
the interpreter's lock, so the feature mapper's thread runs beside tracking.

Robustness and outliers follow ORB-SLAM2's local bundle adjustment (Optimizer::LocalBundleAdjustment, which
FDMO's structure-only step replaces): the first half of the iterations under a Huber kernel, then observations
with a level-normalized squared error above the chi-square 95 % bound (5.991, 2 DOF) or with the point behind
the camera become outliers, and the second half runs on the inliers without the kernel (they are no longer
contaminated). A final check classifies every observation at the final positions.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vo_core.compiled import kernel
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.reprojection import CHI2_2D_95, ORB_SCALE_FACTOR, adjugate_3x3, level_information

ITERATIONS = 10  # FDMO 4.3: "limited the number of iterations ... to ten", no gain beyond
HUBER_PX = float(np.sqrt(CHI2_2D_95))  # ORB-SLAM2 thHuber2D = sqrt(5.991), on the level-normalized error
MIN_OBSERVATIONS = 2  # a point seen once is free along its ray: its 3x3 system is singular
DAMPING_START = 1e-3  # Marquardt damping (relative to the diagonal) for a point whose plain step failed
DAMPING_UP = 10.0
DAMPING_DOWN = 0.1
DIAGONAL_FLOOR = 1e-12  # relative to the trace: keeps the 3x3 solve defined for a near-degenerate point
NO_HUBER = -1.0  # the kernel's "no robust kernel" (the second half of the iterations)
# A point whose Gauss-Newton step is below this, relative to its position, has converged: its remaining iterations
# would move it by less than the step (Ceres' parameter_tolerance, 1e-8). Most points converge in 2-4 of the 10.
PARAMETER_TOLERANCE = 1e-8


class PointRefinement(NamedTuple):
    points: np.ndarray  # (M, 3) world positions after the adjustment
    inlier: np.ndarray  # (L,) bool: observation within the chi-square bound, in front of its camera
    errors_px: np.ndarray  # (L,) reprojection error of each observation at the final positions (level-0 pixels)
    in_front: np.ndarray  # (M,) bool: False for a point behind (or at) the centre of a camera that observes it


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
    parameter_tolerance: float = PARAMETER_TOLERANCE,
) -> PointRefinement:
    """Refine the M ``points_world`` seen by the fixed keyframes ``T_world_cams`` (F, 4, 4) through L observations:
    observation l sees point ``obs_point[l]`` from keyframe ``obs_pose[l]`` at pixel ``obs_uv[l]``, detected at
    pyramid level ``obs_level[l]``. ``huber_px`` and ``chi2`` apply to the level-normalized error (level-0 pixels);
    a point stops once its step is below ``parameter_tolerance`` relative to its position (0: every iteration).

    A point moves only while it has two or more observations in use (all of them in the robust first half, its
    inliers in the second): seen once, its position along the ray is not determined."""
    T_world_cams = np.asarray(T_world_cams, float).reshape(-1, 4, 4)
    R_cam_world = np.ascontiguousarray(T_world_cams[:, :3, :3].transpose(0, 2, 1))
    t_cam_world = -np.einsum("fij,fj->fi", R_cam_world, T_world_cams[:, :3, 3])
    obs_point = np.asarray(obs_point, np.int64)
    order = np.argsort(obs_point, kind="stable")  # each point's observations side by side
    first_obs = np.searchsorted(obs_point[order], np.arange(len(points_world) + 1))
    points = np.array(points_world, dtype=float).reshape(-1, 3)
    inlier, errors_px, in_front = _refine(
        points, first_obs, np.asarray(obs_pose, np.int64)[order], np.asarray(obs_uv, float).reshape(-1, 2)[order],
        level_information(np.asarray(obs_level)[order], scale_factor), R_cam_world, t_cam_world,
        camera.intrinsics, (iterations + 1) // 2, iterations, huber_px, chi2, parameter_tolerance,
    )  # ORB-SLAM2 local BA: robust first, then the inliers alone
    unsorted_inlier, unsorted_errors = np.empty_like(inlier), np.empty_like(errors_px)
    unsorted_inlier[order], unsorted_errors[order] = inlier, errors_px
    return PointRefinement(points, unsorted_inlier, unsorted_errors, in_front)


@kernel
def _refine(points, first_obs, pose, uv, information, R, t, intrinsics, robust_iterations, iterations, huber, chi2,
            tolerance):
    """Every point in place (``points``), its observations ``first_obs[j]:first_obs[j + 1]``. Returns each
    observation's inlier flag and error (px) at the final positions, and each point's in-front flag."""
    inlier = np.zeros(len(pose), np.bool_)
    errors_px = np.zeros(len(pose))
    in_front = np.ones(len(points), np.bool_)
    for j in range(len(points)):
        rows = np.arange(first_obs[j], first_obs[j + 1])
        active = np.ones(len(rows), np.bool_)
        _gauss_newton(points[j], rows, active, pose, uv, information, R, t, intrinsics, robust_iterations, huber,
                      tolerance)
        for k, l in enumerate(rows):
            active[k] = _observation(points[j], l, pose, uv, information, R, t, intrinsics)[0] <= chi2
        _gauss_newton(points[j], rows, active, pose, uv, information, R, t, intrinsics,
                      iterations - robust_iterations, NO_HUBER, tolerance)
        for l in rows:
            chi2_l, _, _, z, e0, e1 = _observation(points[j], l, pose, uv, information, R, t, intrinsics)
            inlier[l] = chi2_l <= chi2
            errors_px[l] = np.sqrt(e0**2 + e1**2)
            in_front[j] &= z > 0.0
    return inlier, errors_px, in_front


@kernel
def _observation(X, l, pose, uv, information, R, t, intrinsics):
    """Observation ``l`` of point X: e^T W e (chi-square units; inf behind the camera or where not finite), the
    point in its camera (R X + t) and the residual e = pi(R X + t) - x."""
    f = pose[l]
    x = R[f, 0, 0] * X[0] + R[f, 0, 1] * X[1] + R[f, 0, 2] * X[2] + t[f, 0]
    y = R[f, 1, 0] * X[0] + R[f, 1, 1] * X[1] + R[f, 1, 2] * X[2] + t[f, 1]
    z = R[f, 2, 0] * X[0] + R[f, 2, 1] * X[1] + R[f, 2, 2] * X[2] + t[f, 2]
    if z == 0.0:
        return np.inf, x, y, z, np.inf, np.inf
    e0 = intrinsics[0] * x / z + intrinsics[2] - uv[l, 0]
    e1 = intrinsics[1] * y / z + intrinsics[3] - uv[l, 1]
    value = information[l] * (e0**2 + e1**2)
    return (value if z > 0.0 and np.isfinite(value) else np.inf), x, y, z, e0, e1


@kernel
def _cost(X, rows, active, pose, uv, information, R, t, intrinsics, huber):
    """The point's (robust) cost over its active observations; inf if one of them is behind its camera."""
    total = 0.0
    for k, l in enumerate(rows):
        if not active[k]:
            continue
        chi2 = _observation(X, l, pose, uv, information, R, t, intrinsics)[0]
        if not np.isfinite(chi2):
            return np.inf
        error = np.sqrt(chi2)
        total += chi2 if huber < 0.0 or error <= huber else 2.0 * huber * error - huber**2
    return total


@kernel
def _gauss_newton(X, rows, active, pose, uv, information, R, t, intrinsics, iterations, huber, tolerance):
    """At most ``iterations`` steps of eq. 4 for one point, in place, until the step is below ``tolerance``
    relative to the point's position. A step that does not lower the cost is refused and retried with Marquardt
    damping (Gauss-Newton alone may overshoot on a point seen under little parallax); the fixed point is the same,
    only the path is safer."""
    if np.count_nonzero(active) < MIN_OBSERVATIONS:
        return
    fx, fy = intrinsics[0], intrinsics[1]
    damping = 0.0  # 0: the plain Gauss-Newton update of eq. 4
    cost = _cost(X, rows, active, pose, uv, information, R, t, intrinsics, huber)
    H, g, J = np.empty((3, 3)), np.empty(3), np.empty((2, 3))
    for _ in range(iterations):
        H[:], g[:] = 0.0, 0.0
        for k, l in enumerate(rows):
            chi2, x, y, z, e0, e1 = _observation(X, l, pose, uv, information, R, t, intrinsics)
            if not active[k] or not z > 0.0:  # behind the camera the derivative points nowhere useful
                continue
            weight = information[l]
            if huber >= 0.0:
                error = np.sqrt(chi2)
                weight *= 1.0 if error <= huber else huber / max(error, 1e-12)
            if not np.isfinite(weight):
                continue
            f = pose[l]
            e0 = e0 if np.isfinite(e0) else 0.0
            e1 = e1 if np.isfinite(e1) else 0.0
            for i in range(3):  # eq. 5: pi'(R X + t) R
                J[0, i] = fx / z * (R[f, 0, i] - x / z * R[f, 2, i])
                J[1, i] = fy / z * (R[f, 1, i] - y / z * R[f, 2, i])
            for a in range(3):
                g[a] += weight * (J[0, a] * e0 + J[1, a] * e1)
                for b in range(3):
                    H[a, b] += weight * (J[0, a] * J[0, b] + J[1, a] * J[1, b])
        floor = DIAGONAL_FLOOR * (H[0, 0] + H[1, 1] + H[2, 2]) + np.finfo(np.float64).tiny
        for a in range(3):
            H[a, a] += damping * H[a, a] + floor
        step = _solve_3x3(H, g)
        if np.sqrt(step @ step) <= tolerance * (np.sqrt(X @ X) + tolerance):
            return
        candidate = X - step  # eq. 4: X <- X - (J^T W J)^-1 J^T W e
        candidate_cost = _cost(candidate, rows, active, pose, uv, information, R, t, intrinsics, huber)
        if candidate_cost < cost:
            X[:] = candidate
            cost = candidate_cost
            damping *= DAMPING_DOWN
        else:
            damping = max(damping * DAMPING_UP, DAMPING_START)


@kernel
def _solve_3x3(H, g):
    """H^-1 g by the adjugate (H symmetric positive semi-definite, floored on its diagonal)."""
    adjugate = np.empty((3, 3))
    determinant = adjugate_3x3(H, adjugate)
    if determinant == 0.0 or not np.isfinite(determinant):
        return np.zeros(3)
    return adjugate @ g / determinant
