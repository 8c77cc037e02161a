"""Feature-based tracking recovery (FDMO section 4.2.2, Fig. 3) and feature-based tracking.

``Relocalizer.recover`` follows Fig. 3, widened the way ORB-SLAM2's Tracking::Relocalization is:

    ORB features of the frame and their bag of words
    candidates: the keyframes covisible with the last direct keyframe, best bag-of-words score first (FDMO);
                if none gives a pose, every keyframe of the map (global: ORB-SLAM2's relocalization)
    per candidate: blind matching within vocabulary nodes against its map points (SearchByBoW)
                   EPnP in RANSAC for a first pose, motion-only bundle adjustment on its inliers
                   guided search in a 5x5 window around every projected point of the candidate and of its
                   covisible keyframes, motion-only bundle adjustment again
                   accepted with at least 30 inliers
    if no candidate gives a pose and the system has an estimate of its own (the direct alignment's): the local map
                   of the last keyframe searched around that estimate, as ORB-SLAM2 tracks every frame
                   (TrackWithMotionModel). A long forward jump changes the view too much for blind matching (KITTI,
                   7 m: 14 matches by bag of words) but not for a search around a good estimate (48 inliers).

``Relocalizer.track`` is feature-based tracking (Fig. 3's fallback until direct tracking is back): the same
guided search and pose refinement, seeded by a motion model instead of EPnP.

The recovered pose is a measurement of the feature map: what it does to the direct half (refine it by direct
alignment, restart the direct map there) is decided by the system.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from vo_core.features.config import FeatureConfig
from vo_core.features.feature_map import FeatureMap, project_points
from vo_core.features.matcher import match_by_bow, search_by_projection
from vo_core.features.orb import Features, OrbExtractor, level_sigma2s
from vo_core.features.vocabulary import Vocabulary
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.multiview import PnPConfig, estimate_pose, reprojection_errors
from vo_core.geometry.pose_only import refine_pose

LOCAL, GLOBAL, ESTIMATE, TRACKING = "local", "global", "estimate", "tracking"  # where a pose came from


@dataclass
class FrameFeatures:
    """A frame's ORB features and bag of words, extracted once however many searches use them."""

    features: Features
    bow: object
    nodes: np.ndarray
    ms: float


@dataclass
class PoseFromMap:
    """A pose measured by the feature map, with the matches that support it."""

    T_world_cam: np.ndarray
    point_ids: np.ndarray  # (K,) map points matched
    feature_ids: np.ndarray  # (K,) their features in the frame
    inlier: np.ndarray  # (K,) bool after the last pose refinement
    in_view: int = 0  # local map points the guided search looked for (in view at the pose it started from)

    @property
    def num_inliers(self) -> int:
        return int(self.inlier.sum())

    @property
    def found_fraction(self) -> float:
        """Inliers per local map point in view: a right pose finds a good share of what it should see."""
        return self.num_inliers / max(self.in_view, 1)


@dataclass
class RecoveryOutcome:
    succeeded: bool
    reason: str = ""
    stage: str = ""  # LOCAL or GLOBAL candidates, around the system's ESTIMATE, or TRACKING from a motion model
    keyframe: int | None = None  # the candidate keyframe that gave the pose
    candidates: dict[str, int] = field(default_factory=dict)  # stage -> candidates tried
    pose: PoseFromMap | None = None
    features: FrameFeatures | None = None
    feature_deprived: bool = False  # too few ORB features in the frame to say anything (RecoveryConfig)
    around_estimate: PoseFromMap | None = None  # the search around the system's estimate, where it ran and failed
    ms: float = 0.0

    def contradicts_estimate(self, config) -> bool:
        """Whether the failed search around the system's estimate says the camera is not there: the map expects
        at least a recovery's count of its points in view at that pose (``config.min_inliers``) and finds under a
        recovery's share of them (``config.min_found_fraction``). KITTI with 60 frames dropped: 5 of 287 (1.7 %)
        around a wrong direct pose; with 20 dropped, 5 of 49 (10 %) around a right one."""
        around = self.around_estimate
        return (around is not None and around.in_view >= config.min_inliers
                and around.found_fraction < config.min_found_fraction)

    @property
    def T_world_cam(self) -> np.ndarray | None:
        return self.pose.T_world_cam if self.pose is not None else None

    def details(self) -> dict:
        details = {"stage": self.stage or None, "keyframe": self.keyframe, "candidates": self.candidates,
                   "ms": round(self.ms, 1)}
        if self.pose is not None:
            details.update(matches=len(self.pose.inlier), inliers=self.pose.num_inliers,
                           found_fraction=round(self.pose.found_fraction, 3))
        if not self.succeeded:
            details["reason"] = self.reason
            details["feature_deprived"] = self.feature_deprived
            if self.around_estimate is not None:
                details["around_estimate"] = {"inliers": self.around_estimate.num_inliers,
                                              "in_view": self.around_estimate.in_view}
        return details


class Relocalizer:
    def __init__(self, config: FeatureConfig, camera: PinholeCamera, vocabulary: Vocabulary):
        self.config = config
        self.camera = camera
        self.vocabulary = vocabulary
        self.extractor = OrbExtractor(config.orb)
        self.sigma2 = level_sigma2s(config.orb)
        recovery = config.recovery
        self.pnp = PnPConfig(
            solver=recovery.pnp_solver, ransac_iterations=recovery.ransac_iterations, ransac_threshold_px=recovery.ransac_threshold_px,
            ransac_confidence=recovery.ransac_confidence, min_inliers=recovery.min_ransac_inliers,
            min_inlier_ratio=0.0,
        )

    def extract(self, image: np.ndarray) -> FrameFeatures:
        start = time.perf_counter()
        features = self.extractor.extract(image)
        bow, nodes = self.vocabulary.transform(features.descriptors)
        return FrameFeatures(features, bow, nodes, (time.perf_counter() - start) * 1000.0)

    # ------------------------------------------------------------------------------------ recovery

    def recover(self, feature_map: FeatureMap, image: np.ndarray, last_keyframe: int | None,
                T_world_estimate: np.ndarray | None = None) -> RecoveryOutcome:
        """A pose for the frame from the feature map, local candidates first, then (if allowed) global ones, then
        the search around ``T_world_estimate`` (the system's own estimate, if it has one)."""
        start = time.perf_counter()
        frame = self.extract(image)
        outcome = self._recover(feature_map, frame, last_keyframe)
        if not outcome.succeeded and T_world_estimate is not None and last_keyframe in feature_map.keyframes:
            around = self.track_from(feature_map, frame, T_world_estimate, last_keyframe, stage=ESTIMATE)
            if around.succeeded:
                around.candidates = outcome.candidates
                outcome = around
            else:
                outcome.around_estimate = around.pose
        outcome.features = frame
        deprived_below = self.config.recovery.feature_deprived_below * self.config.orb.num_features
        outcome.feature_deprived = len(frame.features) < deprived_below
        outcome.ms = (time.perf_counter() - start) * 1000.0
        return outcome

    def _recover(self, feature_map: FeatureMap, frame: FrameFeatures, last_keyframe: int | None) -> RecoveryOutcome:
        recovery = self.config.recovery
        if len(frame.features) < recovery.min_inliers:
            return RecoveryOutcome(False, f"{len(frame.features)} features in the frame, fewer than "
                                          f"{recovery.min_inliers}")
        tried: set[int] = set()
        candidates: dict[str, int] = {}
        stages = [(LOCAL, self._local_candidates(feature_map, last_keyframe))]
        if recovery.global_search:
            stages.append((GLOBAL, feature_map.searchable()))
        best: PoseFromMap | None = None
        for stage, allowed in stages:
            ranked = [k for k, _, _ in feature_map.index.query(frame.bow, restrict_to=allowed) if k not in tried]
            ranked = ranked[:recovery.max_candidates]
            candidates[stage] = len(ranked)
            for keyframe in ranked:
                tried.add(keyframe)
                pose = self._pose_from_candidate(feature_map, frame, keyframe)
                if pose is not None and self.accepted(pose):
                    return RecoveryOutcome(True, stage=stage, keyframe=keyframe, candidates=candidates, pose=pose)
                if pose is not None and (best is None or pose.num_inliers > best.num_inliers):
                    best = pose
        reason = "no candidate keyframe" if not tried else (
            f"no candidate reached {recovery.min_inliers} inliers and {recovery.min_found_fraction:.0%} of the map "
            f"points in view (best {best.num_inliers if best else 0} inliers, "
            f"{best.found_fraction if best else 0:.1%})")
        return RecoveryOutcome(False, reason, candidates=candidates, pose=best)

    def accepted(self, pose: PoseFromMap, stage: str = LOCAL) -> bool:
        """FDMO 4.2.2's 30 inliers, and a fair share of the local map points in view found: a wrong pose can
        gather 30 consistent matches on a few far, poorly triangulated points (teddy, 30 frames dropped at 100:
        49 inliers, 2.8 % of the points in view, 33 cm off), a right one finds 14-15 % there. A search around the
        system's estimate needs a larger share and fewer inliers (RecoveryConfig.*_around_estimate)."""
        recovery = self.config.recovery
        if stage == ESTIMATE:
            return (pose.num_inliers >= recovery.min_inliers_around_estimate
                    and pose.found_fraction >= recovery.conclusive_found_fraction)
        return pose.num_inliers >= recovery.min_inliers and pose.found_fraction >= recovery.min_found_fraction

    def _local_candidates(self, feature_map: FeatureMap, last_keyframe: int | None) -> set[int]:
        """FDMO 4.2.2: the keyframes connected to the last direct keyframe in the covisibility graph."""
        if last_keyframe is None or last_keyframe not in feature_map.keyframes:
            return set()
        return {last_keyframe, *feature_map.covisible_keyframes(last_keyframe, 1)}

    def _pose_from_candidate(self, feature_map: FeatureMap, frame: FrameFeatures, frame_index: int):
        """SearchByBoW against the candidate's map points, EPnP in RANSAC, then the guided search."""
        recovery = self.config.recovery
        keyframe = feature_map.keyframes[frame_index]
        has_point = keyframe.point_ids >= 0
        index_frame, index_kf = match_by_bow(
            frame.features, frame.nodes, keyframe.features.subset(has_point), keyframe.nodes[has_point],
            max_distance=recovery.bow_max_distance, ratio=recovery.bow_ratio,
        )
        point_ids = keyframe.point_ids[np.flatnonzero(has_point)[index_kf]]
        alive = feature_map.points.alive[point_ids]
        index_frame, point_ids = index_frame[alive], point_ids[alive]
        if len(point_ids) < recovery.min_bow_matches:
            return None
        uv = frame.features.uv[index_frame]
        estimate = estimate_pose(self.camera, feature_map.points.position[point_ids], uv, self.pnp)
        if estimate is None:
            return None
        pose = self._refined(feature_map, frame, point_ids[estimate.inliers], index_frame[estimate.inliers],
                             estimate.T_world_cam)
        local_map = self._local_map(feature_map, frame_index)
        return self._guided(feature_map, frame, local_map, pose, recovery.guided_radius_px)

    # ------------------------------------------------------------------------------------ tracking

    def track(self, feature_map: FeatureMap, image: np.ndarray, T_world_guess: np.ndarray,
              around_keyframe: int) -> RecoveryOutcome:
        """Feature-based tracking: the local map of ``around_keyframe`` searched around its projection at the
        motion model's guess (ORB-SLAM2 TrackWithMotionModel's wide window), then in the 5x5 window."""
        start = time.perf_counter()
        frame = self.extract(image)
        outcome = self.track_from(feature_map, frame, T_world_guess, around_keyframe, stage=TRACKING)
        outcome.features, outcome.ms = frame, (time.perf_counter() - start) * 1000.0
        return outcome

    def track_from(self, feature_map: FeatureMap, frame: FrameFeatures, T_world_guess: np.ndarray,
                   around_keyframe: int, stage: str = TRACKING) -> RecoveryOutcome:
        """The local map of ``around_keyframe`` searched around ``T_world_guess`` and the pose refined on what is
        found (the frame's features extracted already)."""
        recovery = self.config.recovery
        local_map = self._local_map(feature_map, around_keyframe)
        guess = PoseFromMap(T_world_guess, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, bool))
        pose = self._guided(feature_map, frame, local_map, guess, recovery.tracking_radius_px)
        if pose.num_inliers >= recovery.min_ransac_inliers:
            pose = self._guided(feature_map, frame, local_map, pose, recovery.guided_radius_px)
        succeeded = self.accepted(pose, stage)
        reason = "" if succeeded else f"{pose.num_inliers} inliers, {pose.found_fraction:.1%} of the points in view"
        return RecoveryOutcome(succeeded, reason, stage=stage, keyframe=around_keyframe, pose=pose)

    # ------------------------------------------------------------------------------------ shared steps

    def _local_map(self, feature_map: FeatureMap, frame_index: int) -> np.ndarray:
        """Points of a keyframe and of its covisible keyframes (κ^f of FDMO 4.2.2)."""
        neighbours = feature_map.covisible_keyframes(frame_index, 1, self.config.mapping.local_keyframes)
        return feature_map.points_of([frame_index, *neighbours])

    def _guided(self, feature_map: FeatureMap, frame: FrameFeatures, local_map: np.ndarray, pose: PoseFromMap,
                radius_px: float) -> PoseFromMap:
        """Every local map point not yet matched, projected at the current pose and searched within
        ``radius_px`` (times the level's scale); the pose refined on all matches."""
        recovery = self.config.recovery
        points = feature_map.points
        kept = pose.inlier
        matched_points, matched_features = pose.point_ids[kept], pose.feature_ids[kept]
        view = project_points(points, np.setdiff1d(local_map, matched_points), pose.T_world_cam, self.camera,
                              self.config.orb)
        available = np.ones(len(frame.features), bool)
        available[matched_features] = False
        found_points, found_features = search_by_projection(
            frame.features, view.uv, points.descriptor[view.point_ids], view.level, radius_px,
            max_distance=recovery.guided_max_distance, ratio=recovery.guided_ratio,
            scale_factor=self.config.orb.scale_factor, available=available,
        )
        point_ids = np.concatenate([matched_points, view.point_ids[found_points]])
        feature_ids = np.concatenate([matched_features, found_features])
        refined = self._refined(feature_map, frame, point_ids, feature_ids, pose.T_world_cam)
        refined.in_view = len(view.point_ids) + len(matched_points)
        return refined

    def _refined(self, feature_map, frame: FrameFeatures, point_ids, feature_ids, T_world_cam) -> PoseFromMap:
        """Motion-only bundle adjustment with Huber on the matches (ORB-SLAM2 Optimizer::PoseOptimization)."""
        refined = refine_pose(
            self.camera, T_world_cam, feature_map.points.position[point_ids], frame.features.uv[feature_ids],
            frame.features.level[feature_ids], scale_factor=self.config.orb.scale_factor,
        )
        return PoseFromMap(refined.T_world_cam, point_ids, feature_ids, refined.inlier)

    # ------------------------------------------------------------------------------------ checks

    def explained(self, feature_map: FeatureMap, pose: PoseFromMap, T_world_cam: np.ndarray,
                  frame: FrameFeatures) -> float:
        """Share of the pose's inlier matches that another pose (the direct one) also explains, by the same
        chi-square test: near 1 when both poses agree, near 0 when one of them is far off."""
        point_ids, feature_ids = pose.point_ids[pose.inlier], pose.feature_ids[pose.inlier]
        if len(point_ids) == 0:
            return 0.0
        error, depth = reprojection_errors(self.camera, T_world_cam, feature_map.points.position[point_ids],
                                           frame.features.uv[feature_ids])
        error2 = np.where(depth > 0, error**2, np.inf)
        bound = self.config.mapping.chi2_two_dof * self.sigma2[frame.features.level[feature_ids]]
        return float(np.mean(error2 <= bound))


