"""Settings of the feature-based initializer (paper 004: Gladkova, "Feature-based Initialization for Monocular
Direct Visual Odometry", TU Munich).

Values the paper gives are cited by section; the two-view model selection follows ORB-SLAM (Mur-Artal et al.
2015, section IV, and ORB_SLAM2 src/Initializer.cc), cited as "ORB-SLAM". Values marked "ours" are not in
either source.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from vo_core.geometry.klt import CornerConfig, KltTrackerConfig
from vo_core.geometry.two_view import TwoViewConfig  # the section init.two_view


@dataclass
class FeatureTrackConfig:
    """Set-up routine (004 section 3.1): corners in the reference frame, KLT frame to frame, 1 -> 2 -> 1 check."""

    num_frames: int = 4  # 3.1: N = 4 frames (the reference and 3 tracked ones) before the first attempt
    min_median_flow_px: float = 1.0  # no two-view attempt while the tracks barely moved (ours): "no motion"
    corners: CornerConfig = field(default_factory=lambda: CornerConfig(max_corners=1000, min_distance=10.0))
    klt: KltTrackerConfig = field(default_factory=KltTrackerConfig)  # forward-backward error below 1 px


@dataclass
class GeometricBAConfig:
    """Geometric bundle adjustment over the window (004 section 3.2) and its outlier removal."""

    huber_px: float = 2.0  # Huber threshold of the reprojection residual (ours, as the KLT baseline's)
    max_iterations: int = 20  # Levenberg-Marquardt iterations per adjustment (ours)
    severe_outlier_px: float = 8.0  # 3.2: "severe" outliers, removed and re-adjusted until none (value ours)
    outlier_px: float = 3.0  # 3.2: afterwards "normal" outliers beyond 3 px are removed too


@dataclass
class SemiDenseConfig:
    """Semi-dense points (004 section 3.3): DSO-selected pixels, feature depths as prior, epipolar line search
    with SSD and Gaussian fusion of inverse depths frame to frame (Engel et al. 2013)."""

    enabled: bool = True  # False: the pixels keep the feature prior (004's comparison "v1" without 3.3)
    neighbours: int = 6  # feature points whose inverse depths form a pixel's prior (ours)
    max_neighbour_distance_px: float = 60.0  # pixels farther than this from every feature are not handed over (ours)
    prior_relative_sigma: float = 0.5  # prior sigma = 0.5 d + the spread of the neighbours' inverse depths (ours)
    search_sigmas: float = 2.0  # search d +- 2 sigma (LSD-SLAM's interval)
    samples: int = 48  # candidates along the epipolar segment (ours)
    min_inverse_depth: float = 1e-4  # the interval never reaches behind the camera
    line_sigma_px: float = 1.0  # 3.3 eq. 6: sigma_l, noise of the epipolar line position (ours: one pixel)
    intensity_variance: float = 4.0 * 10.0  # 3.3 eq. 7: sigma_i^2 = 4 camera_pixel_noise, camera_pixel_noise = 10
    max_ssd_per_pixel: float = 12.0 * 12.0  # DSO setting_outlierTH per pattern pixel: a worse best match is no match
    min_segment_px: float = 0.5  # a shorter segment carries no depth information


@dataclass
class PhotometricFilterConfig:
    """Student-t fit of the photometric residuals and outlier removal (004 section 3.4)."""

    enabled: bool = True
    degrees_of_freedom: float = 5.0  # 3.4: nu = 5 (Kerl et al. 2013)
    mad_sigmas: float = 3.0  # 3.4: residuals within 3 sigma_MAD feed the fit (eq. 13)
    inlier_sigmas: float = 2.571  # 3.4: |r| < 2.571 sigma_k
    min_observing_frames: int = 2  # 3.4: a point observed in fewer than two frames is removed
    max_iterations: int = 50  # eq. 14 iterated until convergence (ours: the cap and the tolerance)
    tolerance: float = 1e-4  # relative change of sigma^2
    min_variance: float = 1e-6  # keeps the iteration defined on noise-free (synthetic) images


@dataclass
class PhotometricBAConfig:
    """Photometric bundle adjustment of the initial map (004 section 3.4, eq. 11), before the Student-t filter
    and once more after it (004's "ORBInitializer v3"; v2 without the filter). It runs the direct system's window
    optimizer, whose Huber threshold, outlier threshold, gradient weights and Levenberg-Marquardt settings come
    from the ``direct`` section (DSO's values)."""

    enabled: bool = True
    max_iterations: int = 20  # DSO FullSystem::optimize: 20 iterations while the window holds two keyframes
    # ... but it stops once an accepted step gains less than this share of the energy (ours; WindowConfig's rule).
    # Teddy's start: the first adjustment is within 0.4 % of its 20th iteration's energy after the 5th, the one
    # after the filter within 0.03 % after the 3rd, and the 40 iterations were 165 ms of the frame that starts.
    min_relative_decrease: float = 1e-3


@dataclass
class ModelChoiceConfig:
    """How clearly one of the two models must win (ORB-SLAM selects the homography when R_H = S_H / (S_H + S_F)
    passes 0.40 in ORB_SLAM2's Initializer.cc and 0.45 in the paper, section IV). A ratio between the two is where
    neither model explains the views clearly better: a general scene seen with little parallax, which a homography
    fits nearly as well as the epipolar geometry. No model is chosen there; a later frame has more parallax."""

    ambiguous_ratio_h: tuple[float, float] = (0.40, 0.45)


@dataclass
class InitConfig:
    tracks: FeatureTrackConfig = field(default_factory=FeatureTrackConfig)
    two_view: TwoViewConfig = field(default_factory=TwoViewConfig)
    model_choice: ModelChoiceConfig = field(default_factory=ModelChoiceConfig)
    geometric_ba: GeometricBAConfig = field(default_factory=GeometricBAConfig)
    semi_dense: SemiDenseConfig = field(default_factory=SemiDenseConfig)
    photometric_filter: PhotometricFilterConfig = field(default_factory=PhotometricFilterConfig)
    photometric_ba: PhotometricBAConfig = field(default_factory=PhotometricBAConfig)
    max_frames: int = 30  # give up on a reference after this many frames without a model (ours)
