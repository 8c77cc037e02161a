"""Photometric bundle adjustment of the initial map (paper 004 section 3.4, eq. 11).

The poses of every frame of the initializer's window but the reference (the world origin, held fixed) and the
inverse depths of the handed-over points (hosted in the reference, 8-pixel pattern, Huber norm) are optimized
over the photometric residuals of the points in every other window frame.

The direct system's windowed bundle adjustment (vo_core/direct/window.py, WindowOptimizer) does exactly this,
so it runs here unchanged: each window frame becomes a lightweight keyframe (``WindowFrame``) and only the
reference hosts points; an empty marginalization prior leaves the oldest keyframe, the reference, as the gauge.
One photometric bundle adjustment in the project instead of two. Its per-keyframe affine brightness (a, b)
(DSO's model) does the job of 004's patch-mean normalization psi (eq. 12): both absorb brightness changes
between frames, DSO's with two parameters per frame instead of one ratio per patch.

Points the optimizer finds without inlier residuals (or with more outliers than inliers, DSO's
flagPointsForRemoval) leave the map (the report's ``kept`` says which: the reference hosts the window's only
points); the survivors keep their order.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from vo_core.direct.config import PATTERN_8, DirectConfig
from vo_core.direct.immature_point import host_pattern
from vo_core.direct.marginalization import MarginalizationPrior
from vo_core.direct.pyramid import ImagePyramid
from vo_core.direct.window import WindowOptimizer, WindowReport
from vo_core.geometry.camera import PinholeCamera
from vo_core.init.config import PhotometricBAConfig


@dataclass
class WindowFrame:
    """One frame of the initializer's window with the attributes WindowOptimizer reads of a keyframe."""

    frame_index: int
    pyramid: ImagePyramid
    exposure: float | None
    T_world_cam: np.ndarray
    affine: np.ndarray = field(default_factory=lambda: np.zeros(2))  # DSO's (a, b); both frames start at zero
    active_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # level-0 pixels of hosted points
    active_idepth: np.ndarray = field(default_factory=lambda: np.zeros(0))
    active_color: np.ndarray = field(default_factory=lambda: np.zeros((0, len(PATTERN_8)), np.float32))
    active_grad_sq: np.ndarray = field(default_factory=lambda: np.zeros((0, len(PATTERN_8)), np.float32))
    dropped_residuals: dict = field(default_factory=dict)  # as Keyframe.dropped_residuals
    energy_threshold: float | None = None  # as Keyframe.energy_threshold

    @property
    def camera(self) -> PinholeCamera:
        return self.pyramid[0].camera


@dataclass
class AdjustedMap:
    poses_world_cam: np.ndarray  # (F, 4, 4), the reference's the identity
    kept: np.ndarray  # (N,) bool over the input points: still in the map
    inverse_depths: np.ndarray  # (kept.sum(),) adjusted, in the order of the input points
    report: WindowReport


def make_photometric_ba(direct: DirectConfig, config: PhotometricBAConfig) -> WindowOptimizer:
    """The window optimizer as DirectOdometry builds it (its robust costs and LM settings), with the
    initializer's iteration count and stopping rule."""
    # The start's adjustment keeps DSO's fixed outlier threshold whatever the window's setting: its frames have no
    # history to adapt one from (DSO's own start, CoarseInitializer, uses a fixed one too).
    window = dataclasses.replace(direct.window, max_iterations=config.max_iterations,
                                 min_relative_decrease=config.min_relative_decrease, adaptive_outlier_threshold=False)
    return WindowOptimizer(
        window, direct.tracker.huber_threshold, direct.immature.outlier_threshold,
        direct.immature.outlier_sum_component,
    )


def photometric_bundle_adjustment(
    optimizer: WindowOptimizer, window: list[tuple[int, ImagePyramid, float | None]], poses_world_cam: np.ndarray,
    uv: np.ndarray, inverse_depths: np.ndarray,
) -> AdjustedMap:
    """Adjust the poses of the window frames (frame index, pyramid, exposure; the reference first) and the inverse
    depths of the reference's points ``uv``."""
    frames = [
        WindowFrame(index, pyramid, exposure, np.array(T, float))
        for (index, pyramid, exposure), T in zip(window, poses_world_cam)
    ]
    reference = frames[0]
    reference.active_uv = np.array(uv, float)
    reference.active_idepth = np.array(inverse_depths, float)
    reference.active_color, reference.active_grad_sq = host_pattern(reference.pyramid[0], reference.active_uv)
    report = optimizer.optimize(frames, MarginalizationPrior())
    return AdjustedMap(
        np.array([frame.T_world_cam for frame in frames]), report.kept, reference.active_idepth, report,
    )

