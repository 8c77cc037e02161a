"""Motion-only bundle adjustment (vo_core/geometry/pose_only.py, ORB-SLAM2 PoseOptimization): a pose several
centimetres and degrees off comes back on exact data, and the gross outliers among the matches are flagged."""

from __future__ import annotations

import numpy as np
import pytest

from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3, se3_exp, se3_inverse, so3_exp, so3_geodesic_angle, transform_points
from vo_core.geometry.pose_only import refine_pose

CAMERA = PinholeCamera(640, 480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)
TRUE_POSE = se3(so3_exp(np.array([0.05, -0.1, 0.02])), np.array([0.4, -0.1, 0.2]))


def matches(seed: int, count: int = 150, outlier_share: float = 0.3):
    """Map points 2-8 m in front of the true camera, their exact pixels, and ``outlier_share`` of the pixels
    replaced by random ones at least 20 px from the truth (wrong matches)."""
    rng = np.random.default_rng(seed)
    rays = CAMERA.unproject(rng.uniform([20, 20], [620, 460], (count, 2)))
    points = transform_points(TRUE_POSE, rays * rng.uniform(2.0, 8.0, count)[:, None])
    uv = CAMERA.project(transform_points(se3_inverse(TRUE_POSE), points))
    level = rng.integers(0, 8, count)
    outliers = rng.choice(count, int(outlier_share * count), replace=False)
    for index in outliers:
        wrong = uv[index]
        while np.linalg.norm(wrong - uv[index]) < 20.0:
            wrong = rng.uniform([0, 0], [639, 479])
        uv[index] = wrong
    is_outlier = np.zeros(count, bool)
    is_outlier[outliers] = True
    return points, uv, level, is_outlier, rng


def guess_off_by(rng: np.random.Generator, metres: float, degrees: float) -> np.ndarray:
    """The true pose moved ``metres`` and turned ``degrees`` about random directions."""
    direction, axis = rng.normal(size=3), rng.normal(size=3)
    twist = np.concatenate([metres * direction / np.linalg.norm(direction),
                            np.radians(degrees) * axis / np.linalg.norm(axis)])
    T = se3_exp(twist)
    return se3(T[:3, :3] @ TRUE_POSE[:3, :3], TRUE_POSE[:3, 3] + twist[:3])


def pose_errors(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(position error in metres, rotation error in degrees)."""
    return (float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])),
            float(np.degrees(so3_geodesic_angle(T_a[:3, :3], T_b[:3, :3]))))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pose_returns_and_outliers_are_flagged(seed):
    points, uv, level, is_outlier, rng = matches(seed)
    guess = guess_off_by(rng, 0.05, 2.0)
    assert pose_errors(guess, TRUE_POSE)[0] == pytest.approx(0.05)
    assert pose_errors(guess, TRUE_POSE)[1] == pytest.approx(2.0)

    T_world_cam, inlier, errors = refine_pose(CAMERA, guess, points, uv, level)

    position, rotation = pose_errors(T_world_cam, TRUE_POSE)
    assert position < 1e-3 and rotation < 0.05
    np.testing.assert_array_equal(inlier, ~is_outlier)
    assert np.max(errors[inlier]) < 1e-3
    assert np.min(errors[~inlier]) > 19.0


def test_the_outliers_would_pull_a_plain_least_squares_fit():
    """The same data without the outlier classification and the robust kernel (a chi-square bound that nothing
    exceeds): the wrong matches pull the pose far away, so the test above does test the outlier handling."""
    points, uv, level, _, rng = matches(0)
    guess = guess_off_by(rng, 0.05, 2.0)
    T_world_cam, inlier, _ = refine_pose(CAMERA, guess, points, uv, level, chi2=1e12)
    assert inlier.all()
    position, rotation = pose_errors(T_world_cam, TRUE_POSE)
    assert position > 0.01 or rotation > 0.5


def test_an_observation_rejected_early_comes_back_when_the_pose_explains_it():
    """One iteration per round from a guess 20 cm and 3 degrees off: after the first round the pose is not there
    yet and 3 correct matches exceed the bound; the later rounds bring the pose back, and those matches with it
    (ORB-SLAM2 classifies every observation, outliers included, after each round)."""
    points, uv, level, _, rng = matches(3, outlier_share=0.0)
    guess = guess_off_by(rng, 0.2, 3.0)
    _, after_first_round, _ = refine_pose(CAMERA, guess, points, uv, level, rounds=1, iterations=1)
    assert not after_first_round.all()
    T_world_cam, inlier, _ = refine_pose(CAMERA, guess, points, uv, level, iterations=1)
    assert inlier.all()
    assert pose_errors(T_world_cam, TRUE_POSE)[0] < 1e-6


def test_level_weights_trust_the_fine_levels():
    """Half the features at level 0 (sigma 1 px), half at level 7 (sigma 1.2^7 = 3.6 px): with the level weights
    the pose is about twice as close to the truth as with equal weights (measured over these 10 draws: 2.7 vs
    5.7 mm, better in every draw)."""
    weighted, equal = [], []
    for seed in range(100, 110):
        rng = np.random.default_rng(seed)
        points, uv, _, _, _ = matches(seed, count=300, outlier_share=0.0)
        level = 7 * rng.integers(0, 2, len(uv))
        noisy = uv + rng.normal(size=uv.shape) * (1.2**level)[:, None]
        guess = guess_off_by(rng, 0.02, 1.0)
        no_outliers = 1e12  # a chi-square bound nothing exceeds: only the weights differ
        weighted.append(pose_errors(refine_pose(CAMERA, guess, points, noisy, level, chi2=no_outliers)[0], TRUE_POSE))
        equal.append(pose_errors(refine_pose(CAMERA, guess, points, noisy, 0 * level, chi2=no_outliers)[0], TRUE_POSE))
    assert np.mean(np.array(weighted)[:, 0]) < 0.7 * np.mean(np.array(equal)[:, 0])


def test_too_few_matches_leave_the_guess():
    points, uv, level, _, rng = matches(5, count=2, outlier_share=0.0)
    guess = guess_off_by(rng, 0.05, 2.0)
    T_world_cam, inlier, errors = refine_pose(CAMERA, guess, points, uv, level)
    np.testing.assert_allclose(T_world_cam, guess, atol=1e-12)
    assert inlier.shape == errors.shape == (2,)
