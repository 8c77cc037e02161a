"""What the direct system asks of an initializer, and what an initializer hands it (DSO's CoarseInitializer is the
model). The direct half defines the contract; the initializers live on either side (DSO's coarse one in
vo_core/direct/, the feature-based one in vo_core/init/) and the system hands the odometry a factory
(vo_core/init/registry.py), which also makes the start check's independent witness (vo_core/init/epipolar_check.py:
it uses the feature half's ORB, which the direct half does not import).

The direct odometry feeds frames until ``track`` returns an ``InitializationResult``; when it has fed
``max_frames`` frames without one it starts over from the current frame. ``status`` says, for the events,
what the latest attempt found (model chosen, tracks kept, why it was rejected). A start that the odometry's check
discards after the hand-over (start_check.py) is an attempt that failed too: the factory is then told which
initializer failed, so that ``direct.initializer=auto`` can try the other one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from vo_core.direct.pyramid import ImagePyramid
from vo_core.geometry.camera import PinholeCamera


@dataclass
class InitializationResult:
    first_frame_index: int
    second_frame_index: int
    T_first_second: np.ndarray  # 4x4, pose of the second keyframe in the first (first is the world origin)
    points_uv: np.ndarray  # (N, 2) pixel coordinates in the first keyframe, level 0 of the rectified image
    inverse_depths: np.ndarray  # (N,) inverse depths in the first keyframe, scaled so their mean is 1 (DSO)
    inverse_depth_variances: np.ndarray | None = None  # (N,), where the initializer estimates them
    details: dict[str, Any] = field(default_factory=dict)  # model chosen, scores, counts: for the event
    # Where an initializer tracked features: the first K points are features, and these are their pixels in the
    # second keyframe (K, 2). The feature map starts from them (FDMO part 1); None for DSO's coarse initializer.
    tracks_second: np.ndarray | None = None


class Initializer(Protocol):
    name: str  # "features" or "coarse": for the events and the next attempt
    max_frames: int

    @property
    def started(self) -> bool: ...

    def set_first(self, frame_index: int, pyramid: ImagePyramid, exposure: float | None) -> None: ...

    def track(self, frame_index: int, pyramid: ImagePyramid, exposure: float | None) -> InitializationResult | None: ...

    def status(self) -> dict[str, Any]: ...


class StartWitness(Protocol):
    """What the start check (start_check.py) asks of its independent witness (vo_core/init/epipolar_check.py): what
    the images of a start's keyframes (each with ``frame_index``, ``image``, ``T_world_cam``) say of their poses."""

    def prepare(self, keyframes: list, camera: PinholeCamera) -> None:
        """Start measuring the keyframes' images, beside mapping."""

    def disagreement(self, keyframes: list, camera: PinholeCamera) -> tuple[str | None, dict]:
        """Why the keyframes' direct poses contradict their images, or None; and the measures for the event."""

    def close(self) -> None:
        """Stop measuring."""


class InitializerFactory(Protocol):
    """What the system hands the direct odometry for its starts."""

    def __call__(self, failed: str | None) -> Initializer:
        """A fresh initializer for every (re)initialization, given the name of the initializer whose attempt just
        failed (None when the last one succeeded, or at the first)."""

    def start_witness(self) -> StartWitness | None:
        """A fresh witness for the check of a new start; None where none runs."""
