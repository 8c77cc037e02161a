"""Multi-view geometry (vo_core/geometry/multiview.py): triangulation and its checks, the pose from 3D-2D matches
by P3P or EPnP inside RANSAC."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3, se3_inverse, so3_exp, so3_geodesic_angle, transform_points
from vo_core.geometry.multiview import PnPConfig, bearing_angles, estimate_pose, triangulate

CAMERA = PinholeCamera(640, 480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)
TRUE_POSE = se3(so3_exp(np.array([0.05, -0.1, 0.02])), np.array([0.4, -0.1, 0.2]))


def project(T_world_cam: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    return CAMERA.project(transform_points(se3_inverse(T_world_cam), points_world))


def points_in_view(rng: np.random.Generator, count: int, T_world_cam: np.ndarray = TRUE_POSE) -> np.ndarray:
    rays = CAMERA.unproject(rng.uniform([20, 20], [620, 460], (count, 2)))
    return transform_points(T_world_cam, rays * rng.uniform(2.0, 8.0, count)[:, None])


def with_wrong_matches(rng: np.random.Generator, uv: np.ndarray, share: float) -> tuple[np.ndarray, np.ndarray]:
    """``share`` of the pixels replaced by random ones at least 20 px from the truth; and which."""
    uv = uv.copy()
    wrong = rng.choice(len(uv), int(share * len(uv)), replace=False)
    for index in wrong:
        true = uv[index].copy()
        while np.linalg.norm(uv[index] - true) < 20.0:
            uv[index] = rng.uniform([0, 0], [639, 479])
    is_wrong = np.zeros(len(uv), bool)
    is_wrong[wrong] = True
    return uv, is_wrong


def test_triangulation_recovers_points_and_rejects_what_fails_the_checks():
    rng = np.random.default_rng(0)
    T_a, T_b = np.eye(4), se3(so3_exp(np.array([0.0, 0.05, 0.0])), np.array([0.5, 0.0, 0.0]))
    points = points_in_view(rng, 100, T_a)
    uv_a, uv_b = project(T_a, points), project(T_b, points)
    uv_b[:10] += 5.0  # bad tracks: reproject worse than 2 px
    triangulated, valid = triangulate(CAMERA, T_a, uv_a, T_b, uv_b, max_reprojection_px=2.0, min_depth=1e-3)
    assert not valid[:10].any() and valid[10:].all()
    np.testing.assert_allclose(triangulated[valid], points[valid], atol=1e-8)
    # The bearing angle of a point seen from both ends of a 0.5 m baseline at 2-8 m: 3.6 to 14 degrees, plus the
    # rotation's share.
    angles = np.degrees(bearing_angles(CAMERA, T_a, uv_a[10:], T_b, uv_b[10:]))
    assert np.all((angles > 2.0) & (angles < 20.0))


def test_triangulation_agrees_with_opencv_and_refuses_pixels_that_are_not_numbers():
    """The batched DLT is cv2.triangulatePoints' algorithm: the same points on noisy matches. A NaN pixel (a lost
    track) makes its own point invalid, not the others'."""
    rng = np.random.default_rng(2)
    T_a, T_b = np.eye(4), se3(so3_exp(np.array([0.02, 0.04, 0.0])), np.array([0.3, 0.05, 0.0]))
    points = points_in_view(rng, 200, T_a)
    uv_a = project(T_a, points) + rng.normal(0.0, 0.5, (200, 2))
    uv_b = project(T_b, points) + rng.normal(0.0, 0.5, (200, 2))
    uv_b[7] = np.nan
    triangulated, valid = triangulate(CAMERA, T_a, uv_a, T_b, uv_b, max_reprojection_px=2.0, min_depth=1e-3)
    P_a, P_b = (CAMERA.K @ se3_inverse(T)[:3] for T in (T_a, T_b))
    homogeneous = cv2.triangulatePoints(P_a, P_b, uv_a.T, uv_b.T)
    opencv = (homogeneous[:3] / homogeneous[3]).T
    assert not valid[7] and np.count_nonzero(valid) > 190
    np.testing.assert_allclose(triangulated[valid], opencv[valid], rtol=1e-9, atol=1e-9)


def test_triangulation_of_nothing():
    points, valid = triangulate(
        CAMERA, np.eye(4), np.empty((0, 2)), np.eye(4), np.empty((0, 2)), max_reprojection_px=2.0, min_depth=0.0
    )
    assert points.shape == (0, 3) and valid.shape == (0,)


@pytest.mark.parametrize("solver", ["epnp", "p3p", "usac"])
def test_pnp_ransac_finds_the_pose_among_40_percent_wrong_matches(solver):
    rng = np.random.default_rng(1)
    points = points_in_view(rng, 120)
    uv, is_wrong = with_wrong_matches(rng, project(TRUE_POSE, points), 0.4)
    estimate = estimate_pose(CAMERA, points, uv, PnPConfig(solver=solver))
    assert estimate is not None
    assert np.linalg.norm(estimate.T_world_cam[:3, 3] - TRUE_POSE[:3, 3]) < 1e-6
    assert np.degrees(so3_geodesic_angle(estimate.T_world_cam[:3, :3], TRUE_POSE[:3, :3])) < 1e-4
    np.testing.assert_array_equal(estimate.inliers, ~is_wrong)


def test_pnp_refuses_when_too_few_matches_agree():
    """60 % wrong: fewer agree than ORB-SLAM2's epsilon (half of the matches), so no pose."""
    rng = np.random.default_rng(2)
    points = points_in_view(rng, 120)
    uv, _ = with_wrong_matches(rng, project(TRUE_POSE, points), 0.6)
    assert estimate_pose(CAMERA, points, uv, PnPConfig(solver="epnp")) is None
    assert estimate_pose(CAMERA, points, uv, PnPConfig(solver="epnp", min_inlier_ratio=0.3)) is not None


def test_pnp_guess_is_one_of_the_starting_points():
    rng = np.random.default_rng(3)
    points = points_in_view(rng, 60)
    uv = project(TRUE_POSE, points)
    estimate = estimate_pose(CAMERA, points, uv, PnPConfig(solver="p3p"), T_world_guess=TRUE_POSE)
    assert estimate is not None and estimate.inliers.all()


def test_pnp_unknown_solver_is_an_error():
    rng = np.random.default_rng(4)
    points = points_in_view(rng, 30)
    with pytest.raises(ValueError, match="dls"):
        estimate_pose(CAMERA, points, project(TRUE_POSE, points), PnPConfig(solver="dls"))
