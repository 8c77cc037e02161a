"""Feature-based mapping at every direct keyframe (FDMO section 4.3, Fig. 4) and map maintenance (4.4).

``FeatureMapper.add_keyframe`` reads as the recipe (the way ORB-SLAM2's LocalMapping::Run does):

    extract ORB features and their bag of words            (the keyframe inherits its direct twin's pose)
    choose the local keyframes                              (covisible with the last keyframe, then the newest)
    find the local map's points in the new keyframe         (projection at the direct pose, guided search)
    match with each local keyframe along epipolar lines     (known poses: no essential matrix is estimated)
    triangulate where baseline / depth >= 0.02              (cheirality, reprojection, parallax, scale checks)
    find the new points in the other local keyframes        (more views for the adjustment: ORB-SLAM2's fusion)
    structure-only bundle adjustment of the local points    (poses fixed: they are the direct system's)
    each point seen by the new keyframe takes its most distinctive descriptor among its views
    cull points not found in 4 of the next 7 keyframes, and redundant keyframes the direct window has left

Poses are never estimated here: FDMO keeps one pose per keyframe, the direct one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from vo_core.features.config import FeatureConfig
from vo_core.features.feature_map import NO_POINT, FeatureKeyframe, FeatureMap, project_points
from vo_core.features.matcher import epipole_in_b, fundamental_matrix, search_by_projection, search_epipolar
from vo_core.features.orb import Features, OrbExtractor, level_scales, level_sigma2s
from vo_core.features.vocabulary import BowVector, Vocabulary
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_inverse, transform_points
from vo_core.geometry.multiview import triangulate
from vo_core.geometry.structure_only import refine_points

if TYPE_CHECKING:
    from vo_core.features.loop_closing import LoopReport


@dataclass(frozen=True)
class KeyframeCheck:
    """The feature map's witness of a new direct keyframe's pose (FeatureOdometry.check_keyframe), the evidence
    fdmo/decide.judge_keyframe reads."""

    T_world_cam: np.ndarray  # the feature map's pose for the keyframe
    inliers: int
    found_fraction: float  # inliers per local map point in view
    explained: float  # the share of those inliers the direct pose explains (Relocalizer.explained)
    in_view: int = 0  # the local map points in view at the direct pose, that the search looked for

    def details(self) -> dict:
        return {"inliers": self.inliers, "found_fraction": round(self.found_fraction, 3),
                "explained": round(self.explained, 3), "in_view": self.in_view}


@dataclass
class MappingReport:
    """What one feature keyframe did to the map (the FEATURE_KEYFRAME_ADDED event's details)."""

    frame_index: int
    features: int = 0
    local_keyframes: list[int] = field(default_factory=list)
    matched_points: int = 0  # existing points found in the new keyframe
    new_points: int = 0  # triangulated with the local keyframes
    refused_baselines: int = 0  # local keyframes too close for triangulation (FDMO 4.4)
    fused_observations: int = 0  # new points found in the other local keyframes too
    tracked_points: int = 0  # points the initializer tracked into this keyframe (the map's first keyframes)
    outlier_observations: int = 0  # removed by the structure-only adjustment
    culled_points: int = 0  # FDMO 4.4's 4-of-7 rule and points left without views
    culled_keyframes: list[int] = field(default_factory=list)
    ms: float = 0.0
    new_matches: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # (u_local, v_local, u_new, v_new)
    loop: LoopReport | None = None  # with loop closing on: what it did after the keyframe was mapped

    def as_details(self) -> dict:
        return {
            "keyframe": self.frame_index, "features": self.features, "local_keyframes": self.local_keyframes,
            "matched_points": self.matched_points, "new_points": self.new_points,
            "refused_baselines": self.refused_baselines, "fused_observations": self.fused_observations,
            "tracked_points": self.tracked_points,
            "outlier_observations": self.outlier_observations,
            "culled_points": self.culled_points, "culled_keyframes": self.culled_keyframes, "ms": round(self.ms, 1),
        }


class FeatureMapper:
    def __init__(self, config: FeatureConfig, camera: PinholeCamera, vocabulary: Vocabulary):
        self.config = config
        self.camera = camera
        self.extractor = OrbExtractor(config.orb)
        self.vocabulary = vocabulary
        self.scales = level_scales(config.orb)
        self.sigma2 = level_sigma2s(config.orb)

    # ------------------------------------------------------------------------------------ the recipe

    def add_keyframe(
        self, feature_map: FeatureMap, frame_index: int, timestamp: float, image: np.ndarray,
        T_world_cam: np.ndarray, scene_depth: float, direct_window: set[int],
    ) -> MappingReport:
        """``scene_depth`` is the median depth of the direct points seen by the keyframe (what FDMO 4.4's
        baseline / depth rule divides by); ``direct_window`` the frame indices of the direct window."""
        start = time.perf_counter()
        keyframe = self.make_keyframe(
            feature_map.next_keyframe_id, frame_index, timestamp, image, T_world_cam, scene_depth
        )
        return self.map_keyframe(feature_map, keyframe, direct_window, start)

    def map_keyframe(self, feature_map: FeatureMap, keyframe: FeatureKeyframe, direct_window: set[int],
                     start: float | None = None) -> MappingReport:
        """``add_keyframe`` for a keyframe already made (described), from choosing the local keyframes on."""
        start = time.perf_counter() if start is None else start
        report = MappingReport(keyframe.frame_index)
        report.features = len(keyframe.features)
        local = self.local_keyframes(feature_map)
        feature_map.add_keyframe(keyframe)
        report.local_keyframes = [k.frame_index for k in local]
        report.matched_points = self.find_local_points(feature_map, keyframe, local)
        report.new_matches, new_points = self.triangulate_with(feature_map, keyframe, local, report)
        report.new_points = len(new_points)
        report.fused_observations = self.fuse(feature_map, new_points, local)
        report.outlier_observations = self.refine_structure(feature_map, [keyframe, *local])
        feature_map.representative_descriptors(keyframe.point_ids[keyframe.point_ids >= 0])
        report.culled_points = self.cull_points(feature_map)
        self.leave_direct_window(feature_map, direct_window)
        report.culled_keyframes = self.cull_keyframes(feature_map)
        feature_map.compact()
        report.ms = (time.perf_counter() - start) * 1000.0
        return report

    def make_keyframe(self, keyframe_id, frame_index, timestamp, image, T_world_cam, scene_depth) -> FeatureKeyframe:
        features, bow, nodes = self._described(image)
        return FeatureKeyframe(keyframe_id, frame_index, timestamp, T_world_cam.copy(), features, bow, nodes,
                               scene_depth=scene_depth, image=image)

    def _described(self, image: np.ndarray) -> tuple[Features, BowVector, np.ndarray]:
        """The image's features, bag of words and direct-index nodes."""
        features = self.extractor.extract(image)
        return (features, *self.vocabulary.transform(features.descriptors))

    def local_keyframes(self, feature_map: FeatureMap) -> list[FeatureKeyframe]:
        """κ^f of FDMO Fig. 4: the last keyframe, its covisible neighbours (most shared points first), then the
        newest keyframes until there are ``local_keyframes`` (a new keyframe has no points of its own yet, so
        its neighbourhood is the previous keyframe's). Only the active segment's: an older one (a map the direct
        half started anew from) has another frame and scale, and joins only by a merge (loop_closing.py); the first
        keyframe of a new segment has none."""
        active = feature_map.active_keyframes()
        if not active:
            return []
        count = self.config.mapping.local_keyframes
        in_segment = {k.frame_index for k in active}
        chosen = [active[-1].frame_index]
        chosen += [f for f in feature_map.covisible_keyframes(active[-1].frame_index, 1) if f in in_segment][:count - 1]
        for keyframe in reversed(active):
            if len(chosen) >= count:
                break
            if keyframe.frame_index not in chosen:
                chosen.append(keyframe.frame_index)
        return [feature_map.keyframes[i] for i in chosen]

    # ------------------------------------------------------------------------------------ data association

    def find_local_points(self, feature_map: FeatureMap, keyframe: FeatureKeyframe, local) -> int:
        """The local keyframes' points projected into the new keyframe at its direct pose and searched in a
        small window (ORB-SLAM2 SearchLocalPoints): they keep being observed, which FDMO 4.4's rule counts."""
        point_ids = feature_map.points_of([k.frame_index for k in local])
        matched_points, matched_features = self.search_points(feature_map, keyframe, point_ids,
                                                              self.config.mapping.projection_radius_px)
        keyframe.point_ids[matched_features] = matched_points
        return len(matched_points)

    def search_points(self, feature_map: FeatureMap, keyframe: FeatureKeyframe, point_ids: np.ndarray,
                      radius_px: float) -> tuple[np.ndarray, np.ndarray]:
        """Map points found among the keyframe's unmatched features by projection: (point ids, feature indices)."""
        mapping = self.config.mapping
        view = project_points(feature_map.points, point_ids, keyframe.T_world_cam, self.camera, self.config.orb)
        found_points, found_features = search_by_projection(
            keyframe.features, view.uv, feature_map.points.descriptor[view.point_ids], view.level, radius_px,
            max_distance=mapping.projection_max_distance, ratio=mapping.projection_ratio,
            scale_factor=self.config.orb.scale_factor, available=keyframe.point_ids == NO_POINT,
        )
        return view.point_ids[found_points], found_features

    # ------------------------------------------------------------------------------------ triangulation

    def triangulate_with(self, feature_map: FeatureMap, keyframe: FeatureKeyframe, local, report):
        """New points from the new keyframe's unmatched features and each local keyframe's, matched along
        epipolar lines at the direct poses; returns the new matches as (u_local, v_local, u_new, v_new) and the
        new points' ids."""
        matches, point_ids = [np.zeros((0, 4))], [np.zeros(0, np.int64)]
        for other in local:
            if not self.baseline_large_enough(keyframe, other):
                report.refused_baselines += 1
                continue
            pair_matches, pair_points = self.triangulate_pair(feature_map, keyframe, other)
            matches.append(pair_matches)
            point_ids.append(pair_points)
        return np.concatenate(matches), np.concatenate(point_ids)

    def fuse(self, feature_map: FeatureMap, point_ids: np.ndarray, local) -> int:
        """The new points searched in every local keyframe that does not observe them yet (ORB-SLAM2
        LocalMapping::SearchInNeighbors): a point made from two keyframes is seen by the others between and
        around them, and every extra view tightens its position in the adjustment that follows."""
        fused = 0
        for other in local:
            unseen = point_ids[~np.isin(point_ids, other.point_ids)]
            found_points, found_features = self.search_points(feature_map, other, unseen,
                                                              self.config.mapping.projection_radius_px)
            other.point_ids[found_features] = found_points
            fused += len(found_points)
        return fused

    def baseline_large_enough(self, keyframe: FeatureKeyframe, other: FeatureKeyframe) -> bool:
        """FDMO 4.4: no triangulation between keyframes with baseline / depth < 0.02, the depth being the scene's
        median depth (the direct points') seen from the farther of the two (ORB-SLAM2 ComputeSceneMedianDepth)."""
        baseline = np.linalg.norm(keyframe.centre - other.centre)
        depth = max(keyframe.scene_depth, other.scene_depth)
        return bool(np.isfinite(depth)) and baseline >= self.config.mapping.min_baseline_depth_ratio * depth

    def triangulate_pair(self, feature_map: FeatureMap, new: FeatureKeyframe, other: FeatureKeyframe) -> np.ndarray:
        mapping = self.config.mapping
        free_new = new.point_ids == NO_POINT
        free_other = other.point_ids == NO_POINT
        T_new_other = se3_inverse(new.T_world_cam) @ other.T_world_cam
        index_new, index_other = search_epipolar(
            new.features, other.features, fundamental_matrix(self.camera, self.camera, T_new_other),
            free_new, free_other, new.nodes, other.nodes,
            max_distance=mapping.epipolar_max_distance, ratio=mapping.epipolar_ratio, level_sigma2=self.sigma2,
            epipole_b=epipole_in_b(self.camera, T_new_other),
        )
        points, good = self.triangulate_checked(new, index_new, other, index_other)
        index_new, index_other, points = index_new[good], index_other[good], points[good]
        level_new = new.features.level[index_new]
        distance = np.linalg.norm(points - new.centre, axis=1)
        ids = feature_map.points.add(points, new.features.descriptors[index_new], new.keyframe_id, distance, level_new)
        new.point_ids[index_new] = ids
        other.point_ids[index_other] = ids
        return np.hstack([other.features.uv[index_other], new.features.uv[index_new]]), ids

    def triangulate_checked(self, a: FeatureKeyframe, index_a, b: FeatureKeyframe, index_b):
        """Linear triangulation, kept where ORB-SLAM2 CreateNewMapPoints would keep it: rays not
        parallel, in front of both cameras, within the chi-square bound of its level in both, and at distances
        that agree with the levels it was detected at."""
        mapping = self.config.mapping
        uv_a, uv_b = a.features.uv[index_a], b.features.uv[index_b]
        rays_a = self.camera.unproject(uv_a) @ a.T_world_cam[:3, :3].T
        rays_b = self.camera.unproject(uv_b) @ b.T_world_cam[:3, :3].T
        cos_parallax = np.sum(rays_a * rays_b, axis=1) / (
            np.linalg.norm(rays_a, axis=1) * np.linalg.norm(rays_b, axis=1))
        points = self.linear_triangulation(a.T_world_cam, uv_a, b.T_world_cam, uv_b)
        good = (cos_parallax < mapping.max_parallax_cos) & np.isfinite(points).all(axis=1)
        for keyframe, uv, index in ((a, uv_a, index_a), (b, uv_b, index_b)):
            points_cam = transform_points(se3_inverse(keyframe.T_world_cam), points)
            good &= points_cam[:, 2] > 0
            with np.errstate(divide="ignore", invalid="ignore"):
                error2 = np.sum((self.camera.project(points_cam) - uv) ** 2, axis=1)
            good &= error2 < mapping.chi2_two_dof * self.sigma2[keyframe.features.level[index]]
        distance_a = np.linalg.norm(points - a.centre, axis=1)
        distance_b = np.linalg.norm(points - b.centre, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio_distance = distance_a / distance_b
        ratio_octave = self.scales[a.features.level[index_a]] / self.scales[b.features.level[index_b]]
        factor = mapping.scale_consistency * self.config.orb.scale_factor
        good &= (ratio_distance * factor >= ratio_octave) & (ratio_distance <= ratio_octave * factor)
        return points, good

    def linear_triangulation(self, T_world_a, uv_a, T_world_b, uv_b) -> np.ndarray:
        """DLT of each pair of rays (Hartley and Zisserman 12.2), in world coordinates; the checks are ours."""
        points, _ = triangulate(self.camera, T_world_a, uv_a, T_world_b, uv_b,
                                max_reprojection_px=np.inf, min_depth=-np.inf)
        return points

    def add_tracked_points(self, feature_map: FeatureMap, frame_a: int, frame_b: int, uv_a: np.ndarray,
                           uv_b: np.ndarray, points_world: np.ndarray) -> int:
        """Points tracked between two keyframes by other means and triangulated (the feature initializer's KLT
        tracks) join the map as features of both keyframes, described by ORB where the tracks are; returns how
        many."""
        a, b = feature_map.keyframes[frame_a], feature_map.keyframes[frame_b]
        if a.image is None or b.image is None or len(points_world) == 0:
            return 0
        features_a, rows_a = self.extractor.describe(a.image, uv_a)
        features_b, rows_b = self.extractor.describe(b.image, uv_b)
        rows, in_a, in_b = np.intersect1d(rows_a, rows_b, return_indices=True)
        features_a, features_b = features_a.subset(in_a), features_b.subset(in_b)
        distance = np.linalg.norm(points_world[rows] - b.centre, axis=1)
        ids = feature_map.points.add(points_world[rows], features_b.descriptors, b.keyframe_id, distance,
                                     np.zeros(len(rows), np.int64))
        for keyframe, features in ((a, features_a), (b, features_b)):
            keyframe.features = Features.concatenate([keyframe.features, features])
            keyframe.point_ids = np.concatenate([keyframe.point_ids, ids])
            keyframe.bow, keyframe.nodes = self.vocabulary.transform(keyframe.features.descriptors)
            feature_map.reindex(keyframe)
        return len(rows)

    # ------------------------------------------------------------------------------------ adjustment

    def refine_structure(self, feature_map: FeatureMap, keyframes: list[FeatureKeyframe]) -> int:
        """Structure-only bundle adjustment (FDMO eqs. 3-6) of every point the keyframes observe, over their
        observations in those keyframes; outlier observations leave, and a point dies that lies behind a camera
        or that its remaining views no longer see under the parallax a triangulation needs
        (``seen_under_parallax``): the adjustment slides such a point along its nearly parallel rays, to
        millions of metres (teddy, KITTI, parking: up to 1.3e9 m), where it would still be matched in recovery."""
        frame_indices = [k.frame_index for k in keyframes]
        table = feature_map.observations(frame_indices)
        alive = feature_map.points.alive[table.point]
        keyframe_of, feature_of, point_of = table.keyframe[alive], table.feature[alive], table.point[alive]
        if len(point_of) == 0:
            return 0
        point_ids, local_point = np.unique(point_of, return_inverse=True)
        order = np.array(sorted(frame_indices))
        pose_of = np.searchsorted(order, keyframe_of)
        poses = np.array([feature_map.keyframes[int(i)].T_world_cam for i in order])
        uv, level = feature_map.pixels_of(keyframe_of, feature_of)
        refined = refine_points(
            self.camera, poses, feature_map.points.position[point_ids], local_point, pose_of, uv, level,
            scale_factor=self.config.orb.scale_factor, iterations=self.config.mapping.structure_iterations,
        )
        feature_map.points.position[point_ids] = refined.points
        outliers = ~refined.inlier
        feature_map.remove_observations(keyframe_of[outliers], feature_of[outliers])
        keep = refined.in_front & self._seen_under_parallax(feature_map, point_ids, refined.points)
        feature_map.remove_points(point_ids[~keep])
        feature_map.update_normals(point_ids[keep])
        return int(outliers.sum())

    def _seen_under_parallax(self, feature_map: FeatureMap, point_ids: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """(P,) whether the keyframes that observe each of the sorted ``point_ids`` (at ``positions``) see it under the
        parallax a triangulation needs (``seen_under_parallax``)."""
        table = feature_map.observations()
        row = np.minimum(np.searchsorted(point_ids, table.point), len(point_ids) - 1)
        mine = point_ids[row] == table.point
        frames = np.array(sorted(feature_map.keyframes), np.int64)
        centres = np.array([feature_map.keyframes[int(i)].centre for i in frames])
        return seen_under_parallax(positions, row[mine], centres[np.searchsorted(frames, table.keyframe[mine])],
                                   self.config.mapping.max_parallax_cos)

    # ------------------------------------------------------------------------------------ maintenance

    def cull_points(self, feature_map: FeatureMap) -> int:
        """FDMO 4.4: a point must be found in at least 4 of the 7 keyframes after the one that created it, and is
        judged only once those 7 exist; points left with fewer than two views die as well."""
        maintenance = self.config.maintenance
        points = feature_map.points
        newest_id = feature_map.newest().keyframe_id
        table = feature_map.observations()
        observer_id = feature_map.keyframe_ids_of(table.keyframe)
        creator_id = points.first_keyframe[table.point]
        after = (observer_id > creator_id) & (observer_id <= creator_id + maintenance.check_keyframes)
        found = np.bincount(table.point[after], minlength=len(points))
        views = np.bincount(table.point, minlength=len(points))
        in_segment = points.segment == feature_map.segment  # an older segment's were judged in their own
        judged = in_segment & (points.first_keyframe == newest_id - maintenance.check_keyframes)
        spurious = points.alive & ((judged & (found < maintenance.min_found)) | (views < 2))
        feature_map.remove_points(np.flatnonzero(spurious))
        return int(spurious.sum())

    @staticmethod
    def leave_direct_window(feature_map: FeatureMap, direct_window: set[int]) -> None:
        """Keyframes whose direct twin was marginalized may be culled from now on (FeatureMap.settle)."""
        for keyframe in feature_map.keyframes.values():
            if keyframe.in_direct_window and keyframe.frame_index not in direct_window:
                feature_map.settle(keyframe)

    def cull_keyframes(self, feature_map: FeatureMap) -> list[int]:
        """FDMO 4.4 (ORB-SLAM2 KeyFrameCulling): a keyframe whose points are 90 % seen by at least 3 other
        keyframes is removed, once its direct twin has left the window; never one at either end of a loop (ORB-SLAM2's
        loop edges keep theirs)."""
        maintenance = self.config.maintenance
        culled = []
        counts = None  # every point's observers, counted once until a keyframe leaves
        looped = feature_map.loop_keyframes()
        for frame_index in [f for f, k in feature_map.keyframes.items() if not k.in_direct_window and f not in looped]:
            keyframe = feature_map.keyframes[frame_index]
            point_ids = keyframe.point_ids[keyframe.point_ids >= 0]
            if len(point_ids) == 0:
                continue
            if counts is None:
                counts = feature_map.observers_per_point()
            others = counts[point_ids] - 1
            if np.mean(others >= maintenance.redundant_observers) >= maintenance.redundancy:
                feature_map.remove_keyframe(frame_index)
                culled.append(frame_index)
                counts = None  # its views are gone, and the points it leaves with one view die
        return culled


def seen_under_parallax(positions: np.ndarray, point_of: np.ndarray, centres: np.ndarray,
                        max_parallax_cos: float) -> np.ndarray:
    """(P,) whether the views at ``centres`` (one per observation of point ``point_of``) see each point at
    ``positions`` under the parallax a triangulation needs (ORB-SLAM2's: rays whose cosine is below
    ``max_parallax_cos``): the mean resultant length of the unit rays from the views to the point, cos(theta / 2) for
    two rays theta apart, is below that of two rays at the least parallax (with more views, their spread, not one
    stray pair, must carry the depth). A point with no view is not seen."""
    rays = positions[point_of] - centres
    with np.errstate(divide="ignore", invalid="ignore"):
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        sums = np.zeros_like(positions)
        np.add.at(sums, point_of, rays)
        resultant = np.linalg.norm(sums, axis=1) / np.bincount(point_of, minlength=len(positions))
    return resultant < np.sqrt((1.0 + max_parallax_cos) / 2.0)
