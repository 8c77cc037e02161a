"""What any initializer hands the direct system: the first keyframe pair and the points it found.

Both DSO's coarse initializer (vo_core/direct/coarse_initializer.py) and the feature-based one
(vo_core/init/feature_initializer.py) return this, so the direct system does not care which one ran.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class InitializationResult:
    first_frame_index: int
    second_frame_index: int
    T_first_second: np.ndarray  # 4x4, pose of the second keyframe in the first (first is the world origin)
    points_uv: np.ndarray  # (N, 2) pixel coordinates in the first keyframe, level 0 of the rectified image
    inverse_depths: np.ndarray  # (N,) inverse depths in the first keyframe, scaled so their mean is 1 (DSO)
    inverse_depth_variances: np.ndarray | None = None  # (N,), where the initializer estimates them
    details: dict[str, Any] = field(default_factory=dict)  # model chosen, scores, counts: for the event
