"""Settings of the classic KLT baseline (paper 003: Oort Alonso et al., "A monocular visual odometry pipeline
implementation", VAMR mini-project, UZH).

Where the paper gives a value it is cited by section or table; where it only says "tuned" the default is
ours, chosen on the shared sequences and stated as such. Per-dataset tuning lives in configs/klt/*.yaml, as
the paper keeps one configuration file per dataset (section II-A.1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from vo_core.geometry.bundle_adjustment import BundleAdjustmentSettings
from vo_core.geometry.klt import CornerConfig, KltTrackerConfig  # the sections klt.corners, klt.tracker
from vo_core.geometry.multiview import PnPConfig
from vo_core.geometry.two_view import TwoViewConfig


@dataclass
class BootstrapConfig:
    """Two-view initialization (paper II-A.1 and II-A.3).

    The relative pose comes from the project's one two-view reconstruction (vo_core/geometry/two_view.py:
    homography or fundamental matrix chosen as ORB-SLAM does), where the paper runs an essential-matrix MSAC;
    ``two_view`` holds its settings."""

    min_frame_gap: int = 2  # II-A.1: the first and third frames are the bootstrap pair
    max_frame_gap: int = 30  # give up on this first frame after this many frames and start again
    min_tracks: int = 50  # fewer surviving KLT tracks than this: restart from the current frame
    min_median_parallax_deg: float = 1.0  # retry with a later frame while the median bearing angle is below
    min_inlier_ratio: float = 0.5  # fewer model inliers than this share of the tracks: retry
    min_landmarks: int = 40  # fewer triangulated landmarks than this: retry with a later frame
    two_view: TwoViewConfig = field(default_factory=TwoViewConfig)


def _paper_003_pose() -> PnPConfig:
    """3D-2D pose (paper II-B.1: P3P inside MSAC, estimateWorldCameraPose), refined on the inliers."""
    return PnPConfig(
        solver="p3p",  # II-B.1: P3P
        ransac_iterations=200,
        ransac_threshold_px=2.0,  # reprojection error of an inlier
        ransac_confidence=0.999,
        min_inliers=30,  # fewer inliers than this is a tracking failure (re-bootstrap)
        min_inlier_ratio=0.3,  # a tracking failure too, when fewer than this share of landmarks agree
    )


@dataclass
class TriangulationConfig:
    """Candidate promotion (paper II-B.2)."""

    min_bearing_angle_deg: float = 2.0  # II-B.2: alpha threshold "chosen after tuning" (value not given)
    max_reprojection_px: float = 2.0  # a new landmark must reproject this well into both views
    min_depth: float = 1e-3  # in map units; cheirality with a margin against points at the camera centre


@dataclass
class KeyframeConfig:
    """When the current frame becomes a keyframe (not in the paper: needed by the windowed bundle adjustment).

    New corners are detected and candidates triangulated at keyframes, so that every landmark has two
    keyframe observations for the bundle adjustment to use."""

    min_median_parallax_deg: float = 1.0  # median bearing angle of the landmarks since the last keyframe
    min_tracked_ratio: float = 0.7  # fewer tracked landmarks than this share of those at the last keyframe
    max_frame_gap: int = 10  # at the latest every this many frames, to keep renewing corners


@dataclass
class BundleAdjustmentConfig(BundleAdjustmentSettings):
    """Sliding-window bundle adjustment (paper II-C: discussed, not implemented; the first poses are held).

    The solver's own settings are inherited: huber_px (2 px, Huber threshold of the reprojection residuals) and
    max_iterations (10 Levenberg-Marquardt iterations, each a solve of the reduced camera system)."""

    window_keyframes: int = 7  # keyframes optimized together (DSO keeps 5-7)
    fixed_keyframes: int = 2  # the oldest ones are held: gauge freedom and scale (paper II-C)
    max_outlier_px: float = 4.0  # landmarks reprojecting worse than this after the adjustment are culled


@dataclass
class KltConfig:
    corners: CornerConfig = field(default_factory=CornerConfig)
    tracker: KltTrackerConfig = field(default_factory=KltTrackerConfig)
    bootstrap: BootstrapConfig = field(default_factory=BootstrapConfig)
    pose: PnPConfig = field(default_factory=_paper_003_pose)  # the YAML section klt.pose
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    window_ba: bool = True  # run the sliding-window bundle adjustment at each keyframe
    ba: BundleAdjustmentConfig = field(default_factory=BundleAdjustmentConfig)
