"""Feature-based tracking of FDMO Fig. 3 while the direct half cannot be trusted, done as ORB-SLAM2 tracks: each frame
from the last one's matches at the constant-velocity pose (or the reference keyframe's bag of words), then the local
map (features/feature_tracking.py); where tracking wants a keyframe, the frame becomes one of the feature map's own,
at its own pose, and local mapping with free poses runs on it (features/local_mapping.py).

Why the map grows here, and not only at direct keyframes: the frames that need feature tracking are those of a
view the direct map has lost (a fast sweep, a collapse the feature map overruled), and a feature map held still
holds the points of the view left behind. Searched only in it, tracking loses the camera within a few frames of a
sweep (TUM fr1/desk, stride 1, seed 1: 49 -> 0 inliers over frames 201-210 while 636 -> 0 of its points stayed in
view, then a new map at its own scale); the features method, which grows its map as it goes, tracks the same frames
with 72-381 inliers. Its keyframes are where the direct map may restart: their points have just been triangulated
and adjusted with the keyframe's pose (vo_core/system.py, ``_follow``).

Nothing here decides between the halves; it offers ``begin`` and ``follow``, and reports a frame it cannot place.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from vo_core.features.config import FeatureConfig
from vo_core.features.feature_map import FeatureKeyframe, FeatureMap
from vo_core.features.feature_tracking import FeatureTracker, TrackedFrame, local_mapping_idle
from vo_core.features.local_mapping import LocalMapper
from vo_core.features.recovery import FrameFeatures, PoseFromMap, RecoveryOutcome, Relocalizer
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.motion_model import extrapolate
from vo_core.timing import ms_since

FOLLOWING = "following"  # RecoveryOutcome.stage of a followed frame


@dataclass
class FollowedFrame:
    outcome: RecoveryOutcome  # succeeded with the frame's pose and matches, or why it could not be placed
    is_keyframe: bool = False  # the frame became a keyframe of the feature map's own


class FeatureFollower:
    def __init__(self, config: FeatureConfig, camera: PinholeCamera, relocalizer: Relocalizer,
                 local_mapper: LocalMapper):
        self.config = config
        self.relocalizer = relocalizer
        self.tracker = FeatureTracker(config, camera, relocalizer)
        self.local_mapper = local_mapper  # the feature map's own (features/feature_odometry.py)
        self.last: TrackedFrame | None = None
        self.posed: list[tuple[float, np.ndarray]] = []  # the last two poses (timestamp, T_world_cam): the velocity
        self.keyframed_at = -np.inf
        self.frame_period = np.inf  # the shortest interval seen between two followed frames

    def begin(self, frame_index: int, timestamp: float, features: FrameFeatures, pose: PoseFromMap,
              reference_keyframe: int, previous: tuple[float, np.ndarray] | None) -> None:
        """Tracking goes on from a frame the feature map placed (``pose``: its matches), with the velocity from
        ``previous`` (timestamp, T_world_cam) where the motion into that frame is known."""
        last = TrackedFrame(frame_index, timestamp, features, pose.T_world_cam.copy(),
                            reference_keyframe=reference_keyframe)
        inlier = pose.inlier
        last.point_ids[pose.feature_ids[inlier]] = pose.point_ids[inlier]
        self.last = last
        self.posed = ([] if previous is None else [previous]) + [(timestamp, last.T_world_cam)]
        self.keyframed_at, self.frame_period = timestamp, np.inf

    def follow(self, feature_map: FeatureMap, frame_index: int, timestamp: float, image: np.ndarray) -> FollowedFrame:
        start = time.perf_counter()
        features = self.relocalizer.extract(image)
        self.frame_period = min(self.frame_period, timestamp - self.last.timestamp)
        current = TrackedFrame(frame_index, timestamp, features, reference_keyframe=self.last.reference_keyframe)
        T_predicted = extrapolate(self.posed, timestamp) if len(self.posed) == 2 else None
        tracked = self.tracker.track(feature_map, current, self.last, T_predicted, relocalized_recently=False)
        if not tracked.succeeded:
            return FollowedFrame(RecoveryOutcome(False, tracked.reason, stage=FOLLOWING, features=features,
                                                 ms=ms_since(start)))
        self.local_mapper.statistics.count(len(feature_map.points), tracked.visible_points,
                                           current.point_ids[current.matched])
        is_keyframe = self._wants_keyframe(feature_map, current, tracked.inliers)
        if is_keyframe:
            self._map_keyframe(feature_map, current)
        self.posed = (self.posed + [(timestamp, current.T_world_cam)])[-2:]
        self.last = current
        matched = current.matched
        pose = PoseFromMap(current.T_world_cam.copy(), current.point_ids[matched], matched,
                           np.ones(len(matched), bool), in_view=len(tracked.visible_points))
        outcome = RecoveryOutcome(True, stage=FOLLOWING, keyframe=current.reference_keyframe, pose=pose,
                                  features=features, ms=ms_since(start))
        return FollowedFrame(outcome, is_keyframe)

    def _wants_keyframe(self, feature_map: FeatureMap, current: TrackedFrame, inliers: int) -> bool:
        """ORB-SLAM2 NeedNewKeyFrame, as the features method takes it (vo_core/front_ends/features.py)."""
        idle = local_mapping_idle(current.timestamp - self.keyframed_at, self.frame_period,
                                  self.config.odometry.tracking.local_mapping_busy_s)
        return (idle and current.frame_index not in feature_map.keyframes
                and self.tracker.tracks_few_reference_points(feature_map, current, inliers))

    def _map_keyframe(self, feature_map: FeatureMap, current: TrackedFrame) -> None:
        """The frame becomes a keyframe at its tracked pose, local mapping adjusts it with its neighbours, and the
        frame takes the adjusted pose (the last frame follows a renumbering of the points)."""
        features = current.features
        keyframe = FeatureKeyframe(feature_map.next_keyframe_id, current.frame_index, current.timestamp,
                                   current.T_world_cam.copy(), features.features, features.bow, features.nodes,
                                   point_ids=current.point_ids.copy(), in_direct_window=False)
        feature_map.add_keyframe(keyframe)
        report = self.local_mapper.process(feature_map, keyframe)
        if report.renumbered is not None:
            observed = self.last.matched
            self.last.point_ids[observed] = report.renumbered[self.last.point_ids[observed]]
        current.T_world_cam = keyframe.T_world_cam.copy()
        current.point_ids = keyframe.point_ids.copy()
        current.reference_keyframe = keyframe.frame_index
        self.keyframed_at = current.timestamp
