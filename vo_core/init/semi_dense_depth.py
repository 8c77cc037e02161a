"""Inverse depths of DSO-selected pixels by epipolar line search and Gaussian fusion (paper 004 section 3.3,
after Engel, Sturm and Cremers, "Semi-dense visual odometry for a monocular camera", ICCV 2013).

Each pixel starts from a prior N(d_p, sigma_p^2) (the feature depths around it). In every later frame of the
window, the inverse-depth interval d_p +- k sigma_p is mapped onto the epipolar line, sampled about once per
pixel, and the sample with the lowest SSD over the 8-pixel pattern (patch means removed) is the match. The
observation d_o has the variance of 004 eq. 8,

    sigma_o^2 = alpha^2 (sigma_l^2 / <g, l>^2 + 2 sigma_i^2 / g_p^2),  alpha = delta_d / delta_lambda (eq. 9),

with g the normalized image gradient at the match, l the unit epipolar direction and g_p the gradient along
the line; prior and observation are fused as the product of Gaussians, frame after frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vo_core.direct.config import PATTERN_8
from vo_core.direct.pyramid import ImagePyramid
from vo_core.init.config import SemiDenseConfig

PATTERN = np.array(PATTERN_8, float)


@dataclass
class InverseDepths:
    mean: np.ndarray  # (N,)
    variance: np.ndarray  # (N,)
    updates: np.ndarray  # (N,) how many frames contributed an observation

    def subset(self, keep: np.ndarray) -> "InverseDepths":
        return InverseDepths(self.mean[keep], self.variance[keep], self.updates[keep])


def _project(K: np.ndarray, T_cam_ref: np.ndarray, rays: np.ndarray, inverse_depth: np.ndarray) -> np.ndarray:
    """Pixels of the reference rays at the given inverse depths: pi(R ray + t d) (the scaled point)."""
    p = rays @ T_cam_ref[:3, :3].T + inverse_depth[..., None] * T_cam_ref[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return (p[..., :2] / p[..., 2:]) * np.diag(K)[:2] + K[:2, 2]


def _centred(values: np.ndarray) -> np.ndarray:
    return values - values.mean(axis=-1, keepdims=True)


def search_and_fuse(
    reference: ImagePyramid, uv: np.ndarray, prior: InverseDepths, frames: list[tuple[ImagePyramid, np.ndarray]],
    config: SemiDenseConfig,
) -> InverseDepths:
    """Refine ``prior`` for pixels ``uv`` of ``reference`` with each (pyramid, T_cam_ref) of ``frames`` in turn."""
    K = reference[0].camera.K
    rays = reference[0].camera.unproject(uv)
    template = _centred(reference[0].sample_intensity(uv[:, None, 0] + PATTERN[:, 0], uv[:, None, 1] + PATTERN[:, 1]))
    mean, variance = prior.mean.copy(), prior.variance.copy()
    updates = prior.updates.copy()
    steps = np.linspace(-1.0, 1.0, config.samples)
    for pyramid, T_cam_ref in frames:
        sigma = np.sqrt(variance)
        low = np.maximum(mean - config.search_sigmas * sigma, config.min_inverse_depth)
        high = mean + config.search_sigmas * sigma
        centre, half = 0.5 * (low + high), 0.5 * (high - low)
        candidates = centre[:, None] + half[:, None] * steps  # (N, S) inverse depths along the interval
        pixels = _project(K, T_cam_ref, rays[:, None, :], candidates)  # (N, S, 2)
        patch_u = pixels[..., 0, None] + PATTERN[:, 0]
        patch_v = pixels[..., 1, None] + PATTERN[:, 1]
        samples = _centred(pyramid[0].sample_intensity(patch_u, patch_v))  # (N, S, 8)
        ssd = np.sum((samples - template[:, None, :]) ** 2, axis=-1)
        ssd = np.where(np.isfinite(ssd), ssd, np.inf)
        best = np.argmin(ssd, axis=1)
        rows = np.arange(len(uv))
        best_ssd = ssd[rows, best]
        segment = pixels[:, -1] - pixels[:, 0]
        length = np.linalg.norm(segment, axis=1)
        direction = segment / np.maximum(length, 1e-9)[:, None]
        match = pixels[rows, best]
        _, gu, gv = np.moveaxis(pyramid[0].sample(match[:, 0], match[:, 1]), -1, 0)
        gradient = np.stack([gu, gv], axis=1)
        along = np.abs(np.sum(gradient * direction, axis=1))  # g_p: gradient along the epipolar line
        cosine = along / np.maximum(np.linalg.norm(gradient, axis=1), 1e-9)  # <g, l> with g normalized
        alpha = (high - low) / np.maximum(length, 1e-9)  # eq. 9
        with np.errstate(divide="ignore", invalid="ignore"):
            observed_variance = alpha**2 * (
                config.line_sigma_px**2 / cosine**2 + 2.0 * config.intensity_variance / along**2
            )  # eq. 8 with eqs. 6, 7
        valid = (
            np.isfinite(best_ssd) & (best_ssd < config.max_ssd_per_pixel * len(PATTERN))
            & (length >= config.min_segment_px) & (best > 0) & (best < config.samples - 1)
            & np.isfinite(observed_variance) & (observed_variance > 0)
        )
        observed = candidates[rows, best]
        with np.errstate(divide="ignore", invalid="ignore"):  # invalid observations are masked out below
            total = variance + observed_variance
            fused_mean = (variance * observed + observed_variance * mean) / total
            fused_variance = variance * observed_variance / total
        mean = np.where(valid, fused_mean, mean)
        variance = np.where(valid, fused_variance, variance)
        updates = updates + valid
    return InverseDepths(mean, variance, updates)
