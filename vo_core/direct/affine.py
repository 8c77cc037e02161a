"""Affine brightness transfer between frames (DSO's AffLight, DSO paper Eq. 4).

Each frame i has (a_i, b_i) mapping its irradiance into a common scale; a pixel of frame i predicts the
intensity in frame j as I_j ~ factor * I_i + offset with (AffLight::fromToVecExposure)

    factor = (t_j / t_i) * exp(a_j - a_i),   offset = b_j - factor * b_i,

where t is the exposure time (1 when unknown).
"""

from __future__ import annotations

import numpy as np


def exposure_ratio(exposure_from: float | None, exposure_to: float | None) -> float:
    """t_j / t_i, 1 where either exposure time is unknown."""
    return exposure_to / exposure_from if exposure_from and exposure_to else 1.0


def relative_affine(
    exposure_from: float | None, exposure_to: float | None, ab_from: np.ndarray, ab_to: np.ndarray
) -> tuple[float, float]:
    """(factor, offset) predicting intensities of frame ``to`` from frame ``from``."""
    with np.errstate(over="ignore"):  # a diverging optimizer may propose huge a: inf is rejected upstream
        factor = exposure_ratio(exposure_from, exposure_to) * float(np.exp(ab_to[0] - ab_from[0]))
    return factor, float(ab_to[1] - factor * ab_from[1])


def relative_affines(exposures: list[float | None], affines: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``relative_affine`` for every pair of frames at once: (K, K) factors and offsets, indexed [from, to]."""
    known = np.array([float(e) if e else np.nan for e in exposures])  # unknown: the ratio is 1
    ratio = np.nan_to_num(known[None, :] / known[:, None], nan=1.0)
    a, b = affines[:, 0], affines[:, 1]
    with np.errstate(over="ignore"):
        factor = ratio * np.exp(a[None, :] - a[:, None])
    return factor, b[None, :] - factor * b[:, None]
