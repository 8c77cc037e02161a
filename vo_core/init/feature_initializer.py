"""The feature-based initializer of the direct system (paper 004, Algorithm 1 "trackFrame").

1. Corners in the reference frame, tracked frame to frame by KLT with a forward-backward check (3.1); fewer
   surviving tracks than a start needs give up this reference (the odometry then starts again from its next frame).
2. From the N-th frame on (N = 4), each frame is tried against the reference: homography and fundamental
   matrix in parallel, model selection, decomposition and cheirality (3.2, vo_core/geometry/two_view.py), with
   ORB-SLAM's acceptance rules (1 degree of parallax, 50 well-triangulated points explaining 90 % of the
   model's inliers, one clearly best decomposition); no model is chosen where neither clearly wins (R_H between
   ORB-SLAM's two thresholds, 0.40 and 0.45).
3. Geometric bundle adjustment over every frame of the window with severe- and normal-outlier removal
   (3.2, vo_core/init/geometric_ba.py); fewer than 50 points left is a wrong start.
4. DSO-selected pixels of the reference frame get inverse depths by epipolar line search through the window
   and Gaussian fusion, the adjusted feature points around them as prior (3.3,
   vo_core/init/semi_dense_depth.py); the features themselves are handed over too.
5. Photometric bundle adjustment of the window's poses and the points' inverse depths (3.4,
   vo_core/init/photometric_ba.py: the direct system's window optimizer); points whose patches then disagree
   with the window frames beyond 2.571 sigma of a fitted Student-t leave (3.4,
   vo_core/init/photometric_outliers.py); a final photometric bundle adjustment of what is left (004's order,
   "ORBInitializer v3").

The map is scaled as DSO expects, mean inverse depth 1 in the first keyframe, before the photometric
adjustments (their thresholds are DSO's, set for that scale) and again in the result.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from vo_core.direct.config import DirectConfig
from vo_core.direct.initialization import InitializationResult
from vo_core.direct.pixel_selector import PixelSelector
from vo_core.direct.pyramid import ImagePyramid
from vo_core.direct.window import WindowReport
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_inverse
from vo_core.geometry.two_view import TwoViewFailure, reconstruct
from vo_core.init.config import InitConfig, SemiDenseConfig
from vo_core.init.geometric_ba import adjust_with_outlier_removal, initial_poses
from vo_core.init.klt_tracks import FeatureTracks
from vo_core.init.photometric_ba import make_photometric_ba, photometric_bundle_adjustment
from vo_core.init.photometric_outliers import photometric_inliers
from vo_core.init.semi_dense_depth import InverseDepths, search_and_fuse


def gray_image(pyramid: ImagePyramid) -> np.ndarray:
    """The full-resolution photometric image as uint8 for corner detection and KLT."""
    return np.clip(np.round(pyramid[0].intensity), 0, 255).astype(np.uint8)


@dataclass
class InitialMap:
    """The map being refined: points in the reference frame (the features first) and the window's poses."""

    uv: np.ndarray  # (N, 2) level-0 pixels in the reference
    depths: InverseDepths
    is_feature: np.ndarray  # (N,) bool
    poses_world_cam: np.ndarray  # (F, 4, 4), the reference's the identity
    uv_last: np.ndarray  # (N, 2) where the features' tracks end, in the last frame (NaN for the other points)

    def subset(self, keep: np.ndarray) -> "InitialMap":
        return InitialMap(self.uv[keep], self.depths.subset(keep), self.is_feature[keep], self.poses_world_cam,
                          self.uv_last[keep])

    def normalized(self) -> "InitialMap":
        """Rescaled so the mean inverse depth is 1 (DSO initializeFromInitializer); translations scale with it."""
        factor = float(np.mean(self.depths.mean))
        poses = self.poses_world_cam.copy()
        poses[:, :3, 3] *= factor
        depths = InverseDepths(self.depths.mean / factor, self.depths.variance / factor**2, self.depths.updates)
        return InitialMap(self.uv, depths, self.is_feature, poses, self.uv_last)


class FeatureInitializer:
    name = "features"

    def __init__(self, config: InitConfig, direct: DirectConfig, camera: PinholeCamera, seed: int):
        self.config = config
        self.selector = direct.selector
        self.point_density = direct.point_density
        self.photometric_ba = make_photometric_ba(direct, config.photometric_ba)
        self.camera = camera
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.max_frames = config.max_frames
        self.tracks: FeatureTracks | None = None
        self.reference: ImagePyramid | None = None
        self.pyramids: list[ImagePyramid] = []  # every frame of the window, the reference first
        self.exposures: list[float | None] = []  # their exposure times, where known
        self._status: dict[str, Any] = {"stage": "waiting for a reference frame"}

    @property
    def started(self) -> bool:
        return self.tracks is not None

    def status(self) -> dict[str, Any]:
        return dict(self._status)

    def set_first(self, frame_index: int, pyramid: ImagePyramid, exposure: float | None) -> None:
        self.reference = pyramid
        self.pyramids = [pyramid]
        self.exposures = [exposure]
        self.tracks = FeatureTracks(self.config.tracks, gray_image(pyramid), frame_index)
        self._status = {"stage": "tracking", "corners": self.tracks.num_alive}

    def track(self, frame_index: int, pyramid: ImagePyramid, exposure: float | None) -> InitializationResult | None:
        tracks = self.tracks
        alive = tracks.add(frame_index, gray_image(pyramid))
        self.pyramids.append(pyramid)
        self.exposures.append(exposure)
        self._status = {"stage": "tracking", "tracks_kept": alive, "frames": tracks.num_frames}
        # Algorithm 1's MIN_NUM_MATCHES (its value not given): the reference is given up once no start can come from
        # it, with fewer tracks than a start's well-triangulated points (ORB-SLAM's minTriangulated). A count of our
        # own (80) gave up VAMR parking's references (about 100 corners) at a third of its frame rate until frame 45.
        needed = self.config.two_view.min_triangulated
        if alive < needed:
            self._reject(f"{alive} tracks survived, fewer than the {needed} a start needs: new reference")
            self.tracks = None  # not started: the odometry hands the next frame as the new reference
            return None
        if tracks.num_frames < self.config.tracks.num_frames:
            return None
        return self._attempt(tracks)

    def _reject(self, reason: str, **details) -> None:
        self._status.update(details, stage="rejected", reason=reason)

    def _attempt(self, tracks: FeatureTracks) -> InitializationResult | None:
        window = tracks.window()
        flow = float(np.median(np.linalg.norm(window[-1] - window[0], axis=1)))
        if flow < self.config.tracks.min_median_flow_px:
            self._reject(f"no motion: median flow {flow:.2f} px since the reference")
            return None
        try:
            geometry = reconstruct(
                self.camera, window[0], window[-1], self.config.two_view, self.rng, list(window[1:-1])
            )
        except TwoViewFailure as failure:
            self._reject(str(failure))
            return None
        scores = geometry.scores
        model_details = {
            "model": geometry.model, "score_h": round(scores.score_h, 1), "score_f": round(scores.score_f, 1),
            "ratio_h": round(scores.ratio, 3), "parallax_deg": round(geometry.parallax_deg, 2),
            "baseline_depth_ratio": round(geometry.baseline_depth_ratio, 4),
        }
        low, high = self.config.model_choice.ambiguous_ratio_h
        if low < scores.ratio <= high:
            self._reject(f"no clear winner between the models: R_H {scores.ratio:.3f} in ({low}, {high}]",
                         **model_details)
            return None
        good = geometry.good
        observations = window[:, good]
        poses = initial_poses(self.camera, observations, geometry.points_first[good], geometry.T_first_second)
        estimate = adjust_with_outlier_removal(
            self.camera, poses, geometry.points_first[good], observations, self.config.geometric_ba
        )
        kept = int(estimate.keep.sum())
        ba_details = {
            "tracks_kept": window.shape[1], "triangulated": int(good.sum()), "severe_outliers": estimate.severe_removed,
            "outliers": estimate.outliers_removed, "points": kept, "reprojection_rms_px": round(estimate.rms_px, 3),
        }
        # ORB-SLAM2 resets a start left with fewer than 100 of its 1000-2000 features; this initializer tracks
        # 100-600 corners (VAMR parking: about 100, where 100 refused every start until frame 22), so the floor is
        # the two-view rule's 50 and the check after the hand-over (start_check.py) catches what passes it wrongly.
        if kept < self.config.two_view.min_triangulated:
            self._reject(f"{kept} points left after the bundle adjustment", **model_details, **ba_details)
            return None
        uv_features = observations[0][estimate.keep]
        idepth_features = 1.0 / estimate.points[estimate.keep, 2]
        uv, depths = self._with_selected_pixels(uv_features, idepth_features, estimate.poses_world_cam)
        is_feature = np.arange(len(uv)) < len(uv_features)
        uv_last = np.full(uv.shape, np.nan)
        uv_last[is_feature] = observations[-1][estimate.keep]
        initial = InitialMap(uv, depths, is_feature, estimate.poses_world_cam, uv_last).normalized()
        refined, refine_details = self._refine_photometrically(initial, tracks.frame_indices)
        ba_details.update(refine_details)
        if len(refined.uv) < self.config.two_view.min_triangulated:
            reason = f"{len(refined.uv)} points left after the photometric refinement"
            self._reject(reason, **model_details, **ba_details)
            return None
        final = refined.normalized()
        ba_details["features_handed_over"] = int(final.is_feature.sum())  # they come first in the result
        ba_details["points_handed_over"] = len(final.uv)
        ba_details["pixels_refined"] = int(np.sum(final.depths.updates[~final.is_feature] > 0))
        self._status = {"stage": "succeeded", **model_details, **ba_details}
        return InitializationResult(
            tracks.frame_indices[0], tracks.frame_indices[-1], final.poses_world_cam[-1], final.uv, final.depths.mean,
            final.depths.variance, details={**model_details, **ba_details, "frames": tracks.num_frames},
            tracks_second=final.uv_last[final.is_feature],
        )

    def _refine_photometrically(self, initial: InitialMap, frame_indices: list[int]) -> tuple[InitialMap, dict]:
        """004 section 3.4 in its order: photometric BA, the Student-t outlier filter, a final photometric BA
        (the final one only refines what the filter changed, so it runs only with the filter)."""
        adjust, filter_outliers = self.config.photometric_ba.enabled, self.config.photometric_filter.enabled
        current, details = initial, {}
        if adjust:
            current, report = self._adjust(current, frame_indices)
            details.update(_report_details("photometric_ba", report))
        if filter_outliers:
            keep = self._photometric_inliers(current.uv, current.depths, current.poses_world_cam)
            current = current.subset(keep)
            details["photometric_outliers"] = int((~keep).sum())
        if adjust and filter_outliers:
            current, report = self._adjust(current, frame_indices)
            details.update(_report_details("final_photometric_ba", report))
        return current, details

    def _adjust(self, current: InitialMap, frame_indices: list[int]) -> tuple[InitialMap, WindowReport]:
        """One photometric bundle adjustment of the window (004 eq. 11); the points it drops leave."""
        window = list(zip(frame_indices, self.pyramids, self.exposures))
        adjusted = photometric_bundle_adjustment(
            self.photometric_ba, window, current.poses_world_cam, current.uv, current.depths.mean
        )
        kept = current.subset(adjusted.kept)
        depths = replace(kept.depths, mean=adjusted.inverse_depths)
        return replace(kept, depths=depths, poses_world_cam=adjusted.poses_world_cam), adjusted.report

    def _with_selected_pixels(
        self, uv_features: np.ndarray, idepth_features: np.ndarray, poses_world_cam: np.ndarray
    ) -> tuple[np.ndarray, InverseDepths]:
        """The features plus DSO-selected pixels (32x32-block thresholds, median + 7) with inverse depths from
        the epipolar search through the window, the nearest features' depths as prior (004 section 3.3)."""
        config = self.config.semi_dense
        selection = PixelSelector(self.selector, self.seed).select(self.reference.levels, self.point_density)
        uv, prior = depth_prior(selection.uv.astype(float), uv_features, idepth_features, config)
        if config.enabled and len(uv):
            frames = [(pyramid, se3_inverse(T)) for pyramid, T in zip(self.pyramids[1:], poses_world_cam[1:])]
            prior = search_and_fuse(self.reference, uv, prior, frames, config)
        # The features' own depths come from the adjustment: their variance is that of one good observation.
        feature_variance = (config.line_sigma_px * idepth_features / self._baseline_px(poses_world_cam)) ** 2
        depths = InverseDepths(
            np.concatenate([idepth_features, prior.mean]), np.concatenate([feature_variance, prior.variance]),
            np.concatenate([np.full(len(uv_features), len(poses_world_cam) - 1), prior.updates]),
        )
        return np.vstack([uv_features, uv]), depths

    def _photometric_inliers(self, uv: np.ndarray, depths: InverseDepths, poses_world_cam: np.ndarray) -> np.ndarray:
        """Points whose patches match in enough window frames (004 section 3.4)."""
        frames = [(pyramid, se3_inverse(T)) for pyramid, T in zip(self.pyramids[1:], poses_world_cam[1:])]
        keep, _ = photometric_inliers(self.reference, uv, depths.mean, frames, self.config.photometric_filter)
        return keep

    def _baseline_px(self, poses_world_cam: np.ndarray) -> float:
        """How many pixels one unit of inverse depth moves a point between the first and last frame: f |t|."""
        return float(self.camera.fx * np.linalg.norm(poses_world_cam[-1][:3, 3]))


def _report_details(name: str, report: WindowReport) -> dict[str, Any]:
    """A photometric adjustment's energies, iterations, removed points and time, for the events."""
    return {
        f"{name}_energy_before": round(report.energy_before, 1), f"{name}_energy_after": round(report.energy_after, 1),
        f"{name}_iterations": report.iterations, f"{name}_removed": report.removed_points,
        f"{name}_ms": round(report.ms, 1),
    }


def depth_prior(
    uv: np.ndarray, uv_features: np.ndarray, idepth_features: np.ndarray, config: SemiDenseConfig
) -> tuple[np.ndarray, InverseDepths]:
    """The pixels ``uv`` close enough to the features, with the prior N(median, sigma^2) of the nearest
    features' inverse depths, sigma = relative sigma x median + their spread."""
    count = min(config.neighbours, len(uv_features))
    if count == 0 or len(uv) == 0:
        return np.empty((0, 2)), InverseDepths(np.empty(0), np.empty(0), np.empty(0, int))
    distance, nearest = cKDTree(uv_features).query(uv, k=count)
    distance, nearest = distance.reshape(len(uv), count), nearest.reshape(len(uv), count)
    near = distance[:, 0] <= config.max_neighbour_distance_px
    neighbours = idepth_features[nearest[near]]
    median = np.median(neighbours, axis=1)
    sigma = config.prior_relative_sigma * median + neighbours.std(axis=1)
    return uv[near], InverseDepths(median, sigma**2, np.zeros(int(near.sum()), int))
