"""The feature half of FDMO as the system uses it: a feature map that grows at every direct keyframe, a
recovery that measures a pose from it, and feature-based tracking. Like DirectOdometry it offers steps and
decides nothing: vo_core/system.py calls them in the order of FDMO's flowcharts.

Nothing here estimates a keyframe pose: keyframes take their direct twins' poses (``add_keyframe`` first
copies the window's optimized poses over, FDMO 4.3).
"""

from __future__ import annotations

import numpy as np

from vo_core.features.config import FeatureConfig
from vo_core.features.feature_map import FeatureMap, project_points
from vo_core.features.loop_closing import LoopCloser
from vo_core.features.mapping import FeatureMapper, MappingReport
from vo_core.features.recovery import FrameFeatures, PoseFromMap, RecoveryOutcome, Relocalizer
from vo_core.features.vocabulary import load_vocabulary
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_inverse, transform_points
from vo_core.geometry.multiview import image_motion_px


class FeatureOdometry:
    def __init__(self, config: FeatureConfig, camera: PinholeCamera):
        self.config = config
        self.camera = camera
        vocabulary = load_vocabulary(config.vocabulary)
        self.map = FeatureMap()
        self.mapper = FeatureMapper(config, camera, vocabulary)
        self.relocalizer = Relocalizer(config, camera, vocabulary)
        self.loop_closer = LoopCloser(config.loop_closing, config.orb, camera) if config.loop_closing.enabled else None

    @property
    def empty(self) -> bool:
        """Whether the active map has no keyframe (older segments aside)."""
        newest = self.map.newest()
        return newest is None or newest.segment != self.map.segment

    @property
    def newest_keyframe(self) -> int | None:
        """The frame index of the newest feature keyframe."""
        newest = self.map.newest()
        return None if newest is None else newest.frame_index

    def reset(self, keep: bool = False) -> None:
        """A map at a new scale starts over (the direct map initialized again from scratch). With loop closing, a map
        to ``keep`` stays as an older segment that a place seen again merges with the new one; one not to keep (a
        start found wrong) goes."""
        if self.loop_closer is None:
            self.map = FeatureMap()
            return
        if keep:
            self.map.begin_segment()
        else:
            self.map.drop_segment()
        self.loop_closer.reset(self.map.next_keyframe_id)

    def add_keyframe(self, frame_index: int, timestamp: float, image: np.ndarray, T_world_cam: np.ndarray,
                     scene_depth: float, window_poses: dict[int, np.ndarray]) -> MappingReport:
        """FDMO Fig. 4 for a new direct keyframe; ``window_poses`` are the direct window's keyframe poses. With loop
        closing, the keyframe then looks for a loop (loop_closing.py), the window held where a loop moves the map."""
        self.map.sync_poses(window_poses)
        report = self.mapper.add_keyframe(self.map, frame_index, timestamp, image, T_world_cam, scene_depth,
                                          set(window_poses))
        if self.loop_closer is not None and frame_index in self.map.keyframes:
            report.loop = self.loop_closer.run(self.map, self.map.keyframes[frame_index], set(window_poses))
        return report

    def describe_ahead(self, frame_index: int, image: np.ndarray) -> None:
        """The image of a frame the direct half is making a keyframe, described while it does (FeatureMapper)."""
        self.mapper.describe_ahead(frame_index, image)

    def add_initial_tracks(self, first: int, second: int, uv_first: np.ndarray, uv_second: np.ndarray,
                           points_world: np.ndarray) -> int:
        """The feature initializer's tracks and their triangulated points start the map (FDMO part 1)."""
        return self.mapper.add_tracked_points(self.map, first, second, uv_first, uv_second, points_world)

    def recover(self, image: np.ndarray, last_keyframe: int | None,
                T_world_estimate: np.ndarray | None = None) -> RecoveryOutcome:
        return self.relocalizer.recover(self.map, image, last_keyframe, T_world_estimate)

    def track(self, image: np.ndarray, T_world_guess: np.ndarray, around_keyframe: int) -> RecoveryOutcome:
        return self.relocalizer.track(self.map, image, T_world_guess, around_keyframe)

    def explained(self, pose: PoseFromMap, T_world_cam: np.ndarray, frame: FrameFeatures) -> float:
        return self.relocalizer.explained(self.map, pose, T_world_cam, frame)

    def reprojection_shift(self, pose: PoseFromMap, T_world_a: np.ndarray, T_world_b: np.ndarray) -> float:
        """Median distance in pixels between where the pose's inlier map points appear from camera pose a and
        from b: how far apart two poses are, in what the images can tell apart (inf with no point in front)."""
        return image_motion_px(self.camera, self.map.points.position[pose.point_ids[pose.inlier]], T_world_a, T_world_b)

    def depths_in_view(self, pose: PoseFromMap, T_world_cam: np.ndarray,
                       min_observations: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Pixels and inverse depths, in a camera at ``T_world_cam``, of the map points the pose's inliers matched
        that at least ``min_observations`` keyframes observe: where a direct map restarted there gets its first depths
        (at the feature map's scale)."""
        matched = pose.point_ids[pose.inlier]
        matched = matched[self.map.observation_counts(matched) >= min_observations]
        view = project_points(self.map.points, matched, T_world_cam, self.camera, self.config.orb)
        return view.uv, 1.0 / transform_points(se3_inverse(T_world_cam), self.map.points.position[view.point_ids])[:, 2]

    def point_positions(self, point_ids: np.ndarray) -> np.ndarray:
        return self.map.points.position[point_ids]

    def points_world(self) -> np.ndarray:
        """The active map's points (an older segment's are in another frame)."""
        points = self.map.points
        return points.position[points.alive & (points.segment == self.map.segment)]

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        return {k.frame_index: k.T_world_cam for k in self.map.active_keyframes()}

    def close(self) -> None:
        """The mapper's describing thread ends (``FeatureProcess`` ends its process)."""
        self.mapper.close()
