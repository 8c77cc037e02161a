"""When a tracked frame becomes a keyframe (DSO FullSystem::addActiveFrame, DSO paper section 3.1).

A new keyframe is needed when the field of view changed (mean squared optical flow of translation only,
rotation only and both, from the tracker), when the exposure/brightness changed (|log a| of the affine
transfer from the keyframe), or when the tracking residual doubled against the first frame tracked on this
keyframe. The flow weights are DSO's, relative to the image size (w + h).
"""

from __future__ import annotations

import numpy as np

from vo_core.direct.config import KeyframeConfig


def keyframe_score(
    flow: np.ndarray, brightness_factor: float, width: int, height: int, config: KeyframeConfig
) -> float:
    """DSO's weighted sum; a keyframe is due when it exceeds 1."""
    flow_t, flow_r, flow_rt = np.sqrt(np.maximum(flow, 0.0))
    size = width + height
    return config.global_weight * (
        config.max_shift_weight_t * flow_t / size
        + config.max_shift_weight_r * flow_r / size
        + config.max_shift_weight_rt * flow_rt / size
        + config.max_affine_weight * abs(np.log(brightness_factor))
    )


def needs_keyframe(
    flow: np.ndarray,
    brightness_factor: float,
    rmse: float,
    first_rmse: float,
    width: int,
    height: int,
    config: KeyframeConfig,
) -> bool:
    return (
        keyframe_score(flow, brightness_factor, width, height, config) > 1.0
        or config.rmse_growth * first_rmse < rmse
    )
