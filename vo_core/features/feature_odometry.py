"""The feature half of FDMO as the system uses it: a feature map that grows at every direct keyframe, a
recovery that measures a pose from it, and feature-based tracking. Like DirectOdometry it offers steps and
decides nothing: vo_core/system.py calls them in the order of FDMO's flowcharts.

A keyframe takes its direct twin's pose (``add_keyframe`` first copies the window's optimized poses over, FDMO 4.3).
With ``mapping.own_poses`` (ours, off by default) the map keeps poses of its own instead: a keyframe takes the pose its
check measured in the map, ORB-SLAM2's local mapping adjusts it with its neighbours, and feature tracking grows the map
at keyframes of its own (``follow``, features/following.py).

One worker thread beside the caller describes and checks the next keyframe (``describe_ahead``) and grows the map
(``add_keyframe_beside``), in the order they were asked for; every other method first waits for the growth in flight
(``_settle``). The map each of them reads is therefore the one the synchronous order gives, whenever the worker ran.
"""

from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from vo_core.features.config import FeatureConfig
from vo_core.features.feature_map import FeatureKeyframe, FeatureMap, project_points
from vo_core.features.following import FOLLOWING, FeatureFollower, FollowedFrame
from vo_core.features.local_mapping import LocalMapper
from vo_core.features.loop_closing import LoopCloser
from vo_core.features.mapping import FeatureMapper, KeyframeCheck, MappingReport
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
        self.checked: FeatureKeyframe | None = None  # the keyframe check_keyframe described, for add_keyframe
        self.checked_pose: PoseFromMap | None = None  # and the map's pose for it
        # With mapping.own_poses: ORB-SLAM2's local mapping, and the feature tracking that uses it
        self.local_mapper = LocalMapper(config, camera, self.mapper) if config.mapping.own_poses else None
        self.follower = FeatureFollower(config, camera, self.relocalizer, self.local_mapper) \
            if config.mapping.own_poses else None
        self.ahead: _Ahead | None = None  # a keyframe being described and checked beside the direct half's mapping
        self.growth: Future | None = None  # a keyframe being mapped beside the caller (add_keyframe_beside)
        self.view_before_growth: tuple[np.ndarray, dict[int, np.ndarray]] | None = None  # map_view meanwhile
        self.grown: list[MappingReport] = []  # growths finished and waited for, not yet taken (take_grown)
        self._worker: ThreadPoolExecutor | None = None

    @property
    def empty(self) -> bool:
        """Whether the active map has no keyframe (older segments aside)."""
        self._settle()
        newest = self.map.newest()
        return newest is None or newest.segment != self.map.segment

    @property
    def newest_keyframe(self) -> int | None:
        """The frame index of the newest feature keyframe."""
        self._settle()
        newest = self.map.newest()
        return None if newest is None else newest.frame_index

    def reset(self, keep: bool = False) -> None:
        """A map at a new scale starts over (the direct map initialized again from scratch). With loop closing, a map
        to ``keep`` stays as an older segment that a place seen again merges with the new one; one not to keep (a
        start found wrong) goes."""
        self._settle()
        self._finish_ahead()
        if self.loop_closer is None:
            self.map = FeatureMap()
            return
        if keep:
            self.map.begin_segment()
        else:
            self.map.drop_segment()
        self.loop_closer.reset(self.map.next_keyframe_id)

    def check_keyframe(self, frame_index: int, timestamp: float, image: np.ndarray, T_world_cam: np.ndarray,
                       scene_depth: float) -> KeyframeCheck | None:
        """The feature map's own pose for a new direct keyframe at ``T_world_cam``, before it joins the map: the local
        map of the newest keyframe searched around that pose and the pose refined on what is found (ORB-SLAM2's
        TrackWithMotionModel, on the features the keyframe is described by anyway); None where the active map has no
        keyframe yet. Taken from ``describe_ahead`` where it ran for this keyframe on this map; the keyframe described
        is the one ``add_keyframe`` maps next."""
        self._settle()
        ahead = self._finish_ahead()
        if ahead is not None and ahead.serves(frame_index, image, T_world_cam, self.map.next_keyframe_id):
            self.checked, self.checked_pose, check = ahead.result.result()
            return check
        self.checked, self.checked_pose, check = self._described_and_checked(frame_index, timestamp, image,
                                                                             T_world_cam, scene_depth)
        return check

    def _finish_ahead(self) -> _Ahead | None:
        """The work ``describe_ahead`` started, finished (it reads the feature map: nothing changes the map meanwhile),
        and handed over once."""
        ahead, self.ahead = self.ahead, None
        if ahead is not None:
            ahead.result.result()
        return ahead

    def _described_and_checked(self, frame_index: int, timestamp: float, image: np.ndarray, T_world_cam: np.ndarray,
                               scene_depth: float) -> tuple[FeatureKeyframe, PoseFromMap | None, KeyframeCheck | None]:
        keyframe = self.mapper.make_keyframe(self.map.next_keyframe_id, frame_index, timestamp, image, T_world_cam,
                                             scene_depth)
        newest = self.map.newest()
        if newest is None or newest.segment != self.map.segment:
            return keyframe, None, None
        frame = FrameFeatures(keyframe.features, keyframe.bow, keyframe.nodes, 0.0)
        pose = self.relocalizer.track_from(self.map, frame, T_world_cam, newest.frame_index).pose
        return keyframe, pose, KeyframeCheck(pose.T_world_cam, pose.num_inliers, pose.found_fraction,
                                       self.relocalizer.explained(self.map, pose, T_world_cam, frame), pose.in_view)

    def add_keyframe(self, frame_index: int, timestamp: float, image: np.ndarray, T_world_cam: np.ndarray,
                     scene_depth: float, window_poses: dict[int, np.ndarray]) -> MappingReport:
        """FDMO Fig. 4 for a new direct keyframe; ``window_poses`` are the direct window's keyframe poses. With loop
        closing, the keyframe then looks for a loop (loop_closing.py), the window held where a loop moves the map."""
        start = time.perf_counter()
        keyframe, own_pose = self._keyframe_to_map(frame_index, timestamp, image, T_world_cam, scene_depth,
                                                   window_poses)
        return self._grow(keyframe, own_pose, set(window_poses), start)

    def add_keyframe_beside(self, frame_index: int, timestamp: float, image: np.ndarray, T_world_cam: np.ndarray,
                            scene_depth: float, window_poses: dict[int, np.ndarray]) -> None:
        """``add_keyframe`` with the map's growth on the worker, beside the caller's next frames; its report is
        ``take_grown``'s once a later call has waited for it. Not with loop closing: a loop moves the direct window
        at once."""
        start = time.perf_counter()
        keyframe, own_pose = self._keyframe_to_map(frame_index, timestamp, image, T_world_cam, scene_depth,
                                                   window_poses)
        self.view_before_growth = (self.points_world(), self.keyframe_poses())
        self.growth = self._worker_pool().submit(self._grow, keyframe, own_pose, set(window_poses), start)

    def _keyframe_to_map(self, frame_index: int, timestamp: float, image: np.ndarray, T_world_cam: np.ndarray,
                         scene_depth: float, window_poses: dict[int, np.ndarray]) -> tuple[FeatureKeyframe, bool]:
        """The keyframe ``check_keyframe`` described (described now where it did not), at its direct pose, and the
        map's keyframes at their window poses; with ``mapping.own_poses``, at the pose its check measured where it
        measured one (and then True: ``_grow`` maps it as ORB-SLAM2's local mapping does)."""
        self._settle()
        self._finish_ahead()
        if self.local_mapper is None:
            self.map.sync_poses(window_poses)
        keyframe, self.checked = self.checked, None
        pose, self.checked_pose = self.checked_pose, None
        if keyframe is None or keyframe.frame_index != frame_index:
            keyframe = self.mapper.make_keyframe(self.map.next_keyframe_id, frame_index, timestamp, image,
                                                 T_world_cam, scene_depth)
            pose = None
        keyframe.T_world_cam, keyframe.scene_depth = T_world_cam.copy(), scene_depth
        own_pose = self._measured_own_pose(pose)
        if own_pose:
            keyframe.T_world_cam = pose.T_world_cam.copy()
            keyframe.point_ids[pose.feature_ids[pose.inlier]] = pose.point_ids[pose.inlier]
        return keyframe, own_pose

    def _measured_own_pose(self, pose: PoseFromMap | None) -> bool:
        """With ``mapping.own_poses``, whether the keyframe's check measured a pose to take: as many inliers as a
        recovery (FDMO 4.2.2's 30), in a map past its start (its first two keyframes, the start's own, FDMO-mapped)."""
        return (self.local_mapper is not None and pose is not None and len(self.map) > 2
                and pose.num_inliers >= self.config.recovery.min_inliers)

    def _grow(self, keyframe: FeatureKeyframe, own_pose: bool, window_frames: set[int], start: float) -> MappingReport:
        if own_pose:
            report = self._map_locally(keyframe, window_frames, start)
        else:
            report = self.mapper.map_keyframe(self.map, keyframe, window_frames, start)
            if self.local_mapper is not None:
                self.local_mapper.reset()  # its statistics are per point id, and the map was renumbered
        if self.loop_closer is not None and keyframe.frame_index in self.map.keyframes:
            report.loop = self.loop_closer.run(self.map, self.map.keyframes[keyframe.frame_index], window_frames)
        return report

    def _map_locally(self, keyframe: FeatureKeyframe, window_frames: set[int], start: float) -> MappingReport:
        """ORB-SLAM2's local mapping on a keyframe at a pose of its own (``mapping.own_poses``)."""
        self.map.add_keyframe(keyframe)
        local = self.local_mapper.process(self.map, keyframe)
        self.mapper.leave_direct_window(self.map, window_frames)
        return MappingReport(keyframe.frame_index, features=len(keyframe.features), matched_points=local.tracked_points,
                             new_points=local.new_points, fused_observations=local.fused_observations,
                             outlier_observations=local.ba_outliers, culled_points=local.culled_points,
                             culled_keyframes=local.culled_keyframes, ms=(time.perf_counter() - start) * 1000.0,
                             new_matches=local.new_matches)

    def _settle(self) -> None:
        """The growth in flight finished (its report kept for ``take_grown``): the map is the synchronous one."""
        growth, self.growth = self.growth, None
        if growth is not None:
            self.grown.append(growth.result())
            self.view_before_growth = None

    def take_grown(self) -> list[MappingReport]:
        """The reports of the growths waited for since the last call (none is waited for here)."""
        grown, self.grown = self.grown, []
        return grown

    def settle(self) -> list[MappingReport]:
        """Every growth finished; their reports not yet taken."""
        self._settle()
        return self.take_grown()

    def map_view(self) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        """The active map's points and keyframe poses for a viewer, without waiting: while a keyframe grows it beside
        the caller, as they were before it."""
        if self.growth is not None:
            return self.view_before_growth
        return self.points_world(), self.keyframe_poses()

    def describe_ahead(self, frame_index: int, timestamp: float, image: np.ndarray, T_world_cam: np.ndarray) -> None:
        """A frame the direct half is making a keyframe at ``T_world_cam``: described (its ORB features and words) and
        checked (``check_keyframe``) on a thread beside the direct half's mapping of it, which changes neither the
        feature map nor that pose, and whose kernels release the interpreter's lock as OpenCV does. Whatever describes
        or changes the map next waits for it (``_finish_ahead``): the mapper's extractor is used by one thread at a
        time. Queued behind a growth in flight, it checks against the map that growth leaves."""
        T_world_cam = np.array(T_world_cam, float)
        result = self._worker_pool().submit(self._described_and_checked, frame_index, timestamp, image, T_world_cam,
                                            0.0)
        self.ahead = _Ahead(frame_index, image, T_world_cam, result)

    def add_initial_tracks(self, first: int, second: int, uv_first: np.ndarray, uv_second: np.ndarray,
                           points_world: np.ndarray) -> int:
        """The feature initializer's tracks and their triangulated points start the map (FDMO part 1)."""
        self._settle()
        return self.mapper.add_tracked_points(self.map, first, second, uv_first, uv_second, points_world)

    def recover(self, image: np.ndarray, last_keyframe: int | None,
                T_world_estimate: np.ndarray | None = None) -> RecoveryOutcome:
        self._settle()
        return self.relocalizer.recover(self.map, image, last_keyframe, T_world_estimate)

    def track(self, image: np.ndarray, T_world_guess: np.ndarray, around_keyframe: int) -> RecoveryOutcome:
        self._settle()
        return self.relocalizer.track(self.map, image, T_world_guess, around_keyframe)

    def begin_following(self, frame_index: int, timestamp: float, outcome: RecoveryOutcome,
                        previous: tuple[float, np.ndarray] | None = None) -> None:
        """Feature tracking goes on from a frame the feature map placed (a recovery, or an overruled keyframe's check
        with its features, ``checked_outcome``), with the velocity into it where ``previous`` gives one."""
        self._settle()
        self.follower.begin(frame_index, timestamp, outcome.features, outcome.pose, outcome.keyframe, previous)

    def checked_outcome(self, frame_index: int) -> RecoveryOutcome | None:
        """The feature map's pose for the keyframe ``check_keyframe`` checked last, as a recovered frame (None where
        that was another frame or no pose was measured)."""
        checked, pose = self.checked, self.checked_pose
        if checked is None or checked.frame_index != frame_index or pose is None:
            return None
        frame = FrameFeatures(checked.features, checked.bow, checked.nodes, 0.0)
        return RecoveryOutcome(True, stage=FOLLOWING, keyframe=self.map.newest().frame_index, pose=pose,
                               features=frame)

    def follow(self, frame_index: int, timestamp: float, image: np.ndarray) -> FollowedFrame:
        """The next frame by feature tracking, the map grown at keyframes of its own (features/following.py)."""
        self._settle()
        return self.follower.follow(self.map, frame_index, timestamp, image)

    def explained(self, pose: PoseFromMap, T_world_cam: np.ndarray, frame: FrameFeatures) -> float:
        self._settle()
        return self.relocalizer.explained(self.map, pose, T_world_cam, frame)

    def reprojection_shift(self, pose: PoseFromMap, T_world_a: np.ndarray, T_world_b: np.ndarray) -> float:
        """Median distance in pixels between where the pose's inlier map points appear from camera pose a and
        from b: how far apart two poses are, in what the images can tell apart (inf with no point in front)."""
        self._settle()
        return image_motion_px(self.camera, self.map.points.position[pose.point_ids[pose.inlier]], T_world_a, T_world_b)

    def depths_in_view(self, pose: PoseFromMap, T_world_cam: np.ndarray,
                       min_observations: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Pixels and inverse depths, in a camera at ``T_world_cam``, of the map points the pose's inliers matched
        that at least ``min_observations`` keyframes observe: where a direct map restarted there gets its first depths
        (at the feature map's scale)."""
        self._settle()
        matched = pose.point_ids[pose.inlier]
        matched = matched[self.map.observation_counts(matched) >= min_observations]
        view = project_points(self.map.points, matched, T_world_cam, self.camera, self.config.orb)
        return view.uv, 1.0 / transform_points(se3_inverse(T_world_cam), self.map.points.position[view.point_ids])[:, 2]

    def point_positions(self, point_ids: np.ndarray) -> np.ndarray:
        self._settle()
        return self.map.points.position[point_ids]

    def points_world(self) -> np.ndarray:
        """The active map's points (an older segment's are in another frame)."""
        self._settle()
        points = self.map.points
        return points.position[points.alive & (points.segment == self.map.segment)]

    def final_poses(self) -> dict[int, np.ndarray]:
        """Every keyframe's pose as the map ends, a culled one's on its parent's (FeatureMap.final_poses)."""
        self._settle()
        return self.map.final_poses()

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        self._settle()
        return {k.frame_index: k.T_world_cam for k in self.map.active_keyframes()}

    def _worker_pool(self) -> ThreadPoolExecutor:
        if self._worker is None:
            self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fdmo-feature-worker")
        return self._worker

    def close(self) -> None:
        """The worker finishes and ends (``FeatureProcess`` ends its process)."""
        if self._worker is not None:
            self._settle()
            self._worker.shutdown()
            self._worker, self.ahead = None, None


@dataclass(frozen=True)
class _Ahead:
    """A keyframe's description and check started by ``describe_ahead``: valid for that frame's image and pose where
    the feature map has the keyframes it had when the check ran (a growth queued before it ran first)."""

    frame_index: int
    image: np.ndarray
    T_world_cam: np.ndarray
    result: Future  # (FeatureKeyframe, PoseFromMap | None, KeyframeCheck | None)

    def serves(self, frame_index: int, image: np.ndarray, T_world_cam: np.ndarray, next_keyframe_id: int) -> bool:
        """(Asked once the result is there.) The keyframe described took the map's next id when it ran. The image is
        the same object in this process, an equal copy where the calls came through the feature process's pipe."""
        return (self.frame_index == frame_index and (self.image is image or np.array_equal(self.image, image))
                and np.array_equal(self.T_world_cam, T_world_cam)
                and self.result.result()[0].keyframe_id == next_keyframe_id)
