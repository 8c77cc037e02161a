"""Two-view triangulation with the checks a new landmark must pass: in front of both cameras, reprojecting
well into both, and seen under a large enough bearing angle (paper 003 II-B.2)."""

from __future__ import annotations

import cv2
import numpy as np

from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_inverse, transform_points


def world_bearings(camera: PinholeCamera, T_world_cam: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Unit viewing rays (N, 3) of pixels ``uv`` expressed in the world frame."""
    rays = camera.unproject(uv) @ T_world_cam[:3, :3].T
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def bearing_angles(
    camera: PinholeCamera, T_world_a: np.ndarray, uv_a: np.ndarray, T_world_b: np.ndarray, uv_b: np.ndarray
) -> np.ndarray:
    """Angle (rad) between the rays of the same point seen from two poses: the paper's alpha.

    ``T_world_a`` may be one pose (4, 4) or one per point (N, 4, 4)."""
    if T_world_a.ndim == 3:
        rays_a = np.einsum("nij,nj->ni", T_world_a[:, :3, :3], camera.unproject(uv_a))
        rays_a /= np.linalg.norm(rays_a, axis=1, keepdims=True)
    else:
        rays_a = world_bearings(camera, T_world_a, uv_a)
    rays_b = world_bearings(camera, T_world_b, uv_b)
    return np.arccos(np.clip(np.sum(rays_a * rays_b, axis=1), -1.0, 1.0))


def reprojection_errors(
    camera: PinholeCamera, T_world_cam: np.ndarray, points_world: np.ndarray, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(pixel distance (N,), depth (N,)) of world points projected into the camera at ``T_world_cam``."""
    points_cam = transform_points(se3_inverse(T_world_cam), points_world)
    depth = points_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        projected = camera.project(points_cam)
    return np.linalg.norm(projected - uv, axis=1), depth


def triangulate(
    camera: PinholeCamera,
    T_world_a: np.ndarray,
    uv_a: np.ndarray,
    T_world_b: np.ndarray,
    uv_b: np.ndarray,
    max_reprojection_px: float,
    min_depth: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(world points (N, 3), valid (N,) bool): linear (DLT) triangulation of matched pixels, valid where the
    point lies in front of both cameras and reprojects within ``max_reprojection_px`` into both."""
    if len(uv_a) == 0:
        return np.empty((0, 3)), np.zeros(0, bool)
    K = camera.K
    P_a = K @ se3_inverse(T_world_a)[:3]
    P_b = K @ se3_inverse(T_world_b)[:3]
    homogeneous = cv2.triangulatePoints(P_a, P_b, uv_a.T.astype(float), uv_b.T.astype(float))
    w = homogeneous[3]
    with np.errstate(divide="ignore", invalid="ignore"):
        points = (homogeneous[:3] / w).T
    finite = np.isfinite(points).all(axis=1) & (np.abs(w) > 1e-12)
    points[~finite] = 0.0
    valid = finite
    for T_world_cam, uv in ((T_world_a, uv_a), (T_world_b, uv_b)):
        error, depth = reprojection_errors(camera, T_world_cam, points, uv)
        valid &= (depth > min_depth) & (error < max_reprojection_px)
    return points, valid
