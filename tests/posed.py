"""The trajectory of the frames a run posed, for tests that judge the FrameResults a run returned."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from vo_core.trajectory import Trajectory


def posed_trajectory(results: Iterable) -> Trajectory:
    """The frames among ``results`` (anything with ``timestamp`` and ``T_world_cam``) that got a pose, in order."""
    posed = [r for r in results if r.T_world_cam is not None]
    return Trajectory(np.array([r.timestamp for r in posed]), np.array([r.T_world_cam for r in posed]))
