"""Settings of the direct half (DSO, Engel et al. 2017; FDMO section 4.2.1).

Defaults are DSO's, from src/util/settings.cpp unless another file is named; ``settings.cpp`` below means
JakobEngel/dso src/util/settings.cpp, ``CoarseTracker`` means src/FullSystem/CoarseTracker.cpp, and so on.
"""

from __future__ import annotations

from dataclasses import dataclass, field

# DSO's 8-pixel residual pattern (settings.cpp staticPattern[8], "8 for SSE efficiency"): (dx, dy) offsets.
PATTERN_8 = ((0, -2), (-1, -1), (1, -1), (-2, 0), (0, 0), (2, 0), (-1, 1), (0, 2))


@dataclass
class PyramidConfig:
    max_levels: int = 6  # settings.cpp PYR_LEVELS / pyrLevelsUsed
    min_pixels_coarsest: int = 5000  # globalCalib.cpp: halve while w*h > 5000 (640x480 -> 5 levels, 40x30)


@dataclass
class SelectorConfig:
    """DSO's PixelSelector (PixelSelector2.cpp)."""

    block_size: int = 32  # region of the adaptive gradient threshold (makeHists)
    hist_quantile: float = 0.5  # setting_minGradHistCut: the median of |grad| per block
    hist_add: float = 7.0  # setting_minGradHistAdd: threshold = median + 7
    hist_max_gradient: int = 48  # makeHists clamps |grad| to 48 in its histogram
    grad_downweight_per_level: float = 0.75  # setting_gradDownweightPerLevel
    initial_potential: int = 3  # PixelSelector::currentPotential
    max_resample_rounds: int = 1  # makeMaps(recursionsLeft = 1)
    resample_more_above: float = 1.25  # makeMaps: re-select with a smaller cell if wanted/have > 1.25
    resample_less_below: float = 0.25  # makeMaps: re-select with a larger cell if wanted/have < 0.25
    subsample_below: float = 0.95  # makeMaps: randomly thin out when wanted/have < 0.95
    border: int = 4  # select(): pixels closer than 4 to the border are never selected


@dataclass
class TrackerConfig:
    """Coarse tracker (CoarseTracker.cpp trackNewestCoarse) and its motion hypotheses (FullSystem.cpp)."""

    huber_threshold: float = 9.0  # setting_huberTH
    cutoff_threshold: float = 20.0  # setting_coarseCutoffTH: residuals above count as saturated
    max_saturated_ratio: float = 0.6  # trackNewestCoarse: double the cutoff while > 60% saturated
    max_cutoff_repeat: float = 50.0  # trackNewestCoarse: levelCutoffRepeat < 50
    max_iterations: tuple[int, ...] = (10, 20, 50, 50, 50, 50)  # maxIterations[] per level (finest first)
    initial_lambda: float = 0.01
    lambda_extrapolation_limit: float = 0.001
    lambda_decrease: float = 0.5
    lambda_increase: float = 4.0
    min_increment_norm: float = 1e-3  # stop the level when |inc| <= 1e-3
    abort_factor: float = 1.5  # give up when a level is 1.5x worse than the best hypothesis so far
    max_abs_a: float = 1.2  # trackNewestCoarse: |a| > 1.2 -> fail
    max_abs_b: float = 200.0  # trackNewestCoarse: |b| > 200 -> fail
    # HessianBlocks.h step scaling; DSO applies SCALE_XI_ROT = 1 to the first (translation) block of its
    # Sophus-ordered increment and SCALE_XI_TRANS = 0.5 to the rotation block: we keep that behaviour.
    scale_translation: float = 1.0
    scale_rotation: float = 0.5
    scale_a: float = 10.0  # SCALE_A
    scale_b: float = 1000.0  # SCALE_B
    retrack_threshold: float = 1.5  # setting_reTrackThreshold: accept a hypothesis within 1.5x last RMSE
    rotation_perturbation: float = 0.02  # trackNewCoarse: quaternion components +-0.02 (~2.3 degrees)
    # trackNewCoarse's 26 rotations of the constant motion, tried when the first guesses fall short. Live runs
    # (--realtime) leave them out (ours): each costs ~50 ms here, so a frame that needed all of them cost 1-2 s and
    # the frames missed meanwhile made the next one as hard; FDMO's feature map recovers such a frame in ~70 ms.
    rotation_hypotheses: bool = True
    # Ours: a guess whose coarsest level ends within this many pixels (median, at that level) of where an earlier
    # guess of the same frame ended is dropped: its finer levels would repeat that guess's. On teddy's hard frames
    # all 31 guesses ran every level (0.2-0.5 s a frame) though most met in a few coarse optima.
    same_coarse_optimum_px: float = 0.05
    # Ours: the image motion of the last tracked frames (how far the reference's points moved from one frame to the
    # next, median) that a frame's motion is compared with (divergence.py's sudden motion), and how many it needs.
    motion_history: int = 10
    min_motion_history: int = 3
    # Ours: after missed frames, the guess from the last motion kept up over the time that passed wins over a guess
    # whose final RMSE is lower by less than this share: photometry cannot tell such poses apart (periodic scenes).
    prediction_tie: float = 0.02
    # Ours: a frame further from the last tracked one than 1.5 times the interval between the last two comes after
    # missed frames (a driver's drop, --drop), one nearer than 1/1.5 of it after a jump: the motion hypotheses then
    # take the time into account (motion_model.py). Regular timestamps (jitter well under half an interval) never
    # trigger it.
    time_gap_factor: float = 1.5
    flow_sample_stride: int = 32  # calcRes: every 32nd point feeds the optical-flow indicators
    min_points_in_view: int = 20  # fewer valid residual terms than this at the finest level = failure


@dataclass
class KeyframeConfig:
    """FullSystem::addActiveFrame's keyframe decision; weights scale with (w + h) / (640 + 480)."""

    global_weight: float = 1.0  # setting_kfGlobalWeight
    max_shift_weight_t: float = 0.04 * (640 + 480)  # setting_maxShiftWeightT
    max_shift_weight_r: float = 0.0 * (640 + 480)  # setting_maxShiftWeightR
    max_shift_weight_rt: float = 0.02 * (640 + 480)  # setting_maxShiftWeightRT
    max_affine_weight: float = 2.0  # setting_maxAffineWeight
    rmse_growth: float = 2.0  # new keyframe when RMSE > 2 x the first RMSE against this keyframe
    # Which keyframes leave the window (FullSystem::flagFramesForMarginalization).
    min_frames: int = 5  # setting_minFrames
    max_frames: int = 7  # setting_maxFrames
    min_points_remaining: float = 0.05  # setting_minPointsRemaining: drop a keyframe with < 5% points in view
    max_log_affine_in_window: float = 0.7  # setting_maxLogAffFacInWindow
    min_frame_age: int = 1  # setting_minFrameAge


@dataclass
class ImmatureConfig:
    """ImmaturePoint::traceOn and the activation test of FullSystem::activatePointsMT."""

    density: float = 1500.0  # setting_desiredImmatureDensity: immature points per keyframe
    max_pixel_search: float = 0.027  # setting_maxPixSearch, times (w + h)
    min_trace_quality: float = 3.0  # setting_minTraceQuality
    min_trace_test_radius: int = 2  # setting_minTraceTestRadius
    trace_stepsize: float = 1.0  # setting_trace_stepsize
    trace_gn_iterations: int = 3  # setting_trace_GNIterations
    trace_gn_threshold: float = 0.1  # setting_trace_GNThreshold
    trace_extra_slack: float = 1.2  # setting_trace_extraSlackOnTH
    trace_slack_interval: float = 1.5  # setting_trace_slackInterval
    trace_min_improvement: float = 2.0  # setting_trace_minImprovementFactor
    huber_threshold: float = 9.0  # setting_huberTH (the tracker's too)
    outlier_threshold: float = 12.0 * 12.0  # setting_outlierTH (per pattern pixel)
    outlier_sum_component: float = 50.0 * 50.0  # setting_outlierTHSumComponent
    max_activation_interval: float = 8.0  # activatePointsMT: lastTracePixelInterval < 8
    min_scale_change: float = 0.75  # traceOn: OOB when the depth ratio leaves [0.75, 1.5]
    max_scale_change: float = 1.5
    max_steps: int = 100  # traceOn: errors[100]
    border: float = 4.0  # traceOn: projections must stay 4 px inside the image
    # Activation (FullSystem::optimizeImmaturePoint): a few Gauss-Newton steps on the inverse depth against
    # every other keyframe of the window before the point is used.
    activation_gn_iterations: int = 3  # setting_GNItsOnPointActivation
    min_idepth_hessian: float = 100.0  # setting_minIdepthH_act
    activation_min_observations: int = 1  # activatePointsMT: optimizeImmaturePoint(..., minObs = 1, ...)
    first_outlier_slack: float = 1000.0  # optimizeImmaturePoint: first linearization with outlierTHSlack 1000
    # DSO's optimizeImmaturePoint makes a new point's residuals only in the keyframes where its activation's ended in;
    # with this off, in every keyframe of the window (each judged at every optimization). Off by default: on the real
    # folders it holds fr1/desk's window through the sweep (the direct method 0.79 -> 0.33 m, DSO's error), but the
    # synthetic circuit tracks worse and its second loop bends its first round (BENCHMARKS.md, Tried and not kept).
    residuals_only_where_activated: bool = False


@dataclass
class InitializerConfig:
    """DSO's CoarseInitializer (CoarseInitializer.cpp trackFrame / setFirst)."""

    densities: tuple[float, ...] = (0.03, 0.05, 0.15, 0.5, 1.0, 1.0)  # setFirst: points per level / (w*h)
    max_iterations: tuple[int, ...] = (5, 5, 10, 30, 50, 50)  # trackFrame maxIterations[] (finest first)
    alpha_k: float = 2.5 * 2.5  # alphaK
    alpha_w: float = 150.0 * 150.0  # alphaW
    regularization_weight: float = 0.8  # regWeight: pull toward the neighbours' median
    coupling_weight: float = 1.0  # couplingWeight
    num_neighbours: int = 10  # makeNN: 10 nearest neighbours per level
    initial_lambda: float = 0.1
    min_increment: float = 1e-4  # eps
    max_fails: int = 2
    max_pixel_step: float = 0.25  # doStep: maxPixelStep
    idepth_range: tuple[float, float] = (1e-3, 50.0)  # doStep clamps
    frames_after_snap: int = 5  # trackFrame: snapped && frameID > snappedAt + 5
    outlier_energy_factor: float = 20.0  # calcResAndGS: energy > outlierTH * 20 -> not good
    selector_threshold_factor: float = 2.0  # setFirst: makeMaps(..., thFactor = 2)
    max_frames: int = 40  # give up on this first frame and restart after this many frames (ours)


@dataclass
class WindowConfig:
    """The windowed photometric bundle adjustment (FullSystem::optimize, EnergyFunctional; FDMO section 4)."""

    enabled: bool = True
    max_iterations: int = 6  # setting_maxOptIterations
    initial_lambda: float = 1e-1  # FullSystem::optimize: lambda = 1e-1
    lambda_decrease: float = 0.25  # an accepted step: lambda *= 0.25
    lambda_increase: float = 100.0  # a rejected step: lambda *= 1e2
    min_step: float = 1e-4  # stop when no keyframe parameter moves more than this (ours, like setting_thOptIterations)
    # Stop when an accepted step lowers the energy by less than this share of it (Ceres' function_tolerance).
    # 0: never; DSO's window runs its iterations (teddy's windows still gain 0.1-0.2 % an iteration at the 6th).
    min_relative_decrease: float = 0.0
    border: float = 2.0  # residuals whose pattern comes this close to the image edge are out
    min_inverse_depth: float = 1e-4  # inverse depths are kept positive (points at infinity are valid)
    idepth_regularization: float = 1e-6  # keeps a point without residuals solvable (its step is then zero)
    marginalization: bool = True  # keep leaving keyframes as a prior (DSO); False drops them
    marginalization_damping: float = 1e-6  # added to the leaving keyframe's block before its inverse
    # DSO's SOLVER_ORTHOGONALIZE_X_LATER: once the window has a marginalization prior, from this step of an
    # optimization on, the keyframe step loses its component along the window's scale (the photometric energy
    # does not see scale, and free steps drifted it by 40-80 % of the translation step on teddy). Before any
    # prior exists the scale stays free: fixing it there too lost KITTI at one seed of five. 0: never fixed.
    scale_fixed_from_step: int = 2
    # DSO's outlier threshold per keyframe (FrameHessian::frameEnergyTH, FullSystem::setNewFrameEnergyTH): a point's
    # residual is an outlier when its energy is above the larger of its host's and its target's threshold. The
    # newest keyframe's is (w c + (1 - w) f sqrt(e_q))^2, e_q the q-quantile of the energies of the residuals in it,
    # so blurred or badly lit keyframes keep their points; a new keyframe starts from the one before it's.
    # Off by default (the fixed setting_outlierTH per pattern pixel for every keyframe): on the real-data matrix it
    # gains at lower frame rates and on the drone clip, but FDMO's two loops lose the second loop on parking and KITTI
    # (BENCHMARKS.md, Tried and not kept).
    adaptive_outlier_threshold: bool = False
    energy_threshold_quantile: float = 0.7  # q: setting_frameEnergyTHN
    energy_threshold_factor: float = 1.5  # f: setting_frameEnergyTHFacMedian
    energy_threshold_constant: float = 26.0  # c: setNewFrameEnergyTH's 26
    energy_threshold_constant_weight: float = 0.5  # w: setting_frameEnergyTHConstWeight
    initial_energy_threshold: float = 8 * 8 * 8  # FrameHessian's frameEnergyTH: 8 * 8 * patternNum


@dataclass
class EpipolarCheckConfig:
    """The start check's independent witness (vo_core/init/epipolar_check.py): the essential matrix of ORB matches
    between the start's keyframes against the direct poses' motion. Measured in BENCHMARKS.md (Starts from many
    frames): right starts' qualified pairs disagree by at most 1.1 deg and 5.4 deg (KITTI, parking; one flipped pair
    on teddy), the wrong ones by 4.3-9.4 deg and 22-142 deg on every qualified pair. The share of the matches the
    direct motion explains (epipolar_check.py): right starts 88-100 % (fr1/desk's blurred ones 61-96 %), the drone
    clip's wrong start at half its frame rate 3-6 % on its pairs under 0.25 deg of parallax."""

    enabled: bool = True
    # ORB-SLAM2's initialization matching: twice the tracking's features (Tracking::MonocularInitialization's
    # mpIniORBextractor), a Hamming distance of at most TH_LOW and a nearest-to-second ratio of 0.9
    # (ORBmatcher::SearchForInitialization).
    num_features: int = 3000
    max_distance: int = 50
    ratio: float = 0.9
    ransac_threshold_px: float = 1.0  # ORB-SLAM's sigma of one pixel
    ransac_confidence: float = 0.999
    # A pair qualifies with this many matches triangulated in front of both views (ORB-SLAM2's
    # CreateInitialMapMonocular resets a start with fewer than 100 tracked points) ...
    min_points: int = 100
    min_parallax_deg: float = 1.0  # ... seen under this median parallax (ORB-SLAM Initialize(): 1 degree)
    # A qualified pair disagrees beyond these (the wrong start of the initializer benchmark: 3 deg, 30 deg).
    max_rotation_deg: float = 3.0
    max_direction_deg: float = 30.0
    # The start is refused where at least this many pairs disagree, and more than half of the qualified ones; or
    # where at least this many pairs with min_points matches are explained under min_explained by the direct motion
    # (FDMO's agreement between the two halves, fdmo.agreement: under half, the direct motion is not the images').
    min_disagreeing_pairs: int = 2
    min_explained: float = 0.5
    seed: int = 0  # of the RANSAC that tells a plane (two_view.estimate_models): the same input, the same verdict
    # Live input (``fdmo run --realtime``): the witness answers when it is done, beside mapping. Waited for on the
    # mapper it took 1-2 s on two cores, during which no keyframe was made and tracking went on against an ever
    # older one (teddy at 30 Hz: 56 frames, ATE 20x the offline run's). Offline it answers at the window
    # optimization after the start's last one, which keeps runs deterministic.
    beside_mapping: bool = False


@dataclass
class StartCheckConfig:
    """The check of a new start over the first window optimizations after the hand-over (start_check.py). DSO has
    none; ORB-SLAM2 has one (CreateInitialMapMonocular resets a start whose first global bundle adjustment leaves a
    negative median depth or fewer than 100 tracked points). These thresholds are ours, from the starts measured in
    BENCHMARKS.md (Initialization that proves itself)."""

    enabled: bool = True
    window_optimizations: int = 4  # optimizations after the hand-over's own that the start must pass
    # The first keyframe pair's parallax (baseline x median inverse depth of the initializer's points) may not
    # change by more than this factor from the hand-over: a right start is refined, a wrong one is rebuilt (right
    # coarse starts on KITTI change it by up to 2.0x, feature starts by 1.1x).
    max_parallax_change: float = 3.0
    # At the last optimization, the energy per residual in view over its lowest since the hand-over (the hand-over's
    # own excepted: two keyframes fit each other best): a wrong structure explains each new frame worse (a wrong
    # plane: 2.6x; right starts on the shared folders and the synthetic presets: up to 1.4x).
    max_energy_growth: float = 2.0
    min_inlier_ratio: float = 0.5  # at the last optimization: residuals in view that are not outliers
    epipolar: EpipolarCheckConfig = field(default_factory=EpipolarCheckConfig)  # at the last optimization


@dataclass
class ScaleWatchConfig:
    """The scale watch at every keyframe (scale_watch.py; ours: DSO reports nothing). The new keyframe's speed is
    compared with the median of the recent ones, and the window's mean inverse depth with the recent ones'. Depths
    change from one keyframe to the next by at most the step (about a tenth of the depth, DSO making keyframes when
    the optical flow passes a threshold), and a camera that slows down or turns leaves them as they were: a factor
    of 1.6 in both at once, in opposite directions, is reported as the map's scale changing. A warning only: near
    points leaving the window move the mean inverse depth alike (the drone clip), so no decision reads it."""

    recent_keyframes: int = 5  # the speeds and depths compared with (DSO's window: setting_minFrames)
    min_recent: int = 3  # fewer recent keyframes than this: nothing to compare with yet
    jump_factor: float = 1.6  # geometric mean of the speed's and the depths' change that is a jump
    min_depth_factor: float = 1.25  # the depths must move by at least this much too (a pure rotation moves none)


@dataclass
class DirectConfig:
    # "features": paper 004's feature-based initializer (vo_core/init/feature_initializer.py, settings in the
    # config's ``init`` section); "coarse": DSO's coarse one (vo_core/direct/coarse_initializer.py); "auto": the
    # feature one, and the coarse one for the next attempt after a feature start fails its checks (its own
    # acceptance rules for ``init.max_frames`` frames, or the start check). The default is "features"
    # (BENCHMARKS.md, Initializers): it starts at frame 3 instead of 7 and started right in 30 of 30 short runs from
    # spread start frames where the coarse one started wrong in 5; over whole runs from frame 0 the coarse one ends
    # 7-20 % more accurate by median ATE.
    initializer: str = "features"
    point_density: float = 2000.0  # setting_desiredPointDensity: active points used for tracking
    pyramid: PyramidConfig = field(default_factory=PyramidConfig)
    selector: SelectorConfig = field(default_factory=SelectorConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    immature: ImmatureConfig = field(default_factory=ImmatureConfig)
    coarse_init: InitializerConfig = field(default_factory=InitializerConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    start_check: StartCheckConfig = field(default_factory=StartCheckConfig)
    scale_watch: ScaleWatchConfig = field(default_factory=ScaleWatchConfig)
