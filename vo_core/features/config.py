"""Settings of the feature half (FDMO sections 4.2.2, 4.3 and 4.4; ORB-SLAM2 where FDMO follows it).

``FDMO`` below means Younes, Asmar and Zelek 2019 (../shared/papers/000); ``ORB-SLAM2`` means
raulmur/ORB_SLAM2 (src/ORBextractor.cc, ORBmatcher.cc, LocalMapping.cc, Tracking.cc); ``DBoW2`` means
Galvez-Lopez and Tardos 2012 and its TemplatedVocabulary. Values marked "ours" are in neither.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class OrbConfig:
    """ORB features of a keyframe or of a frame to recover (FDMO 4.3: ORB on 8 levels, scale factor 1.2)."""

    num_features: int = 1500  # FDMO 4.3 / ORB-SLAM2 TUM and EuRoC settings: 1000-2000 per image
    scale_factor: float = 1.2  # FDMO eq. 6: Sf = 1.2
    num_levels: int = 8  # FDMO eq. 6: 0 <= n < 8
    fast_threshold: int = 20  # ORB-SLAM2 iniThFAST
    min_fast_threshold: int = 7  # ORB-SLAM2 minThFAST: used in cells where the first threshold finds nothing
    cell_size: int = 30  # ORB-SLAM2 ORBextractor W = 30: FAST runs per cell so that features spread
    edge_threshold: int = 19  # ORB-SLAM2 EDGE_THRESHOLD (the 31-px patch and its orientation disc fit inside)
    patch_size: int = 31  # ORB-SLAM2 PATCH_SIZE


@dataclass
class VocabularyConfig:
    """The bag-of-words vocabulary (DBoW2: hierarchical k-majority tree, tf-idf weights, L1 score)."""

    branching: int = 10  # DBoW2 k (ORB-SLAM2's ORBvoc: k = 10)
    depth: int = 4  # DBoW2 L: 10^4 words (ORBvoc has L = 6; a small vocabulary shipped in assets/, ours)
    direct_index_levels_up: int = 2  # ORB-SLAM2 ComputeBoW: features share a node 2 levels above the words
    path: str = ""  # "": the vocabulary bundled with the package (assets/vocabulary/)
    # DBoW2 HKmeansStep iterates until no descriptor changes cluster; a cap keeps training time bounded (ours).
    max_kmeans_iterations: int = 30
    # ORB-SLAM2 KeyFrameDatabase::DetectRelocalizationCandidates: a candidate shares at least 0.8 x the largest
    # number of words any keyframe shares with the query.
    min_common_words_ratio: float = 0.8


@dataclass
class MappingConfig:
    """The feature map grown at every direct keyframe (FDMO 4.3, Fig. 4): local map points searched in the new
    keyframe, epipolar matching with the local keyframes at their direct poses, triangulation, structure-only BA."""

    local_keyframes: int = 10  # FDMO 4.3: "local keyframes surrounding it"; ORB-SLAM2 LocalMapping: 10 (20 mono)
    projection_radius_px: float = 3.0  # ORB-SLAM2 SearchLocalPoints / Fuse: th = 3, times the level's scale
    projection_max_distance: int = 100  # ORB-SLAM2 ORBmatcher TH_HIGH
    projection_ratio: float = 0.8  # ORB-SLAM2 SearchByProjection's nnratio in the local map search
    epipolar_max_distance: int = 50  # ORB-SLAM2 SearchForTriangulation: TH_LOW
    epipolar_ratio: float = 0.6  # ORB-SLAM2 LocalMapping::CreateNewMapPoints: ORBmatcher(0.6, false)
    min_baseline_depth_ratio: float = 0.02  # FDMO 4.4: no triangulation below baseline / depth 0.02
    max_parallax_cos: float = 0.9998  # ORB-SLAM2 CreateNewMapPoints: rays closer than ~1.1 deg are not used
    chi2_two_dof: float = 5.991  # ORB-SLAM2: 95 % of a 2-DOF chi-square, on the level-normalized squared error
    scale_consistency: float = 1.5  # ORB-SLAM2 CreateNewMapPoints: ratioFactor = 1.5 * scale factor
    structure_iterations: int = 10  # FDMO 4.3: ten Gauss-Newton iterations of Eq. 3 per point
    # Ours, off by default (FDMO keeps the direct poses): the feature map keeps poses of its own. A new keyframe takes
    # the pose its check measured in the map (features/feature_odometry.py) and ORB-SLAM2's local mapping adjusts it
    # with its neighbours (local bundle adjustment, free poses), so that the map stays consistent where the direct
    # map drifts; a keyframe it overrules hands tracking to the features (features/following.py) until the direct map
    # restarts at one of their keyframes. TUM fr1/desk, stride 1, seeds 0-2: 0.020-0.030 m where FDMO gets 0.08-0.38;
    # but parking 0.033 m (0.0135), strides 2-3 bimodal, 1.7x the time (teddy): BENCHMARKS.md, Real data.
    own_poses: bool = False


@dataclass
class MaintenanceConfig:
    """Feature map maintenance (FDMO 4.4) and the covisibility graph (Strasdat et al. 2011, as ORB-SLAM2)."""

    check_keyframes: int = 7  # FDMO 4.4: a point is judged on the 7 keyframes after the one that created it
    min_found: int = 4  # FDMO 4.4: ... and must have been found in at least 4 of them
    redundancy: float = 0.9  # FDMO 4.4 (after ORB-SLAM2): 90 % of a keyframe's points seen elsewhere
    redundant_observers: int = 3  # ORB-SLAM2 KeyFrameCulling: "elsewhere" = in at least 3 other keyframes
    min_covisibility: int = 15  # ORB-SLAM2 KeyFrame::UpdateConnections: an edge needs 15 shared points


@dataclass
class RecoveryConfig:
    """Feature-based tracking recovery (FDMO 4.2.2, Fig. 3; ORB-SLAM2 Tracking::Relocalization)."""

    global_search: bool = True  # after the covisible keyframes fail, every keyframe of the map (ORB-SLAM2's way)
    max_candidates: int = 5  # keyframes tried per stage, best bag-of-words score first (ours)
    bow_ratio: float = 0.75  # ORB-SLAM2 Relocalization: ORBmatcher(0.75, true)
    bow_max_distance: int = 50  # ORB-SLAM2 SearchByBoW: TH_LOW
    min_bow_matches: int = 15  # ORB-SLAM2 Relocalization: candidates with fewer matches are discarded
    # FDMO 4.2.2 puts EPnP in RANSAC; OpenCV's classic RANSAC with it took 40-130 ms a candidate keyframe, its USAC
    # (P3P samples, local optimization) finds the same inliers in 4-6 ms (geometry/multiview.py): "epnp" gives the
    # paper's back.
    pnp_solver: str = "usac"
    ransac_iterations: int = 300  # ORB-SLAM2 PnPsolver::SetRansacParameters(0.99, 10, 300, ...)
    ransac_confidence: float = 0.99
    ransac_threshold_px: float = 2.45  # sqrt(5.991): ORB-SLAM2's chi-square test at level 0
    min_ransac_inliers: int = 10  # ORB-SLAM2 PnPsolver minInliers
    guided_radius_px: float = 2.5  # FDMO 4.2.2: a 5x5 search window around each projected point
    guided_max_distance: int = 100  # ORB-SLAM2 TH_HIGH
    guided_ratio: float = 0.9  # ORB-SLAM2 Relocalization's second SearchByProjection: ORBmatcher(0.9, true)
    min_inliers: int = 30  # FDMO 4.2.2: a recovered pose needs 30 inliers (ORB-SLAM2 asks 50)
    # ... and to find this share of the local map points in view (ours: right poses found 14-15 % on teddy, a
    # wrong one that gathered 49 inliers on far points 2.8 %; see Relocalizer.accepted).
    min_found_fraction: float = 0.05
    # A conclusive share of the local map points in view: a feature pose that found this share may contradict an
    # estimate of the system's own. A pose found by searching around that estimate (Relocalizer.recover's last
    # resort) needs it, since a search seeded by the pose it checks leans towards it; and only such a pose overrules a
    # converged direct pose (vo_core/fdmo/decide.py), below it too weakly anchored in the view to say the direct pose
    # is wrong. Ours: teddy, 30 frames dropped, a direct estimate 16 cm off gathered 93 inliers, 5.3 %; parking, 3.15
    # m dropped, candidates found 4.8 % (a global recovery at a look-alike place 30 frames back 5.6 %) against a right
    # direct pose; right recoveries: teddy 13-15 % (13 % after its 20-frame drop, rightly overruling), KITTI after 7 m
    # dropped 21 %.
    conclusive_found_fraction: float = 0.10
    # ... and, being a search at a known pose rather than a pose found from nothing, to the inliers ORB-SLAM2's
    # TrackWithMotionModel asks after its pose optimization (nmatchesMap >= 10), not the 30 of a recovery: after a
    # long forward drop few map points are still in front of the camera (KITTI, 11 m dropped: a right direct
    # estimate found 21 of 134, 16 %).
    min_inliers_around_estimate: int = 10
    # A frame with fewer ORB features than this share of OrbConfig.num_features is feature-deprived: when the
    # recovery fails there, the direct estimate is the only one left and is kept (FDMO's point: direct tracking
    # works where features do not). A textured frame the feature map does not recognize keeps it too, reported as
    # unverified, unless the search around it contradicts it (vo_core/fdmo/decide.py).
    feature_deprived_below: float = 0.2
    tracking_radius_px: float = 15.0  # ORB-SLAM2 TrackWithMotionModel: th = 15 (monocular)


@dataclass
class OrbInitializationConfig:
    """``--method features``: the map's start from two frames (ORB-SLAM2 Tracking::MonocularInitialization and
    CreateInitialMapMonocular); the two-view model selection itself is vo_core/geometry/two_view.py's."""

    min_features: int = 100  # ORB-SLAM2 MonocularInitialization: both frames need more than 100 keypoints
    features_factor: int = 2  # ORB-SLAM2 Tracking: mpIniORBextractor extracts 2 x nFeatures until the start
    min_matches: int = 100  # ORB-SLAM2: fewer matches with the reference and the next frame becomes the reference
    search_radius_px: float = 100.0  # ORB-SLAM2 SearchForInitialization(..., windowSize = 100)
    max_distance: int = 50  # ORB-SLAM2 SearchForInitialization: TH_LOW
    ratio: float = 0.9  # ORB-SLAM2 MonocularInitialization: ORBmatcher matcher(0.9, true)
    ba_iterations: int = 20  # ORB-SLAM2 CreateInitialMapMonocular: GlobalBundleAdjustemnt(mpMap, 20)
    min_map_points: int = 100  # ORB-SLAM2 CreateInitialMapMonocular: reset below 100 tracked map points
    # ORB-SLAM2 Tracking::Track: lost with at most 5 keyframes in the map, the system resets (a new start)
    reset_when_lost_below_keyframes: int = 6
    # Ours (ORB-SLAM2 keeps every start its two-view checks pass): a new map stays on probation until this many
    # keyframes after its first two are mapped; then the start witness (direct.start_check.epipolar's settings)
    # compares the epipolar geometry of its keyframes' ORB matches with their poses and a contradicted start is
    # taken back. Four, as the direct start check's window optimizations: with the two start keyframes, a map of
    # six, where losing it no longer resets it (reset_when_lost_below_keyframes).
    probation_keyframes: int = 4


@dataclass
class TrackingConfig:
    """``--method features``: ORB-SLAM2 Tracking (TrackWithMotionModel, TrackReferenceKeyFrame, TrackLocalMap,
    NeedNewKeyFrame), monocular values."""

    motion_radius_px: float = 15.0  # ORB-SLAM2 TrackWithMotionModel: th = 15 (monocular), times the level's scale
    motion_ratio: float = 0.9  # ORB-SLAM2 TrackWithMotionModel: ORBmatcher matcher(0.9, true)
    motion_min_matches: int = 20  # ORB-SLAM2: fewer than 20, search again with twice the radius, then give up
    min_inliers_after_pose: int = 10  # ORB-SLAM2 TrackWithMotionModel / TrackReferenceKeyFrame: nmatchesMap >= 10
    reference_ratio: float = 0.7  # ORB-SLAM2 TrackReferenceKeyFrame: ORBmatcher matcher(0.7, true)
    reference_min_matches: int = 15  # ORB-SLAM2 TrackReferenceKeyFrame: fewer than 15 BoW matches fail
    max_distance: int = 100  # ORB-SLAM2 SearchByProjection: TH_HIGH
    # ORB-SLAM2 SearchByProjection(Frame, MapPoints) via RadiusByViewingCos: 4 px (2.5 when seen almost head on)
    local_map_radius_px: float = 4.0
    local_map_ratio: float = 0.8  # ORB-SLAM2 SearchLocalPoints: ORBmatcher matcher(0.8)
    neighbours_per_keyframe: int = 10  # ORB-SLAM2 UpdateLocalKeyFrames: GetBestCovisibilityKeyFrames(10)
    max_local_keyframes: int = 80  # ORB-SLAM2 UpdateLocalKeyFrames: at most 80 local keyframes
    min_local_map_inliers: int = 30  # ORB-SLAM2 TrackLocalMap: 30 inliers ...
    min_local_map_inliers_relocalized: int = 50  # ... 50 within mMaxFrames of a relocalization
    # ORB-SLAM2 mMaxFrames = fps, one second of frames: within it of a relocalization no keyframe (once the map has
    # more keyframes than it has frames) and the local map needs the stricter inlier count. Counted in frames at
    # the camera's rate, which the odometry reads off the timestamps.
    relocalization_grace_s: float = 1.0
    # ORB-SLAM3 Tracking::Track, visual only: a map that relocalization has not found the camera in for more than 3 s
    # of camera time is left, and a new one begun (ORB-SLAM3's Atlas; a map with fewer than 10 keyframes is reset
    # instead). ORB-SLAM2 waited for the relocalization however long it took: on TUM fr1/desk two seeds of three lost
    # their map at frame 54 and posed nothing until frame 492. The new map begins where the camera was last posed, at
    # the old map's scene depth (as ORB-SLAM2's reset of a young map here).
    new_map_after_lost_s: float = 3.0
    # ORB-SLAM2 takes a keyframe only while its local mapping thread is idle (NeedNewKeyFrame, monocular: c1b, and
    # not accepted while busy); its local mapping, run at camera rate, is busy for a while after each keyframe.
    # Ours runs to the end between two frames, so this stands for that while: no keyframe sooner after the last.
    # Ours: 0 made nearly every frame a keyframe on teddy (55 of 58 at 1 fps, issue 19). A tracking that asks for a
    # keyframe interrupts ORB-SLAM2's local bundle adjustment (InterruptBA), so the while is its local mapping
    # without most of the adjustment: 0.1 s, three frames at 30 Hz. Measured on the real-data matrix (seed 0,
    # stride 1; BENCHMARKS.md): 0.2 lost fr1/desk at frame 49 (a keyframe every 6 frames could not keep up with its
    # sweeps: 45 of 613 posed) where 0.1 poses 609 at 0.022 m; KITTI 0.184 -> 0.155, parking 0.044 -> 0.032, teddy
    # 0.0079 -> 0.0089, the drone clip 0.32 -> 0.27 (its wrong start either way). 0.067 gave fr1/desk 0.028.
    local_mapping_busy_s: float = 0.1
    reference_ratio_keyframe: float = 0.9  # ORB-SLAM2 NeedNewKeyFrame: thRefRatio = 0.9 (monocular) ...
    reference_ratio_two_keyframes: float = 0.4  # ... 0.4 while the map has a single keyframe
    min_inliers_for_keyframe: int = 15  # ORB-SLAM2 NeedNewKeyFrame c2: mnMatchesInliers > 15
    min_observations: int = 3  # ORB-SLAM2 NeedNewKeyFrame: the reference's points seen by 3 keyframes count ...
    min_observations_two_keyframes: int = 2  # ... 2 while the map has at most 2 keyframes


@dataclass
class LocalMappingConfig:
    """``--method features``: ORB-SLAM2 LocalMapping (CreateNewMapPoints, MapPointCulling, SearchInNeighbors,
    Optimizer::LocalBundleAdjustment, KeyFrameCulling), monocular values."""

    triangulation_neighbours: int = 20  # ORB-SLAM2 CreateNewMapPoints: nn = 20 (monocular)
    min_baseline_depth_ratio: float = 0.01  # ORB-SLAM2 CreateNewMapPoints: baseline / median depth < 0.01 skipped
    fuse_neighbours: int = 20  # ORB-SLAM2 SearchInNeighbors: nn = 20 (monocular)
    min_found_ratio: float = 0.25  # ORB-SLAM2 MapPointCulling: found / visible < 0.25 culls a recent point
    # ORB-SLAM2 MapPointCulling: two keyframes after its creation a point seen by at most 2 (cnThObs) is culled;
    # after three it is no longer recent
    culling_keyframes: int = 2
    culling_max_observations: int = 2
    recent_keyframes: int = 3
    ba_first_iterations: int = 5  # ORB-SLAM2 LocalBundleAdjustment: optimize(5) ...
    ba_second_iterations: int = 10  # ... outliers out, then optimize(10)
    ba_chi2: float = 5.991  # ORB-SLAM2: chi2 95 % 2 DOF on the level-normalized error; Huber at its root
    # Keyframes held at least, the map's first among them (ours: ORB-SLAM2 holds keyframe 0 and the keyframes
    # outside the local ones, which in a small scene are none: one held keyframe leaves the scale free)
    min_held_keyframes: int = 2
    redundancy: float = 0.9  # ORB-SLAM2 KeyFrameCulling: 90 % of a keyframe's points seen elsewhere ...
    redundant_observers: int = 3  # ... by at least 3 other keyframes
    min_covisibility: int = 15  # ORB-SLAM2 KeyFrame::UpdateConnections: an edge needs 15 shared points


@dataclass
class FeatureOdometryConfig:
    """``--method features``: ORB-SLAM2's tracking and local mapping as odometry (no loop closing)."""

    initialization: OrbInitializationConfig = field(default_factory=OrbInitializationConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    local_mapping: LocalMappingConfig = field(default_factory=LocalMappingConfig)


@dataclass
class LoopClosingConfig:
    """Loop closure over the feature map (ORB-SLAM2 LoopClosing: DetectLoop, ComputeSim3, CorrectLoop; LDSO, Gao et
    al. 2018, for a direct odometry beside it). Off for FDMO as the paper's odometry; ``--loop-closure`` or the slam
    settings turn it on."""

    enabled: bool = False
    min_keyframes_between: int = 10  # ORB-SLAM2 DetectLoop: no loop within 10 keyframes of the map's start or last loop
    covisible_min_weight: int = 15  # ORB-SLAM2 KeyFrame::UpdateConnections: the neighbourhood a loop must leave
    # ORB-SLAM2 DetectLoopCandidates: a candidate's score accumulated over 10 covisibles; ours: also each side of a
    # loop (its end and these best covisibles) for the loop edges and the Sim(3)'s refinement on both neighbourhoods
    group_neighbours: int = 10
    group_score_ratio: float = 0.75  # ORB-SLAM2 DetectLoopCandidates: groups within 0.75 of the best accumulated score
    consistency: int = 3  # ORB-SLAM2 mnCovisibilityConsistencyTh: seen again by 3 consecutive keyframes after the first
    bow_max_distance: int = 50  # ORB-SLAM2 ComputeSim3: SearchByBoW with TH_LOW ...
    bow_ratio: float = 0.75  # ... and ORBmatcher(0.75, true)
    min_bow_matches: int = 20  # ORB-SLAM2 ComputeSim3: fewer than 20 matches, the candidate is dropped
    ransac_probability: float = 0.99  # ORB-SLAM2 Sim3Solver::SetRansacParameters(0.99, 20, 300)
    ransac_min_inliers: int = 20
    ransac_max_iterations: int = 300
    ransac_chi2: float = 9.21  # ORB-SLAM2 Sim3Solver: 99 % of a 2-DOF chi-square, on the level-normalized error
    refine_chi2: float = 10.0  # ORB-SLAM2 OptimizeSim3: th2 = 10 ...
    refine_iterations: int = 5  # ... 5 iterations, outliers out, 5 more (the same again on both neighbourhoods)
    min_refined_inliers: int = 20  # ORB-SLAM2 ComputeSim3: nInliers >= 20 after OptimizeSim3
    # ORB-SLAM2 ComputeSim3: SearchByProjection(pKF, mScw, ..., 10); the neighbourhoods' searches use it too
    projection_radius_px: float = 10.0
    min_loop_matches: int = 40  # ORB-SLAM2 ComputeSim3: the loop's neighbourhood matched 40 times, else refused
    essential_min_weight: int = 100  # ORB-SLAM2 OptimizeEssentialGraph: covisibility edges of 100 shared points
    pose_graph_iterations: int = 20  # ORB-SLAM2 OptimizeEssentialGraph: optimize(20)
    # ours: a correction is kept when the pose graph's cost (errors weighted by the Sim(3)'s and the shared points'
    # informations) is within this quantile of a chi-square of its degrees of freedom; the 99 % of ORB-SLAM2's
    # inlier tests (Sim3Solver's 9.21), applied to the whole graph
    pose_graph_chi2_probability: float = 0.99


@dataclass
class FeatureConfig:
    orb: OrbConfig = field(default_factory=OrbConfig)
    vocabulary: VocabularyConfig = field(default_factory=VocabularyConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    maintenance: MaintenanceConfig = field(default_factory=MaintenanceConfig)
    recovery: RecoveryConfig = field(default_factory=RecoveryConfig)
    odometry: FeatureOdometryConfig = field(default_factory=FeatureOdometryConfig)  # --method features
    loop_closing: LoopClosingConfig = field(default_factory=LoopClosingConfig)
