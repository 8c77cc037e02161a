"""Photometric outlier removal of the initial map (paper 004 section 3.4, after Kerl et al. 2013).

Each point's 8-pixel pattern is warped from the reference into every frame of the window; the residual is
r = I_j(warped) - psi I_ref with psi the ratio of the patch sums (004 eqs. 10-12: patch-mean normalization).
Per frame, a Student-t distribution with nu = 5 is fitted to the residuals: a MAD pre-filter keeps those
within 3 sigma_MAD (eq. 13), then the scale is iterated to convergence (eq. 14). Residuals beyond
2.571 sigma_k are discarded; an observation that loses more than half of its residuals is removed, and a
point left with fewer than two observing frames (the reference counts as one) leaves the map.

004 runs this filter between two photometric bundle adjustments (vo_core/init/photometric_ba.py); the
feature-based initializer chains them.
"""

from __future__ import annotations

import numpy as np

from vo_core.direct.config import PATTERN_8
from vo_core.direct.pyramid import ImagePyramid
from vo_core.init.config import PhotometricFilterConfig

PATTERN = np.array(PATTERN_8, float)
MAD_TO_SIGMA = 1.4826  # 004 eq. 13: c, the MAD of a unit normal distribution is 1 / 1.4826


def patch_residuals(
    reference: ImagePyramid, uv: np.ndarray, inverse_depths: np.ndarray, pyramid: ImagePyramid, T_cam_ref: np.ndarray
) -> np.ndarray:
    """(N, 8) residuals I_j(pi(T (x + pi^-1 delta))) - psi I(pi x + delta) (004 eqs. 11, 12); NaN outside."""
    camera = reference[0].camera
    pattern_uv = uv[:, None, :] + PATTERN  # the pattern shares the centre's inverse depth (DSO)
    rays = camera.unproject(pattern_uv.reshape(-1, 2)).reshape(len(uv), len(PATTERN), 3)
    points = rays @ T_cam_ref[:3, :3].T + inverse_depths[:, None, None] * T_cam_ref[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        warped = camera.project(points.reshape(-1, 3)).reshape(points.shape[:2] + (2,))
        warped[points[..., 2] <= 0] = np.nan
    target = pyramid[0].sample_intensity(warped[..., 0], warped[..., 1])
    source = reference[0].sample_intensity(pattern_uv[..., 0], pattern_uv[..., 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        psi = target.sum(axis=1, keepdims=True) / source.sum(axis=1, keepdims=True)
    return target - psi * source


def student_t_scale(residuals: np.ndarray, config: PhotometricFilterConfig) -> float:
    """Scale sigma of a Student-t (nu) fitted to ``residuals`` after the MAD pre-filter (004 eqs. 13, 14)."""
    r = residuals[np.isfinite(residuals)]
    if len(r) == 0:
        return np.nan
    sigma_mad = MAD_TO_SIGMA * np.median(np.abs(r - np.median(r)))
    r = r[np.abs(r) < config.mad_sigmas * sigma_mad] if sigma_mad > 0 else r
    variance = max(float(np.mean(r**2)), config.min_variance)
    nu = config.degrees_of_freedom
    for _ in range(config.max_iterations):
        updated = max(float(np.mean((nu + 1.0) / (nu + r**2 / variance) * r**2)), config.min_variance)
        converged = abs(updated - variance) <= config.tolerance * variance
        variance = updated
        if converged:
            break
    return float(np.sqrt(variance))


def photometric_inliers(
    reference: ImagePyramid, uv: np.ndarray, inverse_depths: np.ndarray,
    frames: list[tuple[ImagePyramid, np.ndarray]], config: PhotometricFilterConfig,
) -> tuple[np.ndarray, list[float]]:
    """(keep (N,) bool, fitted scale per frame): points observed consistently in enough frames."""
    observing = np.ones(len(uv), int)  # the reference frame
    scales = []
    for pyramid, T_cam_ref in frames:
        residuals = patch_residuals(reference, uv, inverse_depths, pyramid, T_cam_ref)
        sigma = student_t_scale(residuals, config)
        scales.append(sigma)
        discarded = ~(np.abs(residuals) < config.inlier_sigmas * sigma)  # NaN (outside the image) is discarded
        observing += discarded.sum(axis=1) <= len(PATTERN) // 2
    return observing >= config.min_observing_frames, scales
