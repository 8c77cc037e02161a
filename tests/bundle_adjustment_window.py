"""A window of known geometry for the bundle adjustment's tests: true poses and points, noisy observations, and
the problem with its free poses and points perturbed."""

from __future__ import annotations

import numpy as np

from vo_core.geometry.bundle_adjustment import WindowProblem
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3, se3_exp, se3_inverse, so3_exp, transform_points

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
