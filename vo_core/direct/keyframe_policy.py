"""When a tracked frame becomes a keyframe (DSO FullSystem::addActiveFrame, DSO paper section 3.1).

A new keyframe is needed when the field of view changed (mean squared optical flow of translation only,
rotation only and both, from the tracker), when the exposure/brightness changed (|log a| of the affine
transfer from the keyframe), or when the tracking residual doubled against the first frame tracked on this
keyframe. The flow weights are DSO's, relative to the image size (w + h).
"""

from __future__ import annotations

import numpy as np

from vo_core.compiled import kernel
from vo_core.direct.config import KeyframeConfig
from vo_core.direct.photometric_kernels import host_pixel_in_view


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


def keyframes_to_marginalize(
    keyframe_ids: np.ndarray,
    positions: np.ndarray,
    in_view_fraction: np.ndarray,
    log_brightness: np.ndarray,
    config: KeyframeConfig,
) -> list[int]:
    """FullSystem::flagFramesForMarginalization over the window before the new keyframe joins it.

    ``keyframe_ids`` count keyframes since initialization (0 = the first, which only leaves when out of
    view), ``positions`` are camera centres, ``in_view_fraction`` the share of each keyframe's points still
    in view and ``log_brightness`` |log| of the brightness factor to the newest frame. Returns window
    positions to drop: keyframes out of view or too differently exposed, then, while the window is full, the
    one with DSO's best distance score (far from the newest keyframe, close to the others)."""
    count = len(keyframe_ids)
    flagged: list[int] = []
    for i in range(count):
        lost = in_view_fraction[i] < config.min_points_remaining or log_brightness[i] > config.max_log_affine_in_window
        if lost and count - len(flagged) > config.min_frames:
            flagged.append(i)
    if count - len(flagged) >= config.max_frames:
        latest = keyframe_ids[-1]
        best_score, chosen = 1.0, None
        for i in range(count):
            if i in flagged or keyframe_ids[i] > latest - config.min_frame_age or keyframe_ids[i] == 0:
                continue
            others = [
                j for j in range(count) if j != i and keyframe_ids[j] <= latest - config.min_frame_age + 1
            ]
            distances = np.linalg.norm(positions[others] - positions[i], axis=1)
            score = -np.sum(1.0 / (1e-5 + distances)) * np.sqrt(np.linalg.norm(positions[-1] - positions[i]))
            if score < best_score:
                best_score, chosen = score, i
        if chosen is not None:
            flagged.append(chosen)
    return sorted(flagged)


@kernel
def fraction_in_view(uv, idepth, T_viewer_host, intrinsics, width, height):
    """Share of a host keyframe's points (pixels ``uv`` at inverse depths ``idepth``, at least 1e-6) that land in
    front of a viewer and inside its image (the pixel centres from 0 to width - 1). One compiled pass: in numpy it
    cost about 1 ms a keyframe over the window, on tracking's wait for the reference."""
    R, t = T_viewer_host[:3, :3], T_viewer_host[:3, 3]
    visible = 0
    for i in range(len(uv)):
        visible += host_pixel_in_view(R, t, intrinsics, uv[i, 0], uv[i, 1], max(idepth[i], 1e-6), width, height)[2]
    return visible / len(uv)
