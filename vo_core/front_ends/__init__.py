"""Front ends: the methods that are whole pipelines of their own, beside FDMO's per-frame flow (vo_core/system.py),
behind one small protocol (``FrontEnd``): the KLT baseline (klt/, paper 003) and the feature-only odometry
(features.py: ORB-SLAM2's tracking and local mapping). ``Odometry`` passes their results through to its sinks.

They sit above the halves and geometry and below the system: a front end may use the feature half (features.py
does) and geometry, never the direct half's flow, the initializers or the system. What the system hands in is used
through its methods alone: the start witness that checks the feature odometry's new maps (vo_core/init's, as the
direct odometry's starts are checked).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np

from vo_core.errors import InputError
from vo_core.events import FrameResult, MapSnapshot
from vo_core.geometry.camera import PinholeCamera

if TYPE_CHECKING:
    from vo_core.config import Config  # vo_core.config reads klt/config.py: no import of it here at run time

IMPLEMENTED_METHODS = ("fdmo", "klt", "direct", "features")
DIRECT_METHODS = ("fdmo", "direct")  # the methods whose per-frame flow is Odometry.track's: no front end


class FrontEnd(Protocol):
    """A method that is a whole pipeline of its own. It never talks to sinks: it returns results, events
    included."""

    def process(self, frame) -> FrameResult: ...

    def map_snapshot(self) -> MapSnapshot: ...

    def final_keyframe_poses(self) -> dict[int, np.ndarray]:
        """The keyframes' poses as the run ends, by frame index: the final trajectory hangs each frame that names
        one (FrameResult.reference_keyframe) on it."""
        ...


def make_front_end(config: Config, camera: PinholeCamera,
                   start_witness: Callable[[], object | None] = lambda: None) -> FrontEnd | None:
    """The pipeline of a method that runs on its own (the KLT baseline, the feature-based odometry); None for the
    direct methods, whose per-frame flow is ``Odometry.track``'s. Methods that do not exist yet are refused, never
    faked. ``start_witness`` makes a fresh witness for each new map of the feature odometry (None: not checked)."""
    if config.method == "klt":
        from vo_core.front_ends.klt.pipeline import KltOdometry

        return KltOdometry(config.klt, camera, seed=config.seed)
    if config.method == "features":
        from vo_core.front_ends.features import FeatureOnlyOdometry

        return FeatureOnlyOdometry(config.features, camera, seed=config.seed, start_witness=start_witness)
    if config.method in DIRECT_METHODS:
        return None
    raise InputError(
        f"method '{config.method}' is not implemented yet (available: {', '.join(IMPLEMENTED_METHODS)})"
    )
