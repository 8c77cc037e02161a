"""Poses over time: a motion kept up at the same velocity (along its geodesic in SE(3)).

What both halves, the hybrid and the feature-only odometry predict from: ``extrapolate`` carries the motion of the
last two posed frames on to a later timestamp (ORB-SLAM2's motion model over the time that passed); DSO's tracking
guesses (vo_core/direct/motion_model.py) scale the last motion with ``scaled_motion``.
"""

from __future__ import annotations

import numpy as np

from vo_core.geometry.lie import se3_exp, se3_inverse, se3_log


def extrapolate(posed: list[tuple[float, np.ndarray]], timestamp: float) -> np.ndarray | None:
    """The pose at ``timestamp`` if the motion between the last two posed frames ((timestamp, T_world_cam), oldest
    first) goes on at the same velocity (ORB-SLAM2's motion model, over the time that passed); the last pose where
    one alone is known or the timestamps give no velocity, None where none is."""
    if not posed:
        return None
    t1, T_world_prev1 = posed[-1]
    if len(posed) < 2 or not posed[-2][0] < t1 < timestamp:
        return T_world_prev1
    t2, T_world_prev2 = posed[-2]
    T_prev2_prev1 = se3_inverse(T_world_prev2) @ T_world_prev1  # the last motion, assumed to repeat
    return T_world_prev1 @ scaled_motion(T_prev2_prev1, (timestamp - t1) / (t1 - t2))


def scaled_motion(T: np.ndarray, factor: float) -> np.ndarray:
    """The motion ``T`` at ``factor`` times its velocity (along its geodesic)."""
    return se3_exp(factor * se3_log(T))
