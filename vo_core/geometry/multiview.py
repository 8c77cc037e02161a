"""Multi-view geometry of calibrated pinhole views: viewing rays, reprojection errors, two-view triangulation with
the checks a new point must pass, and the camera pose from 3D-2D matches by a minimal solver inside RANSAC.

Shared by the KLT baseline (paper 003 II-B), the feature initializer and the feature map (FDMO 4.2.2, 4.3).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3, se3_inverse, transform_points

# ------------------------------------------------------------------------------------------- rays and errors


def world_bearings(camera: PinholeCamera, T_world_cam: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Unit viewing rays (N, 3) of pixels ``uv`` expressed in the world frame."""
    rays = camera.unproject(uv) @ T_world_cam[:3, :3].T
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def bearing_angles(
    camera: PinholeCamera, T_world_a: np.ndarray, uv_a: np.ndarray, T_world_b: np.ndarray, uv_b: np.ndarray
) -> np.ndarray:
    """Angle (rad) between the rays of the same point seen from two poses: paper 003's alpha.

    ``T_world_a`` may be one pose (4, 4) or one per point (N, 4, 4)."""
    if T_world_a.ndim == 3:
        rays_a = np.einsum("nij,nj->ni", T_world_a[:, :3, :3], camera.unproject(uv_a))
        rays_a /= np.linalg.norm(rays_a, axis=1, keepdims=True)
    else:
        rays_a = world_bearings(camera, T_world_a, uv_a)
    rays_b = world_bearings(camera, T_world_b, uv_b)
    return np.arccos(np.clip(np.sum(rays_a * rays_b, axis=1), -1.0, 1.0))


def project_world(
    camera: PinholeCamera, T_world_cam: np.ndarray, points_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(pixels (N, 2), depth (N,)) of world points seen by the camera at ``T_world_cam``; a pixel is only
    meaningful where its depth is positive (the caller checks)."""
    points_cam = transform_points(se3_inverse(T_world_cam), points_world)
    with np.errstate(divide="ignore", invalid="ignore"):
        return camera.project(points_cam), points_cam[:, 2]


def image_motion_px(
    camera: PinholeCamera, points_world: np.ndarray, T_world_a: np.ndarray, T_world_b: np.ndarray
) -> float:
    """Median distance in pixels between where world points appear from camera pose a and from b (those in front
    of both): how far apart two poses are, in what the images can tell apart; inf with no point in front of both."""
    uv_a, depth_a = project_world(camera, T_world_a, points_world)
    uv_b, depth_b = project_world(camera, T_world_b, points_world)
    return median_shift_px(uv_a, uv_b, (depth_a > 0) & (depth_b > 0))


def median_shift_px(uv_a: np.ndarray, uv_b: np.ndarray, front: np.ndarray) -> float:
    """Median distance in pixels between the same points seen at ``uv_a`` and ``uv_b``, over those ``front`` (in
    front of both cameras); inf with none."""
    if not front.any():
        return float("inf")
    return float(np.median(np.linalg.norm(uv_a[front] - uv_b[front], axis=1)))


def reprojection_errors(
    camera: PinholeCamera, T_world_cam: np.ndarray, points_world: np.ndarray, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(pixel distance (N,), depth (N,)) of world points projected into the camera at ``T_world_cam``."""
    projected, depth = project_world(camera, T_world_cam, points_world)
    return np.linalg.norm(projected - uv, axis=1), depth


# ------------------------------------------------------------------------------------------- triangulation


def triangulate(
    camera: PinholeCamera,
    T_world_a: np.ndarray,
    uv_a: np.ndarray,
    T_world_b: np.ndarray,
    uv_b: np.ndarray,
    *,
    max_reprojection_px: float,
    min_depth: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(world points (N, 3), valid (N,) bool): linear (DLT) triangulation of matched pixels, valid where the
    point lies farther than ``min_depth`` in front of both cameras and reprojects within
    ``max_reprojection_px`` into both."""
    if len(uv_a) == 0:
        return np.empty((0, 3)), np.zeros(0, bool)
    K = camera.K
    homogeneous = _dlt(K @ se3_inverse(T_world_a)[:3], K @ se3_inverse(T_world_b)[:3], uv_a, uv_b)
    w = homogeneous[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        points = homogeneous[:, :3] / w[:, None]
    finite = np.isfinite(points).all(axis=1) & (np.abs(w) > 1e-12)
    points[~finite] = 0.0
    valid = finite
    for T_world_cam, uv in ((T_world_a, uv_a), (T_world_b, uv_b)):
        error, depth = reprojection_errors(camera, T_world_cam, points, uv)
        valid &= (depth > min_depth) & (error < max_reprojection_px)
    return points, valid


def _dlt(P_a: np.ndarray, P_b: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    """Homogeneous points (N, 4): for each match the right singular vector of the smallest singular value of its
    4x4 DLT system (Hartley & Zisserman 12.2), the algorithm of cv2.triangulatePoints (same results to 1e-13)
    in one batched SVD, 4x faster than OpenCV's point-by-point loop (20 us a point)."""
    systems = np.stack([uv[:, i, None] * P[2] - P[i] for P, uv in ((P_a, uv_a), (P_b, uv_b)) for i in (0, 1)],
                       axis=1)
    homogeneous = np.full((len(systems), 4), np.nan)
    finite = np.isfinite(systems).all(axis=(1, 2))  # a NaN pixel would stop the whole SVD
    if finite.any():
        homogeneous[finite] = np.linalg.svd(systems[finite])[2][:, -1, :]
    return homogeneous


# ---------------------------------------------------------------------------------------------------- PnP

PNP_SOLVERS = {"p3p": cv2.SOLVEPNP_P3P, "epnp": cv2.SOLVEPNP_EPNP}
# OpenCV's USAC framework (Barath et al.; P3P minimal samples, MSAC scoring, local optimization of the best model):
# the same inliers as the classic RANSAC with EPnP at a tenth to a twentieth of the time in OpenCV 4.12 (25 matches
# with half outliers: 3.9 against 39 ms; 60 with 60 %: 6 against 128 ms), and seeded by its own state.
USAC = "usac"


@dataclass
class PnPConfig:
    """Pose from 3D-2D matches: a minimal solver inside RANSAC, refined on the inliers.

    The defaults are ORB-SLAM2's relocalization (Tracking::Relocalization, PnPsolver::SetRansacParameters(0.99,
    10, 300, 4, 0.5, 5.991)), which FDMO 4.2.2's recovery follows with EPnP (Lepetit et al. 2009). The KLT
    baseline sets its own (vo_core/front_ends/klt/config.py: P3P, paper 003 II-B.1)."""

    solver: str = "epnp"  # inside RANSAC: "p3p" (Kneip et al. 2011), "epnp" (Lepetit et al. 2009) or "usac" (above)
    ransac_iterations: int = 300  # ORB-SLAM2 relocalization: at most 300 RANSAC iterations
    ransac_threshold_px: float = 2.448  # ORB-SLAM2: squared error < 5.991 sigma^2 (chi-square 95 %, 2 DOF), sigma 1 px
    ransac_confidence: float = 0.99  # ORB-SLAM2 relocalization: probability 0.99
    min_inliers: int = 10  # ORB-SLAM2 relocalization: at least 10 inliers
    min_inlier_ratio: float = 0.5  # ORB-SLAM2 relocalization: epsilon 0.5, the expected share of inliers


@dataclass
class PoseEstimate:
    T_world_cam: np.ndarray
    inliers: np.ndarray  # (N,) bool over the matches, after refinement


def estimate_pose(
    camera: PinholeCamera, points_world: np.ndarray, uv: np.ndarray, config: PnPConfig,
    *, T_world_guess: np.ndarray | None = None,
) -> PoseEstimate | None:
    """The pose that best explains the matches, or None when RANSAC finds no consensus of ``min_inliers`` or
    fewer than ``min_inlier_ratio`` of the matches agree.

    The RANSAC inliers are refined by Levenberg-Marquardt from RANSAC's own pose and, when given, from
    ``T_world_guess`` (e.g. a motion model's prediction); the refinement with more inliers wins. Why both:
    OpenCV re-estimates RANSAC's final pose from all inliers with EPnP, which now and then lands far from
    them (seen on KITTI: 148 inliers, none of them within 2 px of the returned pose)."""
    if len(points_world) < max(config.min_inliers, 4):
        return None
    if config.solver not in (*PNP_SOLVERS, USAC):
        raise ValueError(f"PnP solver {config.solver!r} is not one of {', '.join((*PNP_SOLVERS, USAC))}")
    object_points = np.ascontiguousarray(points_world, np.float64)
    image_points = np.ascontiguousarray(uv, np.float64)
    found, rvec, tvec, ransac_inliers = _ransac(camera, object_points, image_points, config)
    if not found or ransac_inliers is None or len(ransac_inliers) < config.min_inliers:
        return None
    chosen = ransac_inliers.ravel()
    starts = [se3(cv2.Rodrigues(rvec)[0], tvec.ravel())]
    if T_world_guess is not None:
        starts.append(se3_inverse(T_world_guess))
    best = None
    for T_cam_world in starts:
        rvec, tvec = cv2.solvePnPRefineLM(
            object_points[chosen], image_points[chosen], camera.K, None,
            cv2.Rodrigues(T_cam_world[:3, :3])[0], T_cam_world[:3, 3].reshape(3, 1).copy(),
        )
        T_world_cam = se3_inverse(se3(cv2.Rodrigues(rvec)[0], tvec.ravel()))
        error, depth = reprojection_errors(camera, T_world_cam, points_world, uv)
        inliers = (depth > 0) & (error < config.ransac_threshold_px)
        if best is None or inliers.sum() > best.inliers.sum():
            best = PoseEstimate(T_world_cam, inliers)
    if best.inliers.sum() < config.min_inliers or best.inliers.mean() < config.min_inlier_ratio:
        return None
    return best


def _ransac(camera: PinholeCamera, object_points: np.ndarray, image_points: np.ndarray, config: PnPConfig):
    """(found, rvec, tvec, inlier indices) of OpenCV's RANSAC with the configured solver."""
    if config.solver == USAC:
        params = cv2.UsacParams()
        params.confidence = config.ransac_confidence
        params.maxIterations = config.ransac_iterations
        params.threshold = config.ransac_threshold_px
        found, _, rvec, tvec, inliers = cv2.solvePnPRansac(object_points, image_points, camera.K, None, params=params)
        return found, rvec, tvec, inliers
    return cv2.solvePnPRansac(
        object_points, image_points, camera.K, None,
        iterationsCount=config.ransac_iterations, reprojectionError=config.ransac_threshold_px,
        confidence=config.ransac_confidence, flags=PNP_SOLVERS[config.solver],
    )
