"""The start check's independent witness: what ORB matches between the start's keyframes say about their motion.

The start check's other measures (vo_core/direct/start_check.py) all come from the direct map itself, so a start
that is wrong in a self-consistent way passes them: DSO's coarse initializer on KITTI played backward from frame 0
hands over a first pose 8 deg and 45 deg off that its window optimizations then refine without complaint (inlier
ratio 0.70, no energy growth, parallax unchanged). Two images say it directly: the essential matrix of their ORB
matches (five-point RANSAC, cv2.findEssentialMat) gives the relative rotation and translation direction without any
of the map's depths. For each keyframe of the start's window against its oldest one, where the matches support the
epipolar geometry well (enough points triangulated in front of both views, seen under enough parallax), the direct
poses' motion is compared with it.

A plane seen from two views has two motions that explain it equally (Faugeras' twofold ambiguity), and the
essential matrix then picks one at random: a pair whose inliers a homography explains as well (ORB-SLAM's model
selection, R_H > 0.4, geometry/two_view.py) does not count. One pair can still be fooled (a near-planar view
flipped the translation of one pair of a right teddy start in 3, with 273 points), so the start is refused only
where several pairs, and most of the qualified ones, disagree. Where too few pairs qualify (too little parallax,
too few matches, a planar view) this comparison says nothing.

Where it says nothing, the matches can still refuse the direct motion itself: taken as the hypothesis, the share of
the matches the essential matrix holds that it explains (their epipolar distances within ORB-SLAM2's chi-square
bound for one degree of freedom, and, where their rays meet at an angle the bound can tell from zero, in front of
both cameras) is the agreement of the two halves that the hybrid measures for a feature pose
(``fdmo.agreement``). This needs no parallax: views nearly from one point fix the rotation, whatever the
translation's direction, and a rotation off by a few degrees moves the matches off their epipolar lines by many
pixels. Where a plane or a narrow view lets rotation and translation trade (the twofold and the bas-relief
ambiguities) the matches explain both motions alike, and nothing is refused for it. The start is refused where
``min_disagreeing_pairs`` pairs are explained under ``min_explained`` (the drone clip at half its frame rate, seed
1: a homography start whose keyframes were 20-40 degrees of rotation off their images, on pairs under 0.25 degrees
of parallax, 3-6 % explained; right starts on the shared folders and the drone clip 88-100 %, fr1/desk's blurred
ones 61-96 %).

The witness lives with the initializers, above both halves: it measures with the feature half's ORB extractor and
matcher, which the direct half does not import. The initializer registry (registry.py) hands a fresh one to the
direct odometry for each start (``InitializerFactory.start_witness``, vo_core/direct/initialization.py).
"""

from __future__ import annotations

import os
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from vo_core.direct.config import EpipolarCheckConfig
from vo_core.features.config import OrbConfig
from vo_core.features.matcher import match_exhaustive
from vo_core.features.orb import Features, OrbExtractor
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import hat, motion_angles_deg, se3_inverse
from vo_core.geometry.multiview import bearing_angles
from vo_core.geometry.two_view import TwoViewConfig, estimate_models, motion_from_essential


@dataclass
class PairGeometry:
    """One keyframe pair: the epipolar geometry of its matches against the direct poses' relative motion."""

    frames: tuple[int, int]
    points: int  # matches triangulated in front of both views by the essential matrix's motion
    parallax_deg: float  # median angle between the two rays of those points, rotation removed
    rotation_deg: float  # between the essential matrix's rotation and the direct poses'
    direction_deg: float  # between their translation directions
    homography_ratio: float  # R_H of the essential matrix's inliers: above TwoViewConfig's, a plane
    held: int  # matches the essential matrix holds (its RANSAC inliers)
    explained: float  # the share of them the direct poses' motion explains (_explained_share)

    def qualified(self, config: EpipolarCheckConfig) -> bool:
        return (self.points >= config.min_points and self.parallax_deg >= config.min_parallax_deg
                and self.homography_ratio <= TwoViewConfig.homography_ratio)

    def disagrees(self, config: EpipolarCheckConfig) -> bool:
        return self.rotation_deg > config.max_rotation_deg or self.direction_deg > config.max_direction_deg

    def unexplained(self, config: EpipolarCheckConfig) -> bool:
        """The direct motion explains under ``min_explained`` of enough matches: at any parallax, on any scene."""
        return self.held >= config.min_points and self.explained < config.min_explained

    def details(self) -> dict:
        return {"frames": list(self.frames), "points": self.points, "parallax_deg": round(self.parallax_deg, 2),
                "rotation_deg": round(self.rotation_deg, 2), "direction_deg": round(self.direction_deg, 1),
                "homography_ratio": round(self.homography_ratio, 2), "held": self.held,
                "explained": round(self.explained, 3)}


@dataclass
class _ImageGeometry:
    """What a pair's images alone say (the direct poses aside, which the window optimizations go on refining)."""

    points: int
    parallax_deg: float
    T_anchor_other: np.ndarray  # the essential matrix's motion, translation of unit length
    homography_ratio: float
    rays_anchor: np.ndarray  # (N, 3) K^-1 (u, v, 1) of the matches the essential matrix holds
    rays_other: np.ndarray
    focal_px: float  # to express epipolar distances in pixels


class EpipolarCheck:
    def __init__(self, config: EpipolarCheckConfig):
        self.config = config
        self._pool: ThreadPoolExecutor | None = None
        self._anchor: tuple[int, Future] | None = None  # the anchor's frame index and its features
        self._images: dict[tuple[int, int], Future] = {}  # (anchor, other) frame indices: _ImageGeometry or None

    def prepare(self, keyframes: list, camera: PinholeCamera) -> None:
        """Start measuring, beside mapping, what the images of the keyframe pairs not measured yet say: at the last
        optimization of the start only the comparison with the direct poses is left (teddy's start: 0.5 s of
        extraction, matching and RANSAC that held up its last probation keyframe)."""
        for other in keyframes[1:]:
            self._images_of(keyframes[0], other, camera)

    def disagreement(self, keyframes: list, camera: PinholeCamera) -> tuple[str | None, dict]:
        """Why the direct poses of ``keyframes`` (each with ``frame_index``, ``image``, ``T_world_cam``) contradict
        the epipolar geometry of their images, or None; and the measures for the event. The pairs are measured on
        all cores (OpenCV's work in them releases the GIL: KITTI's start, 1.1 s in a row), those ``prepare`` did
        not start yet included."""
        config = self.config
        anchor, others = keyframes[0], keyframes[1:]
        measured = [self._images_of(anchor, other, camera) for other in others]
        pairs = [_pair_geometry(anchor, other, images.result(), config) for other, images in zip(others, measured)]
        self.close()
        pairs = [pair for pair in pairs if pair is not None]
        qualified = [pair for pair in pairs if pair.qualified(config)]
        disagreeing = [pair for pair in qualified if pair.disagrees(config)]
        unexplained = [pair for pair in pairs if pair.unexplained(config)]
        details = {"epipolar_pairs": len(qualified), "epipolar_disagreeing": len(disagreeing),
                   "epipolar_unexplained": len(unexplained)}
        if disagreeing:
            worst = max(disagreeing, key=lambda pair: pair.rotation_deg / config.max_rotation_deg
                        + pair.direction_deg / config.max_direction_deg)
            details["epipolar_worst"] = worst.details()
            if len(disagreeing) >= config.min_disagreeing_pairs and 2 * len(disagreeing) > len(qualified):
                return (f"the ORB matches of {len(disagreeing)} of {len(qualified)} keyframe pairs contradict the "
                        f"start's motion (worst, frames {worst.frames[0]}-{worst.frames[1]}: rotation "
                        f"{worst.rotation_deg:.1f} deg, translation direction {worst.direction_deg:.0f} deg apart)",
                        details)
        if unexplained:
            least = min(unexplained, key=lambda pair: pair.explained)
            details["epipolar_least_explained"] = least.details()
            if len(unexplained) >= config.min_disagreeing_pairs:
                return (f"the start's motion explains under {config.min_explained:.0%} of the ORB matches of "
                        f"{len(unexplained)} keyframe pairs (least, frames {least.frames[0]}-{least.frames[1]}: "
                        f"{least.explained:.0%} of {least.held})", details)
        return None, details

    def close(self) -> None:
        """Stop measuring: the pool's threads end once idle, and pairs not started yet are dropped (a start discarded
        before its last optimization leaves them to no one)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def _images_of(self, anchor, other, camera: PinholeCamera) -> Future:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=os.cpu_count(), thread_name_prefix="fdmo-epipolar")
        if self._anchor is None or self._anchor[0] != anchor.frame_index:
            self._anchor = (anchor.frame_index, self._pool.submit(self._extractor().extract, anchor.image))
        key = (anchor.frame_index, other.frame_index)
        if key not in self._images:
            self._images[key] = self._pool.submit(self._measure_images, self._anchor[1], other.image, camera)
        return self._images[key]

    def _extractor(self) -> OrbExtractor:
        """One per image: OpenCV's detectors are not shared between threads."""
        return OrbExtractor(OrbConfig(num_features=self.config.num_features))

    def _measure_images(self, anchor_features: Future, other_image: np.ndarray,
                        camera: PinholeCamera) -> _ImageGeometry | None:
        config = self.config
        other_features = self._extractor().extract(other_image)
        uv_anchor, uv_other = _matches(anchor_features.result(), other_features, config)
        if len(uv_anchor) < config.min_points:
            return None
        cv2.setRNGSeed(config.seed)  # this thread's RANSAC draws: each pair's the same, whichever thread measures it
        E, inliers = cv2.findEssentialMat(uv_anchor, uv_other, camera.K, cv2.RANSAC, config.ransac_confidence,
                                          config.ransac_threshold_px)
        if E is None or E.shape != (3, 3):
            return None
        held = inliers.ravel() > 0
        motion = motion_from_essential(camera, E, uv_anchor, uv_other, held, TwoViewConfig())
        in_front = motion.good
        rays = bearing_angles(camera, np.eye(4), uv_anchor[in_front], motion.T_first_second, uv_other[in_front])
        homography_ratio = (estimate_models(uv_anchor[in_front], uv_other[in_front], TwoViewConfig(),
                                            np.random.default_rng(config.seed)).ratio
                            if in_front.sum() >= config.min_points else 1.0)
        return _ImageGeometry(int(in_front.sum()), float(np.degrees(np.median(rays))) if len(rays) else 0.0,
                              motion.T_first_second, homography_ratio, camera.unproject(uv_anchor[held]),
                              camera.unproject(uv_other[held]), float(camera.intrinsics[0]))


def _pair_geometry(anchor, other, images: _ImageGeometry | None, config: EpipolarCheckConfig) -> PairGeometry | None:
    """The pair's images against its keyframes' direct poses as they are now."""
    if images is None:
        return None
    T_direct = se3_inverse(anchor.T_world_cam) @ other.T_world_cam
    return PairGeometry((anchor.frame_index, other.frame_index), images.points, images.parallax_deg,
                        *motion_angles_deg(images.T_anchor_other, T_direct), images.homography_ratio,
                        len(images.rays_anchor), _explained_share(images, se3_inverse(T_direct), config))


def _explained_share(images: _ImageGeometry, T_other_anchor: np.ndarray, config: EpipolarCheckConfig) -> float:
    """The share of the matches the essential matrix holds that the motion ``T_other_anchor`` explains: their
    Sampson distance to its epipolar geometry (E = [t]x R, x_other^T E x_anchor = 0) within the chi-square bound,
    and, where their two rays meet at an angle the bound can tell from zero, in front of both cameras (the epipolar
    constraint does not see the sign of the translation: a mirrored map, its translation reversed, satisfies it)."""
    rotation, translation = T_other_anchor[:3, :3], T_other_anchor[:3, 3]
    if not np.linalg.norm(translation) > 0.0 or len(images.rays_anchor) == 0:
        return 1.0  # no baseline: no epipolar geometry to test
    t = translation / np.linalg.norm(translation)
    E = hat(t) @ rotation
    lines_other = images.rays_anchor @ E.T  # E x_anchor
    lines_anchor = images.rays_other @ E  # E^T x_other
    algebraic = np.sum(images.rays_other * lines_other, axis=1)
    gradient = lines_other[:, 0] ** 2 + lines_other[:, 1] ** 2 + lines_anchor[:, 0] ** 2 + lines_anchor[:, 1] ** 2
    bound_px = config.ransac_threshold_px * np.sqrt(TwoViewConfig.chi2_fundamental)  # ORB-SLAM's 1-DOF T_F
    on_lines = np.abs(algebraic) <= bound_px / images.focal_px * np.sqrt(gradient)
    # Where the rays meet (depth_other x_other = depth_anchor R x_anchor + t), up to a positive factor each.
    turned = images.rays_anchor @ rotation.T  # the anchor's rays in the other camera
    crossing = np.cross(turned, images.rays_other)
    sine_sq = np.sum(crossing ** 2, axis=1) / (np.sum(turned ** 2, axis=1) * np.sum(images.rays_other ** 2, axis=1))
    depth_anchor = -np.sum(np.cross(t, images.rays_other) * crossing, axis=1)
    depth_other = -np.sum(np.cross(t, turned) * crossing, axis=1)
    behind = (sine_sq > (bound_px / images.focal_px) ** 2) & ((depth_anchor <= 0.0) | (depth_other <= 0.0))
    return float(np.mean(on_lines & ~behind))


def _matches(first: Features, second: Features, config: EpipolarCheckConfig) -> tuple[np.ndarray, np.ndarray]:
    """Nearest descriptor in the other image, kept when clearly nearer than the second (Lowe's ratio)."""
    if len(first) < 2 or len(second) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    index_first, index_second = match_exhaustive(first, second, max_distance=config.max_distance, ratio=config.ratio)
    return first.uv[index_first], second.uv[index_second]
