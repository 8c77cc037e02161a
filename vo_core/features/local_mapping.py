"""Local mapping of ``--method features``: ORB-SLAM2's LocalMapping::Run for one new keyframe, as a recipe.

    the keyframe's tracked points: viewing directions and representative descriptors     ProcessNewKeyFrame
    recent points culled: found in under a quarter of the frames that should have seen them, or seen by two
        keyframes or fewer two keyframes after their creation                            MapPointCulling
    new points triangulated with the 20 best covisible keyframes (baseline / median depth >= 0.01)
                                                                                         CreateNewMapPoints
    new points searched in the neighbours, the neighbours' points in the keyframe       SearchInNeighbors
    local bundle adjustment: the keyframe and its covisible keyframes free, the keyframes that also see their
        points held; 5 iterations, outliers out, 10 more                                 LocalBundleAdjustment
    covisible keyframes whose points 90 % of are seen by 3 other keyframes removed      KeyFrameCulling

The matching and triangulation are FDMO's mapping pieces (vo_core/features/mapping.py: epipolar search,
checked triangulation, search by projection, fusion), there run at fixed direct poses; what differs is that the
poses are this map's own and the adjustment moves them (vo_core/geometry/bundle_adjustment.py, Schur complement).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from vo_core.features.config import FeatureConfig
from vo_core.features.feature_map import NO_POINT, Covisibility, FeatureKeyframe, FeatureMap, positions_in
from vo_core.features.mapping import FeatureMapper
from vo_core.geometry.bundle_adjustment import BundleAdjustmentSettings, WindowProblem, adjust_window
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_inverse
from vo_core.geometry.reprojection import level_information


class PointStatistics:
    """Per map point: frames it was in view of and frames it was matched in (ORB-SLAM2 MapPoint mnVisible and
    mnFound), indexed by point id like the map's own columns."""

    def __init__(self):
        self.visible = np.zeros(0, np.int64)
        self.found = np.zeros(0, np.int64)

    def cover(self, num_points: int) -> None:
        """Rows for points added since; a new point has been seen and found once (ORB-SLAM2's constructor)."""
        grow = num_points - len(self.visible)
        if grow > 0:
            self.visible = np.concatenate([self.visible, np.ones(grow, np.int64)])
            self.found = np.concatenate([self.found, np.ones(grow, np.int64)])

    def count(self, num_points: int, visible: np.ndarray, found: np.ndarray) -> None:
        self.cover(num_points)
        np.add.at(self.visible, np.asarray(visible, np.int64), 1)
        np.add.at(self.found, np.asarray(found, np.int64), 1)

    def found_ratio(self, point_ids: np.ndarray) -> np.ndarray:
        return self.found[point_ids] / np.maximum(self.visible[point_ids], 1)

    def keep_only(self, rows: np.ndarray) -> None:
        self.visible, self.found = self.visible[rows], self.found[rows]


@dataclass
class LocalMappingReport:
    """What local mapping did with one keyframe (the KEYFRAME_ADDED event's details)."""

    keyframe: int
    tracked_points: int = 0
    new_points: int = 0
    fused_observations: int = 0
    culled_points: int = 0
    ba_keyframes: int = 0
    ba_fixed_keyframes: int = 0
    ba_points: int = 0
    ba_rms_before: float = 0.0  # in units of each observation's level sigma
    ba_rms_after: float = 0.0
    ba_outliers: int = 0
    culled_keyframes: list[int] = field(default_factory=list)
    new_point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    new_matches: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    renumbered: np.ndarray | None = None  # where the map compacted: new id of each old id (NO_POINT: gone)
    ms: float = 0.0

    def as_details(self) -> dict:
        return {
            "keyframe": self.keyframe, "tracked_points": self.tracked_points, "new_points": self.new_points,
            "fused_observations": self.fused_observations, "culled_points": self.culled_points,
            "local_ba": {"keyframes": self.ba_keyframes, "fixed_keyframes": self.ba_fixed_keyframes,
                         "points": self.ba_points, "rms_before": round(self.ba_rms_before, 3),
                         "rms_after": round(self.ba_rms_after, 3), "outliers": self.ba_outliers},
            "culled_keyframes": self.culled_keyframes, "ms": round(self.ms, 1),
        }


class LocalMapper:
    def __init__(self, config: FeatureConfig, camera: PinholeCamera, mapper: FeatureMapper):
        self.config = config
        self.local = config.odometry.local_mapping
        self.camera = camera
        self.mapper = mapper
        self.statistics = PointStatistics()
        # points created by the last few keyframes (ORB-SLAM2 mlpRecentAddedMapPoints)
        self.recent = np.zeros(0, np.int64)

    def reset(self) -> None:
        self.statistics = PointStatistics()
        self.recent = np.zeros(0, np.int64)

    def process(self, feature_map: FeatureMap, keyframe: FeatureKeyframe) -> LocalMappingReport:
        start = time.perf_counter()
        report = LocalMappingReport(keyframe.frame_index, tracked_points=len(keyframe.observed()))
        self.process_new_keyframe(feature_map, keyframe)
        report.culled_points = self.cull_recent_points(feature_map, keyframe)
        report.new_matches, report.new_point_ids = self.create_new_points(feature_map, keyframe)
        report.new_points = len(report.new_point_ids)
        self.recent = np.concatenate([self.recent, report.new_point_ids])
        self.statistics.cover(len(feature_map.points))
        report.fused_observations = self.search_in_neighbours(feature_map, keyframe, report.new_point_ids)
        self.local_bundle_adjustment(feature_map, keyframe, report)
        report.culled_keyframes = self.cull_keyframes(feature_map, keyframe)
        report.renumbered = self.compact(feature_map)
        report.ms = (time.perf_counter() - start) * 1000.0
        return report

    # ------------------------------------------------------------------------------------ the steps

    def process_new_keyframe(self, feature_map: FeatureMap, keyframe: FeatureKeyframe) -> None:
        """The keyframe's points gained a view: their viewing directions and descriptors follow."""
        points = keyframe.point_ids[keyframe.observed()]
        feature_map.update_normals(points)
        feature_map.representative_descriptors(points)
        keyframe.scene_depth = self.median_depth(feature_map, keyframe)

    def cull_recent_points(self, feature_map: FeatureMap, keyframe: FeatureKeyframe) -> int:
        """ORB-SLAM2 MapPointCulling over the recently created points."""
        local = self.local
        points = feature_map.points
        self.statistics.cover(len(points))
        recent = self.recent[points.alive[self.recent]]
        age = keyframe.keyframe_id - points.first_keyframe[recent]
        views = feature_map.observation_counts(recent)
        spurious = (self.statistics.found_ratio(recent) < local.min_found_ratio) | (
            (age >= local.culling_keyframes) & (views <= local.culling_max_observations))
        feature_map.remove_points(recent[spurious])
        self.recent = recent[~spurious & (age < local.recent_keyframes)]
        return int(spurious.sum())

    def create_new_points(self, feature_map: FeatureMap, keyframe: FeatureKeyframe) -> tuple[np.ndarray, np.ndarray]:
        """ORB-SLAM2 CreateNewMapPoints: epipolar matches of unmatched features with each of the best covisible
        keyframes far enough away, triangulated and checked (FeatureMapper.triangulate_pair)."""
        matches, point_ids = [np.zeros((0, 4))], [np.zeros(0, np.int64)]
        graph = feature_map.covisibility_graph()
        for neighbour in self.neighbours(graph, keyframe, self.local.triangulation_neighbours):
            other = feature_map.keyframes[neighbour]
            baseline = np.linalg.norm(keyframe.centre - other.centre)
            depth = self.median_depth(feature_map, other)
            if not np.isfinite(depth) or baseline < self.local.min_baseline_depth_ratio * depth:
                continue
            pair_matches, pair_points = self.mapper.triangulate_pair(feature_map, keyframe, other)
            matches.append(pair_matches)
            point_ids.append(pair_points)
        point_ids = np.concatenate(point_ids)
        feature_map.update_normals(point_ids)
        return np.concatenate(matches), point_ids

    def search_in_neighbours(self, feature_map: FeatureMap, keyframe: FeatureKeyframe, new_points: np.ndarray) -> int:
        """ORB-SLAM2 SearchInNeighbors, without merging duplicates: the keyframe's new points searched in its
        neighbours (and theirs), the neighbours' points searched among the keyframe's unmatched features."""
        graph = feature_map.covisibility_graph()
        first = self.neighbours(graph, keyframe, self.local.fuse_neighbours)
        second = [k for n in first for k in graph.covisible_keyframes(n, 1, 5) if k != keyframe.frame_index]
        targets = [feature_map.keyframes[k] for k in dict.fromkeys(first + second)]
        fused = self.mapper.fuse(feature_map, new_points, targets)
        unseen = np.setdiff1d(feature_map.points_of([k.frame_index for k in targets]), keyframe.point_ids)
        found_points, found_features = self.mapper.search_points(feature_map, keyframe, unseen,
                                                                 self.config.mapping.projection_radius_px)
        keyframe.point_ids[found_features] = found_points
        touched = keyframe.point_ids[keyframe.observed()]
        feature_map.update_normals(touched)
        feature_map.representative_descriptors(touched)
        return fused + len(found_points)

    def local_bundle_adjustment(self, feature_map: FeatureMap, keyframe: FeatureKeyframe,
                                report: LocalMappingReport) -> None:
        """ORB-SLAM2 Optimizer::LocalBundleAdjustment: the keyframe and its covisible keyframes free (the map's
        first keyframe always held), their points free, the other keyframes that see those points held; level
        weights and Huber at sqrt(5.991); 5 iterations, the outliers out, 10 more; outlier observations leave."""
        graph = feature_map.covisibility_graph()
        local = [keyframe.frame_index, *graph.covisible_keyframes(keyframe.frame_index, 1)]
        points = feature_map.points_of(local)
        table = graph.table
        keep = np.isin(table.point, points)
        observer, feature, point = table.keyframe[keep], table.feature[keep], table.point[keep]
        observers = list(dict.fromkeys([*local, *np.unique(observer).tolist()]))
        fixed = self._held(feature_map, observers, local)
        if fixed.all():
            return
        poses = np.stack([feature_map.keyframes[k].T_world_cam for k in observers])
        pose_index = positions_in(np.array(observers, np.int64), observer)
        uv, level = feature_map.pixels_of(observer, feature)
        active = self._usable(poses, feature_map.points.position[point], pose_index, point)
        settings = BundleAdjustmentSettings(huber_px=float(np.sqrt(self.local.ba_chi2)), sparse_schur=True)
        for iterations in (self.local.ba_first_iterations, self.local.ba_second_iterations):
            ids, point_index = np.unique(point[active], return_inverse=True)
            problem = WindowProblem(poses, fixed, feature_map.points.position[ids], pose_index[active], point_index,
                                    uv[active], level_information(level[active], self.config.orb.scale_factor))
            settings.max_iterations = iterations
            solution = adjust_window(self.camera, problem, settings)
            poses = solution.poses_world_cam
            feature_map.points.position[ids] = solution.points_world
            if iterations == self.local.ba_first_iterations:
                report.ba_rms_before = _rms(solution.errors_before)
            active[np.flatnonzero(active)[solution.errors_after**2 > self.local.ba_chi2]] = False
            active &= self._in_front(poses, feature_map.points.position[point], pose_index)
        report.ba_rms_after = _rms(solution.errors_after)
        for frame_index, T_world_cam in zip(observers, poses):
            feature_map.keyframes[frame_index].T_world_cam = T_world_cam
        feature_map.remove_observations(observer[~active], feature[~active])
        feature_map.update_normals(points)
        report.ba_keyframes, report.ba_fixed_keyframes = int((~fixed).sum()), int(fixed.sum())
        report.ba_points, report.ba_outliers = len(np.unique(point[active])), int((~active).sum())

    def _held(self, feature_map: FeatureMap, observers: list[int], local: list[int]) -> np.ndarray:
        """Keyframes the adjustment holds: those outside the local ones (ORB-SLAM2's fixed keyframes), the map's
        first (ORB-SLAM2 holds keyframe 0), and, while that makes fewer than ``min_held_keyframes``, the oldest
        local ones before the new keyframe. One held keyframe leaves a monocular map its scale free; where every
        keyframe is covisible with the new one (a small scene) nothing else holds it (ours: the synthetic planar
        sequence's scale changed by 1.6 in one adjustment)."""
        ids = np.array([feature_map.keyframes[k].keyframe_id for k in observers])
        held = np.array([k not in local for k in observers]) | (ids == ids.min())
        for i in np.argsort(ids)[:-1]:  # oldest first, never the newest
            if held.sum() >= self.local.min_held_keyframes:
                break
            held[i] = True
        return held

    def cull_keyframes(self, feature_map: FeatureMap, keyframe: FeatureKeyframe) -> list[int]:
        """ORB-SLAM2 KeyFrameCulling: a covisible keyframe (never the map's first, this one, nor one at either end of
        a loop) whose points are 90 % seen by at least 3 other keyframes is redundant and leaves the map."""
        local = self.local
        origin = min(feature_map.keyframes.values(), key=lambda k: k.keyframe_id).frame_index
        kept = feature_map.loop_keyframes() | {origin}
        culled = []
        graph = feature_map.covisibility_graph()
        for frame_index in graph.covisible_keyframes(keyframe.frame_index, 1):
            if frame_index in kept:
                continue
            candidate = feature_map.keyframes[frame_index]
            points = candidate.point_ids[candidate.observed()]
            if len(points) == 0:
                continue
            others = graph.observation_counts(points) - 1
            if np.mean(others >= local.redundant_observers) > local.redundancy:
                feature_map.remove_keyframe(frame_index)
                culled.append(frame_index)
                graph = feature_map.covisibility_graph()  # the culled keyframe's views are gone
        return culled

    def compact(self, feature_map: FeatureMap) -> np.ndarray | None:
        """The map drops its dead rows when most are dead; the statistics and the recent points follow. Returns
        the renumbering (new id per old id, NO_POINT for the dead) where it happened."""
        live = np.flatnonzero(feature_map.points.alive)
        before = len(feature_map.points)
        feature_map.compact()
        if len(feature_map.points) == before:
            return None
        renumbered = np.full(before, NO_POINT, np.int64)
        renumbered[live] = np.arange(len(live))
        self.statistics.cover(before)
        self.statistics.keep_only(live)
        self.recent = renumbered[self.recent]
        self.recent = self.recent[self.recent >= 0]
        return renumbered

    # ------------------------------------------------------------------------------------ helpers

    def neighbours(self, graph: Covisibility, keyframe: FeatureKeyframe, count: int) -> list[int]:
        """ORB-SLAM2 GetBestCovisibilityKeyFrames: the neighbours sharing at least 15 points, most first; the
        best one alone where none does."""
        neighbours = graph.covisible_keyframes(keyframe.frame_index, self.local.min_covisibility, count)
        return neighbours or graph.covisible_keyframes(keyframe.frame_index, 1, 1)

    @staticmethod
    def median_depth(feature_map: FeatureMap, keyframe: FeatureKeyframe) -> float:
        """ORB-SLAM2 ComputeSceneMedianDepth: the median depth of the keyframe's points in its camera."""
        points = keyframe.point_ids[keyframe.observed()]
        if len(points) == 0:
            return np.nan
        depths = feature_map.in_camera(keyframe, points)[:, 2]
        return float(np.median(depths))

    def _usable(self, poses, positions, pose_index, point) -> np.ndarray:
        """Observations the adjustment can use: in front of their camera, of points seen at least twice, one per
        keyframe and point (the adjustment's model has at most one)."""
        usable = self._in_front(poses, positions, pose_index)
        _, first = np.unique(pose_index * (point.max() + 1 if len(point) else 1) + point, return_index=True)
        once = np.zeros(len(point), bool)
        once[first] = True
        usable &= once
        counts = np.bincount(point[usable], minlength=point.max() + 1 if len(point) else 0)
        return usable & (counts[point] >= 2)

    @staticmethod
    def _in_front(poses, positions, pose_index) -> np.ndarray:
        T_cam_world = np.stack([se3_inverse(T) for T in poses])[pose_index]
        depth = np.einsum("nj,nj->n", T_cam_world[:, 2, :3], positions) + T_cam_world[:, 2, 3]
        return depth > 0


def _rms(errors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(errors**2))) if len(errors) else 0.0
