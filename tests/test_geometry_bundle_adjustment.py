"""The windowed bundle adjustment (vo_core/geometry/bundle_adjustment.py) on a perturbed window of known geometry."""

from __future__ import annotations

import numpy as np
import pytest

from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3, se3_exp, se3_inverse, so3_exp, transform_points
from vo_core.geometry.bundle_adjustment import BundleAdjustmentSettings, WindowProblem, adjust_window

CAMERA = PinholeCamera(320, 240, fx=250.0, fy=250.0, cx=159.5, cy=119.5)
NUM_KEYFRAMES = 6
PIXEL_NOISE = 0.5


def make_window(seed: int, outliers: int = 0):
    """True poses and points, noisy observations, and a problem whose free poses and points are perturbed."""
    rng = np.random.default_rng(seed)
    poses = np.stack([
        se3(so3_exp(rng.normal(0.0, 0.05, 3)), np.array([0.2 * i, 0.02 * i, 0.05 * i]))
        for i in range(NUM_KEYFRAMES)
    ])
    points = rng.uniform([-3.0, -2.0, 4.0], [3.0, 2.0, 8.0], (300, 3))
    pose_index, point_index, uv = [], [], []
    for i, T in enumerate(poses):
        projected = CAMERA.project(transform_points(se3_inverse(T), points))
        seen = np.flatnonzero(CAMERA.in_image(projected))
        pose_index.append(np.full(len(seen), i))
        point_index.append(seen)
        uv.append(projected[seen] + rng.normal(0.0, PIXEL_NOISE, (len(seen), 2)))
    pose_index, point_index, uv = map(np.concatenate, (pose_index, point_index, uv))
    corrupted = rng.choice(len(uv), outliers, replace=False)
    uv[corrupted] += rng.uniform(20.0, 40.0, (outliers, 2))
    fixed = np.arange(NUM_KEYFRAMES) < 2
    perturbed = poses.copy()
    for i in np.flatnonzero(~fixed):
        perturbed[i] = se3_exp(rng.normal(0.0, 0.05, 6)) @ poses[i]
    problem = WindowProblem(
        perturbed, fixed, points + rng.normal(0.0, 0.1, points.shape), pose_index, point_index, uv
    )
    return poses, points, problem, corrupted


def position_errors(poses_a: np.ndarray, poses_b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(poses_a[:, :3, 3] - poses_b[:, :3, 3], axis=1)


@pytest.mark.parametrize("outliers", [0, 40])
def test_adjustment_recovers_a_perturbed_window(outliers):
    poses, points, problem, corrupted = make_window(seed=1, outliers=outliers)
    solution = adjust_window(CAMERA, problem, BundleAdjustmentSettings())

    clean = np.ones(len(problem.observation_uv), bool)
    clean[corrupted] = False
    assert np.sqrt(np.mean(solution.errors_before[clean] ** 2)) > 5.0
    # Down to the noise floor (sqrt(2) sigma for a 2D error), the gross errors kept out by the Huber loss.
    assert np.sqrt(np.mean(solution.errors_after[clean] ** 2)) < 1.2 * np.sqrt(2.0) * PIXEL_NOISE

    before = position_errors(problem.poses_world_cam, poses)[~problem.fixed]
    after = position_errors(solution.poses_world_cam, poses)[~problem.fixed]
    assert np.all(after < 0.6 * before)
    assert np.max(after) < 0.02  # 2 cm on a 1 m path: the fixed poses hold gauge and scale
    held = problem.fixed
    np.testing.assert_allclose(solution.poses_world_cam[held], problem.poses_world_cam[held], atol=1e-12)
    assert np.median(np.linalg.norm(solution.points_world - points, axis=1)) < 0.7 * np.median(
        np.linalg.norm(problem.points_world - points, axis=1)
    )


def test_adjustment_leaves_an_exact_window_alone():
    poses, points, problem, _ = make_window(seed=2)
    exact = WindowProblem(
        poses, problem.fixed, points, problem.observation_pose, problem.observation_point,
        CAMERA.project(
            np.einsum("nij,nj->ni", np.stack([se3_inverse(T) for T in poses])[problem.observation_pose, :3, :3],
                      points[problem.observation_point])
            + np.stack([se3_inverse(T) for T in poses])[problem.observation_pose, :3, 3]
        ),
    )
    solution = adjust_window(CAMERA, exact, BundleAdjustmentSettings())
    assert np.max(solution.errors_after) < 1e-6
    assert np.max(position_errors(solution.poses_world_cam, poses)) < 1e-9
