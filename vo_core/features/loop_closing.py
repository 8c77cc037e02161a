"""Loop closure over the feature map: ORB-SLAM2's LoopClosing, as LDSO (Gao, Wang, Demmel, Cremers 2018) adds it
to a direct odometry that keeps ORB features on its keyframes.

At every feature keyframe, ``LoopCloser.run`` is the recipe:

1. ``detect``: keyframes outside the new keyframe's covisible neighbourhood that the bag of words finds at least as
   similar as its least similar neighbour, grouped with their covisibles (accumulated scores), and kept only when
   the same place comes back for ``consistency`` keyframes in a row (ORB-SLAM2 DetectLoop, DetectLoopCandidates).
2. ``verify``: per candidate, BoW matches between both keyframes' map points, a Sim(3) by RANSAC, more matches
   guided by it, refined, then refined again on both keyframes' neighbourhoods (each side's points found by the
   other side's keyframes: ours, where ORB-SLAM2 refines on the two keyframes only); then the candidate's whole
   neighbourhood, projected into the keyframe at the pose the Sim(3) gives it, must be found there (ORB-SLAM2
   ComputeSim3).
3. ``correct``: a pose graph over the map's keyframes in Sim(3) (consecutive keyframes, strong covisibility, the
   loop), with the direct window held where it is: the older keyframes and their points move to where the current
   map sees them, so tracking goes on from the same window without a jump, and the loop's duplicate points are
   fused (ORB-SLAM2 CorrectLoop and OptimizeEssentialGraph hold the loop's side instead; LDSO likewise leaves the
   window alone). The trajectory of the frames before follows their keyframes' corrections (``corrections``).

A place of an older segment (a map the direct half started anew after a loss ended, FeatureMap.begin_segment) is
found the same way; it merges that segment into the active map by one similarity (``merge``, ORB-SLAM3's Atlas).

A wrong loop is worse than none: every candidate is reported with why it was taken or refused.

Conventions: poses are T_world_cam; a similarity S_a_b maps points in b's frame into a's (x_a = S_a_b x_b); a
keyframe's correction C = S_world_cam(after) T_world_cam(before)^-1 maps the world points it saw to where they are
now, and a pose T taken relative to the keyframe to C T (its scale dropped from the rotation).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.special import chdtri  # chi2.ppf(p, k) = chdtri(k, 1 - p); scipy.stats costs 0.4 s to import

from vo_core.features.config import LoopClosingConfig, OrbConfig
from vo_core.features.feature_map import Covisibility, FeatureKeyframe, FeatureMap, project_points
from vo_core.features.matcher import match_by_bow, search_by_projection
from vo_core.features.orb import level_sigma2s
from vo_core.features.vocabulary import bow_score
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_inverse, sim3_adjoint, sim3_inverse, sim3_pose, sim3_scale, transform_points
from vo_core.geometry.pose_graph import PoseGraphEdge, optimize_pose_graph
from vo_core.geometry.sim3_solver import (SIM3_DOF, Sim3Matches, Sim3Sightings, ransac_sim3, refine_sim3,
                                          refine_sim3_on_sightings, reprojection_inliers, sim3_information,
                                          sim3_information_on_sightings)


@dataclass
class LoopCandidate:
    """A place the bag of words recognised, and what became of it (``why`` it was refused, "" where accepted)."""

    frame_index: int
    score: float
    consistency: int = 0
    why: str = ""
    bow_matches: int = 0
    inliers: int = 0
    sightings: int = 0  # of either side's points by the other side's keyframes, inliers of the refined Sim(3)
    loop_matches: int = 0
    scale: float | None = None

    def as_details(self) -> dict:
        return {"candidate": self.frame_index, "score": round(self.score, 4), "consistency": self.consistency,
                "accepted": not self.why, "why": self.why or "accepted", "bow_matches": self.bow_matches,
                "inliers": self.inliers, "sightings": self.sightings, "loop_matches": self.loop_matches,
                "scale": None if self.scale is None else round(self.scale, 4)}


@dataclass
class LoopCorrection:
    """An accepted loop and how it moved the map: ``corrections`` holds (timestamp, C) of every keyframe of the map,
    in time order (identity for the held window)."""

    keyframe: int
    loop_keyframe: int
    S_keyframe_loop: np.ndarray
    corrections: list[tuple[float, np.ndarray]]
    moved_keyframes: int
    fused_points: int
    cost_before: float
    cost_after: float
    positions: np.ndarray  # (2, 3) the keyframe's and the loop keyframe's centres after the correction

    def as_details(self) -> dict:
        return {"keyframe": self.keyframe, "loop_keyframe": self.loop_keyframe, "positions": self.positions.tolist(),
                "scale": round(sim3_scale(self.S_keyframe_loop), 4), "moved_keyframes": self.moved_keyframes,
                "fused_points": self.fused_points, "pose_graph_cost": [self.cost_before, self.cost_after]}


@dataclass
class MapMerge:
    """An older segment (a map the direct half started anew after a loss ended) brought into the active map's frame
    and scale by a place seen in both (ORB-SLAM3's Atlas merges its maps so): one similarity moves all of it."""

    keyframe: int
    merged_keyframe: int  # the older segment's keyframe of the place
    segment: int
    S_active_old: np.ndarray  # world -> world: the older segment's poses and points into the active map
    fused_points: int
    positions: np.ndarray  # (2, 3) the keyframe's and the merged keyframe's centres after the merge

    def as_details(self) -> dict:
        return {"keyframe": self.keyframe, "merged_keyframe": self.merged_keyframe, "segment": self.segment,
                "scale": round(sim3_scale(self.S_active_old), 4), "fused_points": self.fused_points,
                "positions": self.positions.tolist()}


@dataclass
class LoopReport:
    """What loop closing did at one keyframe: nothing (``skipped`` says why), candidates tried, a loop, or a merge."""

    keyframe: int
    skipped: str = ""
    candidates: list[LoopCandidate] = field(default_factory=list)
    loop: LoopCorrection | None = None
    merge: MapMerge | None = None
    ms: float = 0.0


@dataclass(frozen=True)
class _Verified:
    """A candidate's Sim(3), and the keyframe's features matched to points of the loop's side."""

    S_keyframe_loop: np.ndarray
    information: np.ndarray  # (7, 7) of S_keyframe_loop's left tangent, from the refinement's inliers
    features: np.ndarray  # feature indices of the keyframe
    points: np.ndarray  # the loop side's point ids they matched


class _Refined(NamedTuple):
    """A Sim(3) refined on both neighbourhoods' sightings."""

    S_keyframe_loop: np.ndarray
    information: np.ndarray  # (7, 7) from the inlying sightings
    sightings: int  # how many of them are inliers


class LoopCloser:
    def __init__(self, config: LoopClosingConfig, orb: OrbConfig, camera: PinholeCamera):
        self.config = config
        self.orb = orb
        self.camera = camera
        self.sigma2 = level_sigma2s(orb)
        self.groups: list[tuple[frozenset[int], int]] = []  # places seen by the last keyframes, and for how many
        self.last_loop_id = 0  # keyframe_id of the last loop or merge (the map's start counts as one)

    def reset(self, first_keyframe_id: int = 0) -> None:
        """A new map, from keyframe ``first_keyframe_id`` on: nothing seen yet."""
        self.groups, self.last_loop_id = [], first_keyframe_id

    def run(self, feature_map: FeatureMap, keyframe: FeatureKeyframe, window: set[int]) -> LoopReport:
        """ORB-SLAM2 LoopClosing::Run for one new keyframe; ``window``: the direct window's frame indices (held)."""
        start = time.perf_counter()
        report = LoopReport(keyframe.frame_index)
        if keyframe.keyframe_id < self.last_loop_id + self.config.min_keyframes_between:
            report.skipped = f"within {self.config.min_keyframes_between} keyframes of the map's start or last loop"
            return report
        graph = feature_map.covisibility_graph()
        report.candidates = self.detect(feature_map, graph, keyframe)
        for candidate in report.candidates:
            if candidate.why:
                continue
            verified = self.verify(feature_map, graph, keyframe, candidate)
            if verified is None:
                continue
            if feature_map.keyframes[candidate.frame_index].segment == keyframe.segment:
                report.loop = self.correct(feature_map, graph, keyframe, candidate, verified, window)
                if report.loop is None:
                    continue
                feature_map.loop_edges.add((candidate.frame_index, keyframe.frame_index))
            else:
                report.merge = self.merge(feature_map, keyframe, candidate.frame_index, verified)
            self.last_loop_id, self.groups = keyframe.keyframe_id, []
            for other in report.candidates:  # one loop per keyframe, as ORB-SLAM2
                if other is not candidate and not other.why:
                    other.why = f"another candidate ({candidate.frame_index}) closed the loop"
            break
        report.ms = (time.perf_counter() - start) * 1000.0
        return report

    # ------------------------------------------------------------------------------------ 1. detect

    def detect(self, feature_map: FeatureMap, graph: Covisibility, keyframe: FeatureKeyframe) -> list[LoopCandidate]:
        """The places recognised for the keyframe: refused ones say why (not consistent yet)."""
        scored = self._recognised(feature_map, graph, keyframe)
        groups, candidates = [], []
        for frame_index, score in scored.items():
            group = frozenset({frame_index, *graph.covisible_keyframes(frame_index, self.config.covisible_min_weight)})
            consistency = max((count + 1 for previous, count in self.groups if group & previous), default=0)
            groups.append((group, consistency))
            candidate = LoopCandidate(frame_index, score, consistency)
            if consistency < self.config.consistency:
                candidate.why = f"seen by {consistency + 1} keyframes in a row, not yet {self.config.consistency + 1}"
            candidates.append(candidate)
        self.groups = groups
        return candidates

    def _recognised(self, feature_map: FeatureMap, graph: Covisibility, keyframe: FeatureKeyframe) -> dict[int, float]:
        """ORB-SLAM2 DetectLoopCandidates: keyframes outside the neighbourhood scoring at least the least similar
        neighbour, by groups (a candidate with its best covisibles, scores summed); the best of each group within
        ``group_score_ratio`` of the best group. Returns candidate -> its own score, best first."""
        config = self.config
        neighbours = set(graph.covisible_keyframes(keyframe.frame_index, config.covisible_min_weight))
        # The least similar neighbour sets the bar (1: nothing to compare with, nothing is recognised).
        min_score = min((bow_score(keyframe.bow, feature_map.keyframes[n].bow) for n in neighbours), default=1.0)
        others = set(feature_map.keyframes) - neighbours - {keyframe.frame_index}
        scores = {k: s for k, s, _ in feature_map.index.query(keyframe.bow, restrict_to=others) if s >= min_score}
        if not scores:
            return {}
        best_of_group = {}
        for frame_index in scores:
            group = [k for k in (frame_index, *graph.covisible_keyframes(frame_index, 1, config.group_neighbours))
                     if k in scores]
            best_of_group[frame_index] = (sum(scores[k] for k in group), max(group, key=scores.get))
        bar = config.group_score_ratio * max(total for total, _ in best_of_group.values())
        chosen = {best for total, best in best_of_group.values() if total >= bar}
        return {k: scores[k] for k in sorted(chosen, key=lambda k: -scores[k])}

    # ------------------------------------------------------------------------------------ 2. verify

    def verify(self, feature_map: FeatureMap, graph: Covisibility, keyframe: FeatureKeyframe,
               candidate: LoopCandidate) -> _Verified | None:
        """ORB-SLAM2 ComputeSim3 for one candidate; a refusal is written into ``candidate.why``."""
        config = self.config
        loop = feature_map.keyframes[candidate.frame_index]
        features, points = self._bow_matches(feature_map, keyframe, loop)
        candidate.bow_matches = len(features)
        if len(features) < config.min_bow_matches:
            candidate.why = f"{len(features)} BoW matches of map points, fewer than {config.min_bow_matches}"
            return None
        rng = np.random.default_rng(keyframe.frame_index)  # deterministic: the same run closes the same loops
        fit = ransac_sim3(self._matches(feature_map, keyframe, features, loop, points), self.camera, rng,
                          min_inliers=config.ransac_min_inliers, max_iterations=config.ransac_max_iterations,
                          chi2=config.ransac_chi2, probability=config.ransac_probability)
        if fit is None:
            candidate.why = f"no Sim(3) with {config.ransac_min_inliers} inliers among {len(features)} matches"
            return None
        # More of the loop keyframe's points, found where the Sim(3) puts them (ORB-SLAM2 SearchBySim3), then refined.
        more_features, more_points = self._found(feature_map, keyframe, loop.frame_index, fit.S_a_b,
                                                 feature_map.points_of([loop.frame_index]), features, points,
                                                 with_points_only=True)
        features, points = np.concatenate([features, more_features]), np.concatenate([points, more_points])
        matches = self._matches(feature_map, keyframe, features, loop, points)
        fit = refine_sim3(matches, self.camera, fit.S_a_b, chi2=config.refine_chi2,
                          iterations=config.refine_iterations)
        candidate.inliers = fit.num_inliers
        if fit.num_inliers < config.min_refined_inliers:
            candidate.why = f"{fit.num_inliers} inliers after refinement, fewer than {config.min_refined_inliers}"
            return None
        # Two keyframes' matches say little of the scale where the two views coincide, a loop's usual case (the
        # similarity's scale then hardly moves a reprojection: KITTI played twice, 0.996 -> 0.264 in the refinement
        # above), and the neighbourhoods' refinement only finds the optimum nearest its start. It starts twice: from
        # the matches' similarity and from the same without its change of scale (one map keeps one scale where it
        # has not drifted); the one more sightings agree with is kept.
        refined = max((self._refined_on_neighbourhoods(feature_map, graph, keyframe, candidate, start)
                       for start in (fit.S_a_b, sim3_pose(fit.S_a_b))), key=lambda r: r.sightings)
        S_keyframe_loop, information, candidate.sightings = refined
        candidate.scale = sim3_scale(S_keyframe_loop)
        kept = reprojection_inliers(matches, self.camera, S_keyframe_loop, config.refine_chi2)
        features, points = features[kept], points[kept]
        # The loop's whole neighbourhood, seen from the pose the Sim(3) gives the keyframe, must be found there.
        neighbourhood = [loop.frame_index, *graph.covisible_keyframes(loop.frame_index, 1)]
        found_features, found_points = self._found(feature_map, keyframe, loop.frame_index, S_keyframe_loop,
                                                   feature_map.points_of(neighbourhood), features, points,
                                                   with_points_only=False)
        candidate.loop_matches = len(features) + len(found_features)
        if candidate.loop_matches < config.min_loop_matches:
            candidate.why = (f"{candidate.loop_matches} matches with the loop's neighbourhood, fewer than "
                             f"{config.min_loop_matches}")
            return None
        return _Verified(S_keyframe_loop, information, np.concatenate([features, found_features]),
                         np.concatenate([points, found_points]))

    def _refined_on_neighbourhoods(self, feature_map: FeatureMap, graph: Covisibility, keyframe: FeatureKeyframe,
                                   candidate: LoopCandidate, S_keyframe_loop: np.ndarray) -> _Refined:
        """The Sim(3) refined on the two neighbourhoods, not the two keyframes: the loop side's points found by the
        keyframe's side's keyframes, and the other way round, each searched where the Sim(3) puts it. Between two
        keyframes a narrow view of a far scene trades rotation against translation, and the scale rests on their
        own points' depths; the neighbourhoods bring more points, each triangulated on its own, seen from keyframes
        with baseline between them over a wider field, and their errors average out (tests/
        test_geometry_sim3_solver.py: a side of three keyframes halves the errors at least), from the start
        ``S_keyframe_loop``."""
        loop = feature_map.keyframes[candidate.frame_index]
        order = {f: k.keyframe_id for f, k in feature_map.keyframes.items()
                 if k.segment in (keyframe.segment, loop.segment)}
        own_side, loop_side = self._sides(graph, keyframe.frame_index, loop.frame_index, order)
        own_points, loop_points = feature_map.points_of(own_side), feature_map.points_of(loop_side)
        # A point both sides observe (fused by an earlier loop) already ties them where the map put it: no measure.
        into_own = self._sightings(feature_map, own_side, keyframe, loop, S_keyframe_loop,
                                   np.setdiff1d(loop_points, own_points))
        into_loop = self._sightings(feature_map, loop_side, loop, keyframe, sim3_inverse(S_keyframe_loop),
                                    np.setdiff1d(own_points, loop_points))
        S_keyframe_loop, inliers_own, inliers_loop = refine_sim3_on_sightings(
            into_own, into_loop, self.camera, S_keyframe_loop, chi2=self.config.refine_chi2,
            iterations=self.config.refine_iterations)
        information = sim3_information_on_sightings(into_own.subset(inliers_own), into_loop.subset(inliers_loop),
                                                    self.camera, S_keyframe_loop)
        inlying = int(np.count_nonzero(inliers_own) + np.count_nonzero(inliers_loop))
        return _Refined(S_keyframe_loop, information, inlying)

    def _sightings(self, feature_map: FeatureMap, seers: list[int], seer_reference: FeatureKeyframe,
                   seen_reference: FeatureKeyframe, S_seer_seen: np.ndarray, point_ids: np.ndarray) -> Sim3Sightings:
        """The seen side's points found by each keyframe of the seeing side (``seers``), projected at the pose the
        Sim(3) S_seer_seen (seer reference <- seen reference) gives it in the seen side's map, and searched among
        all its features (ORB-SLAM2 SearchByProjection at ComputeSim3's radius)."""
        positions = feature_map.points.position
        S_world_seer = seen_reference.T_world_cam @ sim3_inverse(S_seer_seen)  # the seer reference in the seen map
        T_seen_world = se3_inverse(seen_reference.T_world_cam)
        parts = []
        for frame in seers:
            seer = feature_map.keyframes[frame]
            T_view_reference = se3_inverse(seer.T_world_cam) @ seer_reference.T_world_cam
            T_world_view = sim3_pose(S_world_seer @ se3_inverse(T_view_reference))
            view = project_points(feature_map.points, point_ids, T_world_view, self.camera, self.orb)
            index_point, index_feature = search_by_projection(
                seer.features, view.uv, feature_map.points.descriptor[view.point_ids], view.level,
                self.config.projection_radius_px, scale_factor=self.orb.scale_factor)
            parts.append(Sim3Sightings(
                transform_points(T_seen_world, positions[view.point_ids[index_point]]),
                np.broadcast_to(T_view_reference, (len(index_point), 4, 4)), seer.features.uv[index_feature],
                self.sigma2[seer.features.level[index_feature]]))
        return Sim3Sightings.concatenate(parts)

    def _sides(self, graph: Covisibility, keyframe: int, loop_frame: int,
               order: dict[int, int]) -> tuple[list[int], list[int]]:
        """Each end of the loop with its best covisible keyframes made nearer (by ``order``, creation) to it than
        to the other end: after an earlier loop the loop keyframe's neighbours may include keyframes of the current
        side, which must not be taken for the loop's."""
        return tuple([frame, *(n for n in graph.covisible_keyframes(frame, self.config.covisible_min_weight,
                                                                     self.config.group_neighbours)
                               if n in order and abs(order[n] - order[frame]) < abs(order[n] - order[other]))]
                     for frame, other in ((keyframe, loop_frame), (loop_frame, keyframe)))

    def _bow_matches(self, feature_map: FeatureMap, keyframe: FeatureKeyframe,
                     loop: FeatureKeyframe) -> tuple[np.ndarray, np.ndarray]:
        """ORB-SLAM2 SearchByBoW(KF, KF): the keyframe's features with a map point matched to the loop keyframe's.
        Returns (feature indices of the keyframe, point ids of the loop keyframe)."""
        mine, theirs = self._with_points(feature_map, keyframe), self._with_points(feature_map, loop)
        index_a, index_b = match_by_bow(keyframe.features.subset(mine), keyframe.nodes[mine],
                                        loop.features.subset(theirs), loop.nodes[theirs],
                                        max_distance=self.config.bow_max_distance, ratio=self.config.bow_ratio)
        return mine[index_a], loop.point_ids[theirs[index_b]]

    @staticmethod
    def _with_points(feature_map: FeatureMap, keyframe: FeatureKeyframe) -> np.ndarray:
        observed = keyframe.observed()
        return observed[feature_map.points.alive[keyframe.point_ids[observed]]]

    def _matches(self, feature_map: FeatureMap, keyframe: FeatureKeyframe, features: np.ndarray,
                 loop: FeatureKeyframe, points: np.ndarray) -> Sim3Matches:
        """The keyframe's points (its features' own) and the loop keyframe's matched points (each one it observes),
        each in its camera's frame as that keyframe sees it (``_seen_by``), with where each keyframe saw them."""
        loop_features = _observing_features(loop, points)
        return Sim3Matches(
            points_a=_seen_by(feature_map, keyframe, features), points_b=_seen_by(feature_map, loop, loop_features),
            uv_a=keyframe.features.uv[features], uv_b=loop.features.uv[loop_features],
            sigma2_a=self.sigma2[keyframe.features.level[features]],
            sigma2_b=self.sigma2[loop.features.level[loop_features]])

    def _found(self, feature_map: FeatureMap, keyframe: FeatureKeyframe, loop_frame: int, S_keyframe_loop: np.ndarray,
               point_ids: np.ndarray, matched_features: np.ndarray, matched_points: np.ndarray,
               with_points_only: bool) -> tuple[np.ndarray, np.ndarray]:
        """Points of the loop's side not matched yet, projected into the keyframe at the pose the Sim(3) gives it
        in the loop's map, and searched among its features not matched yet (with a map point of their own where
        ``with_points_only``: the Sim(3) needs both ends). Returns (feature indices, point ids)."""
        T_world_keyframe = sim3_pose(feature_map.keyframes[loop_frame].T_world_cam @ sim3_inverse(S_keyframe_loop))
        point_ids = np.setdiff1d(point_ids, matched_points)
        view = project_points(feature_map.points, point_ids, T_world_keyframe, self.camera, self.orb)
        available = np.ones(len(keyframe.features), bool)
        available[matched_features] = False
        if with_points_only:
            available &= keyframe.point_ids >= 0
        index_point, index_feature = search_by_projection(
            keyframe.features, view.uv, feature_map.points.descriptor[view.point_ids], view.level,
            self.config.projection_radius_px, scale_factor=self.orb.scale_factor, available=available)
        return index_feature, view.point_ids[index_point]

    # ------------------------------------------------------------------------------------ 3. correct

    def correct(self, feature_map: FeatureMap, graph: Covisibility, keyframe: FeatureKeyframe,
                candidate: LoopCandidate, verified: _Verified, window: set[int]) -> LoopCorrection | None:
        """The pose graph (ORB-SLAM2 OptimizeEssentialGraph) with the window held, the keyframes and points moved
        by it, and the loop's matches fused; None, the map left as it was and ``candidate.why`` set, where the
        corrected map is not consistent with the measurements: its cost (every edge's error weighted by its
        information, so a chi-square variable when the loop and the odometry agree) above the chi-square bound of
        the graph's degrees of freedom at ``pose_graph_chi2_probability``. The loop's Sim(3) and the odometry then
        disagree by more than their informations allow, and one of them is wrong."""
        loop_frame = candidate.frame_index
        frames = [k.frame_index for k in feature_map.active_keyframes()]  # in order of creation
        row = {frame_index: i for i, frame_index in enumerate(frames)}  # each keyframe's node
        before = np.array([feature_map.keyframes[f].T_world_cam for f in frames])
        edges = self._essential_graph(feature_map, row, before, graph) + self._loop_edges(
            row, before, graph, keyframe.frame_index, loop_frame, verified)
        held = np.array([f in window for f in frames])
        result = optimize_pose_graph(before, edges, held, iterations=self.config.pose_graph_iterations)
        degrees_of_freedom = SIM3_DOF * (len(edges) - int(np.count_nonzero(~held)))
        bound = float(chdtri(max(degrees_of_freedom, 1), 1.0 - self.config.pose_graph_chi2_probability))
        if result.cost_after > bound:
            candidate.why = (f"the corrected map disagrees with its measurements: pose graph cost "
                             f"{result.cost_after:.0f} over the {self.config.pose_graph_chi2_probability:.0%} "
                             f"chi-square bound {bound:.0f} of its {degrees_of_freedom} degrees of freedom")
            return None
        corrections = result.S_world_nodes @ np.array([se3_inverse(T) for T in before])
        self._move_points(feature_map, row, corrections)
        for frame_index, S_world_cam in zip(frames, result.S_world_nodes):
            feature_map.keyframes[frame_index].place(S_world_cam)
        fused = self._fuse(feature_map, keyframe, verified)
        timed = sorted((feature_map.keyframes[f].timestamp, C) for f, C in zip(frames, corrections))
        positions = np.array([keyframe.centre, feature_map.keyframes[loop_frame].centre])
        return LoopCorrection(keyframe.frame_index, loop_frame, verified.S_keyframe_loop, timed,
                              int(np.count_nonzero(~held)), fused, result.cost_before, result.cost_after, positions)

    def merge(self, feature_map: FeatureMap, keyframe: FeatureKeyframe, merged_frame: int,
              verified: _Verified) -> MapMerge:
        """The older segment of ``merged_frame`` joins the active map: its keyframes and points moved by the one
        similarity that puts the merged keyframe where the Sim(3) says the keyframe sees it, and the place's
        duplicate points fused. The active map does not move (tracking goes on in it)."""
        merged = feature_map.keyframes[merged_frame]
        segment = merged.segment
        S_active_old = keyframe.T_world_cam @ verified.S_keyframe_loop @ se3_inverse(merged.T_world_cam)
        for other in feature_map.keyframes.values():
            if other.segment == segment:
                other.place(S_active_old @ other.T_world_cam)
                other.segment = feature_map.segment
        points = feature_map.points
        moved = np.flatnonzero(points.alive & (points.segment == segment))
        _move(points, moved, S_active_old)
        points.segment[moved] = feature_map.segment
        feature_map.update_normals(moved)
        fused = self._fuse(feature_map, keyframe, verified)
        return MapMerge(keyframe.frame_index, merged_frame, segment, S_active_old, fused,
                        np.array([keyframe.centre, merged.centre]))

    def _essential_graph(self, feature_map: FeatureMap, row: dict[int, int], poses: np.ndarray,
                         graph: Covisibility) -> list[PoseGraphEdge]:
        """Consecutive keyframes (the odometry), strongly covisible pairs and the loop edges of the loops closed
        before (ORB-SLAM2's: their fused points may be too few for a covisibility edge), each at its present relative
        pose, as sure of it as their shared points make it (``_shared_information``); ``row``: each keyframe's node,
        in order of creation."""
        frames = list(row)
        pairs = {(i, i + 1) for i in range(len(frames) - 1)}
        pairs |= {(row[older], row[newer]) for older, newer in feature_map.loop_edges if older in row and newer in row}
        for i, frame_index in enumerate(frames):
            for other in graph.covisible_keyframes(frame_index, self.config.essential_min_weight):
                if other in row:  # the active map's
                    pairs.add((min(i, row[other]), max(i, row[other])))
        edges = []
        for i, j in sorted(pairs):
            S_i_j = se3_inverse(poses[i]) @ poses[j]
            information = self._shared_information(feature_map, frames[i], frames[j], S_i_j)
            edges.append(PoseGraphEdge(i, j, S_i_j, information=information))
        _hold_odometry_scale(edges)
        return edges

    def _shared_information(self, feature_map: FeatureMap, frame_a: int, frame_b: int,
                            S_a_b: np.ndarray) -> np.ndarray:
        """The information of the relative pose S_a_b that the points both keyframes observe give it, in the units
        of the loop's (``sim3_information`` of their two-way reprojection errors, those within ``refine_chi2``),
        plus the identity (the unit information every edge had, ORB-SLAM2's): a pair sharing no point still
        pulls a little, one sharing many is as stiff as its points make it."""
        a, b = feature_map.keyframes[frame_a], feature_map.keyframes[frame_b]
        observed_a, observed_b = self._with_points(feature_map, a), self._with_points(feature_map, b)
        _, index_a, index_b = np.intersect1d(a.point_ids[observed_a], b.point_ids[observed_b], return_indices=True)
        matches = self._matches(feature_map, a, observed_a[index_a], b, a.point_ids[observed_a[index_a]])
        inliers = reprojection_inliers(matches, self.camera, S_a_b, self.config.refine_chi2)
        return np.eye(SIM3_DOF) + sim3_information(matches.subset(inliers), self.camera, S_a_b)

    def _loop_edges(self, row: dict[int, int], poses: np.ndarray, graph: Covisibility, keyframe: int,
                    loop_frame: int, verified: _Verified) -> list[PoseGraphEdge]:
        """The loop joins both neighbourhoods, not only its two keyframes (ORB-SLAM2's LoopConnections): an edge
        between each keyframe near the keyframe and each near the loop keyframe, at their relative pose once the
        loop's side is moved rigidly onto the keyframe's by the Sim(3). With one edge, the stiffness of the many
        covisibility edges on either side kept half the loop's error (the circuit preset played twice).

        Each edge is as sure as the Sim(3) is, in the directions it is sure of (``_loop_information``): the essential
        graph counts a point once for every pair of keyframes that observe it, and the Sim(3)'s matches are points
        observed on both sides, so by that same count they enter every pair across the loop. Its well-determined
        directions then pull hard, and the rotation a narrow view trades against translation pulls no harder than
        the odometry that disagrees with it (the circuit's 240-frame seed-0 second loop, 1.8 deg off)."""
        loop_onto_keyframe = poses[row[keyframe]] @ verified.S_keyframe_loop @ se3_inverse(poses[row[loop_frame]])
        sides = self._sides(graph, keyframe, loop_frame, row)
        edges = []
        for i in sides[0]:
            for j in sides[1]:
                S_i_j = se3_inverse(poses[row[i]]) @ loop_onto_keyframe @ poses[row[j]]
                T_i_keyframe = se3_inverse(poses[row[i]]) @ poses[row[keyframe]]
                edges.append(PoseGraphEdge(row[i], row[j], S_i_j,
                                           information=_loop_information(verified, T_i_keyframe, S_i_j)))
        return edges

    @staticmethod
    def _move_points(feature_map: FeatureMap, row: dict[int, int], corrections: np.ndarray) -> None:
        """Each point moves with the oldest keyframe that observes it (the one whose view placed it first); ``row``:
        each keyframe's correction."""
        table = feature_map.observations(list(row))
        if len(table.point) == 0:
            return
        observer = np.array([row[k] for k in table.keyframe.tolist()], np.int64)
        oldest = np.full(len(feature_map.points), len(row), np.int64)
        np.minimum.at(oldest, table.point, observer)
        moved = np.flatnonzero(oldest < len(row))
        for i in np.unique(oldest[moved]):
            _move(feature_map.points, moved[oldest[moved] == i], corrections[i])
        feature_map.update_normals(moved)

    @staticmethod
    def _fuse(feature_map: FeatureMap, keyframe: FeatureKeyframe, verified: _Verified) -> int:
        """The keyframe's features matched to the loop's points observe those from now on; a point of its own
        there is a duplicate, merged into the loop's (ORB-SLAM2 CorrectLoop's fusion)."""
        features, points = verified.features, verified.points
        _, first = np.unique(points, return_index=True)  # one feature per loop point
        features, points = features[first], points[first]
        own = keyframe.point_ids[features]
        duplicate = (own >= 0) & (own != points) & ~np.isin(own, points)
        feature_map.merge_points(own[duplicate], points[duplicate])
        # A point the keyframe observes at another feature keeps that observation: one per point and keyframe.
        elsewhere = np.isin(points, keyframe.point_ids[np.setdiff1d(keyframe.observed(), features)])
        keyframe.point_ids[features[~elsewhere]] = points[~elsewhere]
        feature_map.representative_descriptors(points)
        feature_map.update_normals(points)
        return int(np.count_nonzero(duplicate))


def _hold_odometry_scale(edges: list[PoseGraphEdge]) -> None:
    """Each odometry edge (consecutive keyframes) made at least as sure of its change of scale as the map's median
    odometry edge. Two keyframes a few centimetres apart see their shared points from nearly one place, so the
    points' reprojections barely tell the pair's change of scale (its information grows as (baseline / depth)^2),
    and where the keyframes between them were culled the pair shares few points: a run of keyframes between two such
    pairs floats in scale, and the pose graph spends that scale on the loop's error instead of bending the stiffer
    rotations and translations (TUM fr1/desk played backward, seed 0: its first loop rescaled keyframes 257-416 by
    1.5-2x, and loop closure took the run from 0.109 to 0.129 m). The direct window measured every consecutive pair's
    scale the same way, on points all its keyframes see; a typical pair's information is what that is worth, and
    the median is the typical pair's, whatever the scene's depth and the camera's speed."""
    odometry = [edge for edge in edges if edge.j == edge.i + 1]
    if not odometry:
        return
    scale = SIM3_DOF - 1  # the tangent's last component, log of the scale (v, w, sigma)
    floor = float(np.median([edge.information[scale, scale] for edge in odometry]))
    for edge in odometry:
        edge.information[scale, scale] = max(edge.information[scale, scale], floor)


def _loop_information(verified: _Verified, T_i_keyframe: np.ndarray, S_i_j: np.ndarray) -> np.ndarray:
    """The Sim(3)'s information carried to the loop edge (i, j) it measures, S_i_j = T_i_keyframe S_keyframe_loop B:
    a left change exp(d) of S_keyframe_loop is the right change r = M d of S_i_j, M = Adj(S_i_j^-1 T_i_keyframe),
    so the information of r is M^-T Lambda M^-1; plus the identity, as every essential edge (``_shared_information``),
    which keeps it positive definite where the matches leave a direction undetermined."""
    to_edge_inverse = np.linalg.inv(sim3_adjoint(sim3_inverse(S_i_j) @ T_i_keyframe))
    carried = to_edge_inverse.T @ verified.information @ to_edge_inverse
    return 0.5 * (carried + carried.T) + np.eye(SIM3_DOF)


def _seen_by(feature_map: FeatureMap, keyframe: FeatureKeyframe, features: np.ndarray) -> np.ndarray:
    """The map points of the keyframe's ``features``, (N, 3) in its camera frame, as it saw them when its pose became
    final (FeatureKeyframe.seen_points) where it did, else where the map has them now. A loop's similarity relates
    two keyframes' views, and an old keyframe's points have since been adjusted at later poses: on fr1/desk, whose
    direct map shrinks before its second map begins, a new map's keyframes and the first map's found the right places
    (their bag-of-words matches on the ground truth's epipolar lines) and RANSAC no similarity that 20 of 20-43 of
    them agree with, the old keyframes' points 3-6 px off their own features (median); with the views they settled on,
    both runs of two maps merged them."""
    now = feature_map.in_camera(keyframe, keyframe.point_ids[features])
    if keyframe.seen_points is None:
        return now
    then = keyframe.seen_points[features]
    return np.where(np.isfinite(then[:, :1]), then, now)


def _observing_features(keyframe: FeatureKeyframe, point_ids: np.ndarray) -> np.ndarray:
    """The feature of ``keyframe`` that observes each of ``point_ids`` (each one it observes; of two features on one
    point, the later)."""
    observed = keyframe.observed()
    order = np.argsort(keyframe.point_ids[observed], kind="stable")
    sorted_ids = keyframe.point_ids[observed][order]
    return observed[order][np.searchsorted(sorted_ids, point_ids, side="right") - 1]


def _move(points, point_ids: np.ndarray, S: np.ndarray) -> None:
    """Points moved by a similarity (world -> world), their reference distances (the scale prediction) with it."""
    points.position[point_ids] = transform_points(S, points.position[point_ids])
    points.reference_distance[point_ids] *= sim3_scale(S)
