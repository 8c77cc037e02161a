"""The reprojection residual of a pinhole camera, its derivatives, and how residuals are weighted: the pieces that
the bundle adjustments (window, structure-only, motion-only) share.

Residuals are predicted minus measured, e = pi(R X + t) - x, the sign of FDMO eq. 4 (X <- X - (J^T W J)^-1 J^T W e).
"""

from __future__ import annotations

import numpy as np

from vo_core.compiled import kernel
from vo_core.geometry.camera import PinholeCamera

# Chi-square 95 % quantile with 2 degrees of freedom: the outlier threshold of a monocular observation's
# squared error in units of its level's variance (ORB-SLAM2 Optimizer.cc: chi2Mono = 5.991; thHuber2D = sqrt of it).
CHI2_2D_95 = 5.991
ORB_SCALE_FACTOR = 1.2  # FDMO 4.3 eq. 6: Sf = 1.2, the ORB pyramid's scale factor (ORB-SLAM2's default too)


def project_points(camera: PinholeCamera, points_cam: np.ndarray) -> np.ndarray:
    """Pixels (L, 2) of camera-frame points (L, 3); inf/nan where the depth is zero (the caller checks depth)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.stack(
            [camera.fx * points_cam[:, 0] / points_cam[:, 2] + camera.cx,
             camera.fy * points_cam[:, 1] / points_cam[:, 2] + camera.cy],
            axis=1,
        )


def projection_jacobians(camera: PinholeCamera, points_cam: np.ndarray) -> np.ndarray:
    """d(u, v)/d(x, y, z) of the pinhole projection at camera-frame points: (L, 2, 3),
    [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] (FDMO eq. 5 before its R_KF; the paper prints the first row's
    last entry as -fx X/Z, a typo for -fx X/Z^2)."""
    inv_z = 1.0 / points_cam[:, 2]
    J = np.zeros((len(points_cam), 2, 3))
    J[:, 0, 0] = camera.fx * inv_z
    J[:, 0, 2] = -camera.fx * points_cam[:, 0] * inv_z**2
    J[:, 1, 1] = camera.fy * inv_z
    J[:, 1, 2] = -camera.fy * points_cam[:, 1] * inv_z**2
    return J


def pose_jacobians(points_cam: np.ndarray) -> np.ndarray:
    """d(exp(delta) p)/d(v, w) at delta = 0 for the left update T_cam_world <- exp(delta) T_cam_world: [I, -[p]x],
    (L, 3, 6), twists ordered (translation, rotation) as everywhere in the project."""
    p = points_cam
    J = np.zeros((len(p), 3, 6))
    J[:, :, :3] = np.eye(3)
    J[:, 0, 4], J[:, 0, 5] = p[:, 2], -p[:, 1]
    J[:, 1, 3], J[:, 1, 5] = -p[:, 2], p[:, 0]
    J[:, 2, 3], J[:, 2, 4] = p[:, 1], -p[:, 0]
    return J


def huber_cost_and_weights(errors: np.ndarray, k: float) -> tuple[float, np.ndarray]:
    """Huber cost sum rho(e) with rho(e) = e^2 (e <= k), 2 k e - k^2 (e > k), and the IRLS weights
    w = rho'(e) / (2 e) = min(1, k / e) that make the weighted Gauss-Newton step minimize it."""
    inlier = errors <= k
    cost = np.where(inlier, errors**2, 2.0 * k * errors - k**2).sum()
    weights = np.where(inlier, 1.0, k / np.maximum(errors, 1e-12))
    return float(cost), weights


def level_information(level: np.ndarray, scale_factor: float) -> np.ndarray:
    """Weight (information, 1/sigma^2) of a feature found at pyramid level n: Sf^(-2n).

    A feature detected at level n is located to about Sf^n level-0 pixels, so its squared error has variance
    Sf^(2n) and its information is the inverse. FDMO eq. 6 prints W = Sf^(2n), but its text says W
    "down-weighs the effect of residuals computed from feature matches found at high pyramidal levels" as in
    ORB-SLAM2, which sets the information to mvInvLevelSigma2[octave] = 1 / Sf^(2n) (Optimizer.cc, every
    monocular edge); Sf^(2n) would up-weigh them, so the printed exponent's sign is taken to be a typo."""
    return np.power(float(scale_factor), -2.0 * np.asarray(level, dtype=float))


def sum_by(index: np.ndarray, values: np.ndarray, count: int) -> np.ndarray:
    """Sums of ``values`` (n, ...) grouped by ``index`` (n,) into (count, ...): one bincount for all entries."""
    width = int(np.prod(values.shape[1:]))
    flat = values.reshape(len(values), width)  # explicit width: -1 is undefined when there are no values
    bins = (index[:, None] * width + np.arange(width)).ravel()
    sums = np.bincount(bins, weights=flat.ravel(), minlength=count * width)
    return sums.reshape((count, *values.shape[1:]))


@kernel
def adjugate_3x3(M, out):
    """``out`` = the adjugate of a 3x3 M (M^-1 times its determinant), and the determinant: a point's 3x3 block of
    the normal equations solved in closed form (a LAPACK call per point costs more than the point's work)."""
    out[0, 0] = M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]
    out[1, 0] = M[1, 2] * M[2, 0] - M[1, 0] * M[2, 2]
    out[2, 0] = M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]
    out[0, 1] = M[0, 2] * M[2, 1] - M[0, 1] * M[2, 2]
    out[0, 2] = M[0, 1] * M[1, 2] - M[0, 2] * M[1, 1]
    out[1, 1] = M[0, 0] * M[2, 2] - M[0, 2] * M[2, 0]
    out[1, 2] = M[0, 2] * M[1, 0] - M[0, 0] * M[1, 2]
    out[2, 1] = M[0, 1] * M[2, 0] - M[0, 0] * M[2, 1]
    out[2, 2] = M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]
    return M[0, 0] * out[0, 0] + M[0, 1] * out[1, 0] + M[0, 2] * out[2, 0]
