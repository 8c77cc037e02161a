"""The start of ``--method features``: two frames, their ORB matches and the homography / fundamental model
selection (ORB-SLAM2 Tracking::MonocularInitialization and CreateInitialMapMonocular).

    a reference frame with enough features                 (its level-0 features are the ones matched)
    each next frame: matches searched in a window around where each reference feature was last matched
        (SearchForInitialization); too few and the next frame becomes the reference
    two-view reconstruction: H and F in parallel, model selection, decomposition, cheirality
        (vo_core/geometry/two_view.py, shared with the other initializers)
    the two keyframes and their points adjusted together, the first held (ORB-SLAM2's global BA at the start)
    scaled so that the first keyframe's median depth is the map's unit; too few points left is a failed start

The result is in the first frame's coordinates; the odometry places it in the world.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vo_core.features.config import FeatureConfig
from vo_core.features.matcher import orientation_consistent, search_by_projection
from vo_core.features.recovery import FrameFeatures
from vo_core.geometry.bundle_adjustment import BundleAdjustmentSettings, WindowProblem, adjust_window
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_inverse, transform_points
from vo_core.geometry.reprojection import CHI2_2D_95, level_information
from vo_core.geometry.two_view import TwoViewConfig, TwoViewFailure, reconstruct


@dataclass
class TwoFrameMap:
    """Two keyframes and the points they both see, in the first frame's coordinates, median depth 1 there."""

    first_index: int
    first_timestamp: float
    first: FrameFeatures
    T_first_second: np.ndarray
    points_first: np.ndarray  # (P, 3)
    feature_first: np.ndarray  # (P,) the feature of each point in the first frame
    feature_second: np.ndarray  # (P,) and in the second
    details: dict = field(default_factory=dict)


@dataclass
class InitializationStep:
    """What one frame did to the start: a map, or why not (``started`` when it became the new reference)."""

    map: TwoFrameMap | None = None
    started: bool = False
    failure: str | None = None
    model: dict | None = None


class OrbInitializer:
    def __init__(self, config: FeatureConfig, camera: PinholeCamera, seed: int, two_view: TwoViewConfig | None = None):
        self.config = config.odometry.initialization
        self.scale_factor = config.orb.scale_factor
        self.camera = camera
        self.two_view = two_view or TwoViewConfig()
        self.rng = np.random.default_rng(seed)
        self.reference: FrameFeatures | None = None
        self.reference_index = -1
        self.reference_timestamp = 0.0
        self.candidates = np.zeros(0, np.int64)  # the reference's level-0 features, the ones matched
        self.previous_uv = np.zeros((0, 2))  # where each of them was matched last (ORB-SLAM2 mvbPrevMatched)
        self.matched_last = np.zeros(0, bool)

    def reset(self) -> None:
        self.reference = None

    def step(self, frame_index: int, timestamp: float, frame: FrameFeatures) -> InitializationStep:
        if self.reference is None or len(frame.features) <= self.config.min_features:
            return self._new_reference(frame_index, timestamp, frame)
        first, second = self._matches(frame)
        if len(first) < self.config.min_matches:
            # ORB-SLAM2 drops the reference; this frame, which has enough features, is the next one.
            step = self._new_reference(frame_index, timestamp, frame)
            step.failure = f"{len(first)} matches with the reference, fewer than {self.config.min_matches}"
            return step
        rows = np.searchsorted(self.candidates, first)
        uv_before, matched_before = self.previous_uv[rows].copy(), self.matched_last[rows]
        self.previous_uv[rows] = frame.features.uv[second]
        self.matched_last[:] = False
        self.matched_last[rows] = True
        try:
            geometry = self._two_view(first, second, frame)
        except TwoViewFailure as failure:
            # A plane leaves two motions that explain both views (Faugeras' ambiguity): the matches the frame
            # before had too are a third view that only the true one explains (ours, as the direct initializer).
            if "ambiguous" not in str(failure) or matched_before.sum() < self.config.min_matches:
                return InitializationStep(failure=str(failure))
            first, second = first[matched_before], second[matched_before]
            try:
                geometry = self._two_view(first, second, frame, [uv_before[matched_before]])
            except TwoViewFailure as again:
                return InitializationStep(failure=str(again))
        scores = geometry.scores
        model = {"model": geometry.model, "score_h": round(scores.score_h, 1), "score_f": round(scores.score_f, 1),
                 "ratio_h": round(scores.ratio, 3), "parallax_deg": round(geometry.parallax_deg, 2)}
        good = geometry.good
        two_frames = self._adjusted(first[good], second[good], frame, geometry.T_first_second,
                                    geometry.points_first[good])
        if two_frames is None or len(two_frames.points_first) < self.config.min_map_points:
            count = 0 if two_frames is None else len(two_frames.points_first)
            self.reset()
            return InitializationStep(failure=f"{count} points after the adjustment, fewer than "
                                              f"{self.config.min_map_points}: new reference", model=model)
        two_frames.details = {**model, "first_frame": self.reference_index, "points": len(two_frames.points_first)}
        self.reset()
        return InitializationStep(map=two_frames, model=model)

    def _two_view(self, first: np.ndarray, second: np.ndarray, frame: FrameFeatures, uv_others=None):
        return reconstruct(self.camera, self.reference.features.uv[first], frame.features.uv[second], self.two_view,
                           self.rng, uv_others)

    def _new_reference(self, frame_index: int, timestamp: float, frame: FrameFeatures) -> InitializationStep:
        if len(frame.features) <= self.config.min_features:
            self.reference = None
            return InitializationStep(failure=f"{len(frame.features)} features, no more than "
                                              f"{self.config.min_features}")
        self.reference, self.reference_index, self.reference_timestamp = frame, frame_index, timestamp
        self.candidates = np.flatnonzero(frame.features.level == 0)
        self.previous_uv = frame.features.uv[self.candidates].copy()
        self.matched_last = np.zeros(len(self.candidates), bool)  # matched in the frame before (not the reference)
        return InitializationStep(started=True)

    def _matches(self, frame: FrameFeatures) -> tuple[np.ndarray, np.ndarray]:
        """ORB-SLAM2 SearchForInitialization: each level-0 reference feature takes the nearest level-0 feature
        within the window around its last match, by the ratio test; one-to-one, rotations consistent."""
        reference = self.reference.features
        found, feature = search_by_projection(
            frame.features, self.previous_uv, reference.descriptors[self.candidates],
            np.zeros(len(self.candidates), np.int64), self.config.search_radius_px,
            max_distance=self.config.max_distance, ratio=self.config.ratio, level_window=0,
            scale_factor=self.scale_factor, available=frame.features.level == 0,
        )
        first = self.candidates[found]
        consistent = orientation_consistent(reference.angle[first], frame.features.angle[feature])
        return first[consistent], feature[consistent]

    def _adjusted(self, first: np.ndarray, second: np.ndarray, frame: FrameFeatures, T_first_second: np.ndarray,
                  points: np.ndarray) -> TwoFrameMap | None:
        """Both views and the points adjusted with the first view held, outliers out, median depth 1."""
        reference = self.reference.features
        count = len(points)
        problem = WindowProblem(
            np.stack([np.eye(4), T_first_second]), np.array([True, False]), points,
            np.repeat([0, 1], count), np.tile(np.arange(count), 2),
            np.vstack([reference.uv[first], frame.features.uv[second]]),
            level_information(np.concatenate([reference.level[first], frame.features.level[second]]),
                              self.scale_factor),
        )
        settings = BundleAdjustmentSettings(huber_px=float(np.sqrt(CHI2_2D_95)),
                                            max_iterations=self.config.ba_iterations, sparse_schur=True)
        solution = adjust_window(self.camera, problem, settings)
        T_first_second = solution.poses_world_cam[1]
        inlier = np.all(solution.errors_after.reshape(2, count) ** 2 <= CHI2_2D_95, axis=0)
        points = solution.points_world
        for T_first_cam in (np.eye(4), T_first_second):
            inlier &= transform_points(se3_inverse(T_first_cam), points)[:, 2] > 0
        if not inlier.any():
            return None
        median_depth = float(np.median(points[inlier, 2]))
        T_first_second = T_first_second.copy()
        T_first_second[:3, 3] /= median_depth
        return TwoFrameMap(self.reference_index, self.reference_timestamp, self.reference, T_first_second,
                           points[inlier] / median_depth, first[inlier], second[inlier])
