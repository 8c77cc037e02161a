"""Tracking of ``--method features``: ORB-SLAM2's Tracking thread for a monocular camera, map given.

Per frame, while tracking (``FeatureTracker.track``):

    with a velocity: the last frame's points projected at the constant-velocity pose and searched in a window
        of 15 px (twice that when fewer than 20 are found), pose-only optimization      TrackWithMotionModel
    without one, or when that fails: bag-of-words matches with the reference keyframe, pose-only optimization
        from the last pose                                                              TrackReferenceKeyFrame
    then the local map: the keyframes that see the frame's points and their best covisible neighbours, their
        points projected and searched, pose-only optimization; 30 inliers (50 just after a relocalization)
                                                                                        TrackLocalMap
    lost: the global bag-of-words relocalization of vo_core/features/recovery.py, then the local map
                                                                                        Relocalization

``tracks_few_reference_points`` is NeedNewKeyFrame's tracked-points condition; its timing conditions (local
mapping idle, a relocalization just before) are the odometry's (vo_core/front_ends/features.py), which knows the clock.

The pose-only optimization is vo_core/geometry/pose_only.py (ORB-SLAM2 PoseOptimization); its outliers leave the
frame's matches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vo_core.features.config import FeatureConfig
from vo_core.features.feature_map import NO_POINT, Covisibility, FeatureMap, project_points
from vo_core.features.matcher import TH_LOW, match_by_bow, orientation_consistent, search_by_projection
from vo_core.features.recovery import FrameFeatures, RecoveryOutcome, Relocalizer
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.pose_only import refine_pose

MOTION, REFERENCE, RELOCALIZATION = "motion_model", "reference_keyframe", "relocalization"


@dataclass
class TrackedFrame:
    """A frame with its pose and, per ORB feature, the map point it was matched to (ORB-SLAM2 Frame)."""

    frame_index: int
    timestamp: float
    features: FrameFeatures
    T_world_cam: np.ndarray | None = None
    point_ids: np.ndarray | None = None  # (N,) int64, NO_POINT where unmatched
    reference_keyframe: int | None = None  # frame index of the keyframe sharing the most points

    def __post_init__(self) -> None:
        if self.point_ids is None:
            self.point_ids = np.full(len(self.features.features), NO_POINT, np.int64)

    @property
    def matched(self) -> np.ndarray:
        return np.flatnonzero(self.point_ids >= 0)

    def clear(self) -> None:
        self.point_ids[:] = NO_POINT


@dataclass
class TrackingOutcome:
    succeeded: bool
    stage: str = ""  # MOTION, REFERENCE or RELOCALIZATION: how the first pose was found
    inliers: int = 0  # after the local map
    reason: str = ""
    visible_points: np.ndarray | None = None  # local map points in view (ORB-SLAM2 IncreaseVisible)
    relocalization: RecoveryOutcome | None = None


class FeatureTracker:
    def __init__(self, config: FeatureConfig, camera: PinholeCamera, relocalizer: Relocalizer):
        self.config = config
        self.tracking = config.odometry.tracking
        self.camera = camera
        self.relocalizer = relocalizer

    # ------------------------------------------------------------------------------------ the state machine

    def track(self, feature_map: FeatureMap, frame: TrackedFrame, last: TrackedFrame,
              T_predicted: np.ndarray | None, relocalized_recently: bool) -> TrackingOutcome:
        """A pose for ``frame`` from the last frame's pose (and velocity, when ``T_predicted`` is given)."""
        stage = MOTION
        found = T_predicted is not None and self.with_motion_model(feature_map, frame, last, T_predicted)
        if not found:
            stage = REFERENCE
            found = self.with_reference_keyframe(feature_map, frame, last)
        if not found:
            return TrackingOutcome(False, stage, reason="neither the motion model nor the reference keyframe gave "
                                                        f"{self.tracking.min_inliers_after_pose} inliers")
        return self.with_local_map(feature_map, frame, stage, relocalized_recently)

    def relocalize(self, feature_map: FeatureMap, image: np.ndarray, frame_index: int,
                   timestamp: float) -> tuple[TrackedFrame, TrackingOutcome]:
        """ORB-SLAM2 Relocalization: every keyframe a bag-of-words candidate (recovery.py's global stage), then the
        local map with the stricter inlier count."""
        outcome = self.relocalizer.recover(feature_map, image, None)
        frame = TrackedFrame(frame_index, timestamp, outcome.features)
        if not outcome.succeeded:
            return frame, TrackingOutcome(False, RELOCALIZATION, reason=outcome.reason, relocalization=outcome)
        pose = outcome.pose
        frame.T_world_cam = pose.T_world_cam
        frame.point_ids[pose.feature_ids[pose.inlier]] = pose.point_ids[pose.inlier]
        tracked = self.with_local_map(feature_map, frame, RELOCALIZATION, relocalized_recently=True)
        tracked.relocalization = outcome
        return frame, tracked

    # ------------------------------------------------------------------------------------ the three trackings

    def with_motion_model(self, feature_map: FeatureMap, frame: TrackedFrame, last: TrackedFrame,
                          T_predicted: np.ndarray) -> bool:
        """ORB-SLAM2 TrackWithMotionModel: the last frame's points searched around their projections."""
        tracking = self.tracking
        frame.T_world_cam = T_predicted
        for radius in (tracking.motion_radius_px, 2.0 * tracking.motion_radius_px):
            frame.clear()
            if self._search_last_frame(feature_map, frame, last, radius) >= tracking.motion_min_matches:
                break
        else:
            return False
        return self.optimize_pose(feature_map, frame) >= tracking.min_inliers_after_pose

    def with_reference_keyframe(self, feature_map: FeatureMap, frame: TrackedFrame, last: TrackedFrame) -> bool:
        """ORB-SLAM2 TrackReferenceKeyFrame: bag-of-words matches with the reference keyframe's points, the pose
        optimized from the last frame's."""
        reference = feature_map.keyframes.get(last.reference_keyframe) or feature_map.newest()
        has_point = reference.point_ids >= 0
        index_frame, index_reference = match_by_bow(
            frame.features.features, frame.features.nodes, reference.features.subset(has_point),
            reference.nodes[has_point], max_distance=TH_LOW, ratio=self.tracking.reference_ratio,
        )
        point_ids = reference.point_ids[np.flatnonzero(has_point)[index_reference]]
        alive = feature_map.points.alive[point_ids]
        if alive.sum() < self.tracking.reference_min_matches:
            return False
        frame.clear()
        frame.point_ids[index_frame[alive]] = point_ids[alive]
        frame.T_world_cam = last.T_world_cam
        return self.optimize_pose(feature_map, frame) >= self.tracking.min_inliers_after_pose

    def with_local_map(self, feature_map: FeatureMap, frame: TrackedFrame, stage: str,
                       relocalized_recently: bool) -> TrackingOutcome:
        """ORB-SLAM2 TrackLocalMap: local keyframes and points, the points in view searched, the pose optimized."""
        tracking = self.tracking
        local_keyframes = self.local_keyframes(feature_map.covisibility_graph(), frame)
        frame.reference_keyframe = local_keyframes[0] if local_keyframes else frame.reference_keyframe
        local_points = feature_map.points_of(local_keyframes)
        view = project_points(feature_map.points, np.setdiff1d(local_points, frame.point_ids), frame.T_world_cam,
                              self.camera, self.config.orb)
        # Just after a relocalization the pose is rougher: ORB-SLAM2 widens the search (th = 5).
        radius = tracking.local_map_radius_px * (5.0 if stage == RELOCALIZATION else 1.0)
        found_points, found_features = search_by_projection(
            frame.features.features, view.uv, feature_map.points.descriptor[view.point_ids], view.level, radius,
            max_distance=tracking.max_distance, ratio=tracking.local_map_ratio,
            scale_factor=self.config.orb.scale_factor, available=frame.point_ids == NO_POINT,
        )
        frame.point_ids[found_features] = view.point_ids[found_points]
        inliers = self.optimize_pose(feature_map, frame)
        needed = tracking.min_local_map_inliers_relocalized if relocalized_recently else tracking.min_local_map_inliers
        visible = np.concatenate([view.point_ids, frame.point_ids[frame.matched]])
        if inliers < needed:
            return TrackingOutcome(False, stage, inliers, f"{inliers} inliers in the local map, fewer than {needed}",
                                   visible_points=visible)
        return TrackingOutcome(True, stage, inliers, visible_points=visible)

    # ------------------------------------------------------------------------------------ shared steps

    def _search_last_frame(self, feature_map: FeatureMap, frame: TrackedFrame, last: TrackedFrame,
                           radius_px: float) -> int:
        """The last frame's live points projected at the frame's pose, each searched within the radius at the
        level it was found at in the last frame (ORB-SLAM2 SearchByProjection(Frame, Frame)), rotations checked."""
        observed = last.matched
        observed = observed[feature_map.points.alive[last.point_ids[observed]]]
        view = project_points(feature_map.points, last.point_ids[observed], frame.T_world_cam, self.camera,
                              self.config.orb)
        row_of = {point: row for row, point in zip(observed, last.point_ids[observed])}
        rows = np.array([row_of[point] for point in view.point_ids], np.int64)
        if len(rows) == 0:
            return 0
        found_points, found_features = search_by_projection(
            frame.features.features, view.uv, last.features.features.descriptors[rows],
            last.features.features.level[rows], radius_px, max_distance=self.tracking.max_distance,
            ratio=self.tracking.motion_ratio, scale_factor=self.config.orb.scale_factor,
        )
        consistent = orientation_consistent(last.features.features.angle[rows[found_points]],
                                            frame.features.features.angle[found_features])
        frame.point_ids[found_features[consistent]] = view.point_ids[found_points[consistent]]
        return int(consistent.sum())

    def optimize_pose(self, feature_map: FeatureMap, frame: TrackedFrame) -> int:
        """ORB-SLAM2 PoseOptimization on the frame's matches; outliers leave them. Returns the inliers."""
        matched = frame.matched
        if len(matched) == 0:
            return 0
        features = frame.features.features
        refined = refine_pose(
            self.camera, frame.T_world_cam, feature_map.points.position[frame.point_ids[matched]],
            features.uv[matched], features.level[matched], scale_factor=self.config.orb.scale_factor,
        )
        frame.T_world_cam = refined.T_world_cam
        frame.point_ids[matched[~refined.inlier]] = NO_POINT
        return int(refined.inlier.sum())

    def local_keyframes(self, graph: Covisibility, frame: TrackedFrame) -> list[int]:
        """ORB-SLAM2 UpdateLocalKeyFrames: the keyframes that see the frame's points, most shared first (the
        first is the frame's reference keyframe), then the best covisible neighbours of each, up to 80."""
        tracking = self.tracking
        table = graph.table
        sees = np.isin(table.point, frame.point_ids[frame.matched])
        keyframes, shared = np.unique(table.keyframe[sees], return_counts=True)
        chosen = [int(k) for k in keyframes[np.lexsort((-keyframes, -shared))]]
        for keyframe in list(chosen):
            if len(chosen) >= tracking.max_local_keyframes:
                break
            for neighbour in graph.covisible_keyframes(keyframe, 1, tracking.neighbours_per_keyframe):
                if neighbour not in chosen:
                    chosen.append(neighbour)
                    break  # ORB-SLAM2 takes the first neighbour not yet chosen
        return chosen[:tracking.max_local_keyframes]

    def tracks_few_reference_points(self, feature_map: FeatureMap, frame: TrackedFrame, inliers: int) -> bool:
        """ORB-SLAM2 NeedNewKeyFrame's c2 (monocular): the frame tracks fewer than 90 % of the points its reference
        keyframe has well observed (40 % while the map has one keyframe), with more than 15 inliers. When the
        keyframe is taken (local mapping idle, no relocalization just before) is vo_core/front_ends/features.py's."""
        tracking = self.tracking
        keyframes = len(feature_map)
        reference = feature_map.keyframes.get(frame.reference_keyframe) or feature_map.newest()
        min_observations = tracking.min_observations if keyframes > 2 else tracking.min_observations_two_keyframes
        points = reference.point_ids[reference.point_ids >= 0]
        well_observed = int(np.sum(feature_map.observation_counts(points) >= min_observations))
        ratio = tracking.reference_ratio_keyframe if keyframes >= 2 else tracking.reference_ratio_two_keyframes
        return inliers < ratio * well_observed and inliers > tracking.min_inliers_for_keyframe


def local_mapping_idle(since_keyframe_s: float, frame_period_s: float, busy_s: float) -> bool:
    """ORB-SLAM2 takes a keyframe only while local mapping is idle: once the camera time it would have been busy
    (``busy_s``) has passed since the last keyframe, counted in frames at the camera's rate (rounded: timestamps are
    not exact multiples of the period); always while the rate is not known yet."""
    if not np.isfinite(frame_period_s):
        return True
    return np.round(since_keyframe_s / frame_period_s) >= np.round(busy_s / frame_period_s)
