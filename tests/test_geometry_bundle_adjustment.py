"""The windowed bundle adjustment (vo_core/geometry/bundle_adjustment.py) on a perturbed window of known geometry."""

from __future__ import annotations

import numpy as np
import pytest
from bundle_adjustment_window import CAMERA, PIXEL_NOISE, make_window

from vo_core.geometry.bundle_adjustment import BundleAdjustmentSettings, WindowProblem, adjust_window
from vo_core.geometry.lie import se3_inverse


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
