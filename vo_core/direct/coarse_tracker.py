"""Coarse-to-fine direct image alignment of a frame against the reference keyframe (FDMO Eq. 2).

Follows DSO's CoarseTracker (trackNewestCoarse, calcRes, calcGSSSE): Levenberg-Marquardt over the SE(3)
increment and the frame's affine brightness (a, b), left-multiplicative updates T <- exp(inc) T, Huber
weights, a cutoff above which residuals count as saturated (doubled while more than 60% are), DSO's lambda
schedule and stopping rules, and an abort when a level ends worse than the best hypothesis tried so far.

Every reference point is DSO's 8-pixel pattern around a pixel of the reference keyframe, all pattern pixels
warped with the point's inverse depth. On coarser levels, points falling into the same pixel are merged
(their inverse depths averaged), as DSO's makeCoarseDepthL0 does, and so are the pattern pixels that neighbouring
points share there: each pixel is one residual (teddy's level 3: 2,380 instead of 8,568, where the 31 guesses of a
hard frame spend their time; the same ATE over three seeds on teddy, KITTI and parking). The per-pixel loops (warp,
bilinear lookup, Huber residual, normal equations) and each level's optimization loop are compiled kernels
(photometric_kernels.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vo_core.compiled import kernel
from vo_core.direct.affine import exposure_ratio
from vo_core.direct.config import PATTERN_8, TrackerConfig
from vo_core.direct.photometric_kernels import align_level, bilinear1, level_residuals
from vo_core.direct.pyramid import ImagePyramid, to_level
from vo_core.geometry.multiview import median_shift_px

PATTERN = np.array(PATTERN_8, dtype=float)  # (8, 2)
WARP_BORDER = 2.0  # calcRes: Ku > 2 && Ku < w - 3


def pattern_rays(intrinsics: np.ndarray) -> np.ndarray:
    """(8, 3) K^-1 (du, dv, 0) of the pattern's offsets, for intrinsics (fx, fy, cx, cy): a pinhole's unprojection
    is affine in the pixel, so pattern pixel k's ray is its point's K^-1 (u, v, 1) plus row k."""
    return np.c_[PATTERN / intrinsics[:2], np.zeros(len(PATTERN))]


@dataclass
class _LevelPoints:
    """One level's reference: per pattern pixel its normalized ray, inverse depth and intensity."""

    rays: np.ndarray  # (M, 3) K_l^-1 (u, v, 1) of each pattern pixel
    idepth: np.ndarray  # (M,)
    color: np.ndarray  # (M,) reference intensity
    centre_rays: np.ndarray  # (N, 3) of the point centres (flow indicators)
    centre_idepth: np.ndarray  # (N,)
    intrinsics: np.ndarray  # (fx, fy, cx, cy) of the level


@dataclass
class TrackingResult:
    success: bool
    T_frame_ref: np.ndarray  # 4x4, reference keyframe -> frame
    affine: np.ndarray  # (a, b) of the frame (DSO's aff_g2l)
    rmse_per_level: np.ndarray  # (levels,) sqrt of the mean Huber energy at the end of each level, NaN if unused
    rmse_before: float  # finest level, at the initial pose (FDMO's divergence test)
    rmse_after: float  # finest level, after the optimization
    saturated_share: float  # finest level: the share of its terms beyond its cutoff after the optimization
    cutoff_repeat: float  # finest level: how many times DSO's cutoff was doubled (1: not raised)
    flow: np.ndarray  # (3,) DSO's flow indicators (mean squared shift in px^2: T, R (0), RT)
    num_terms: int  # residual terms used at the finest level


def orthonormalized(T: np.ndarray) -> np.ndarray:
    """T with its rotation projected back onto SO(3): composing guesses from poses amplifies rounding
    (the constant-velocity guess multiplies three of them every frame), so each start is cleaned."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = np.array(T, dtype=float)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return out


def _merged_per_pixel(uv: np.ndarray, idepth: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The pixels (rounded) that points fall into, each once, with the mean inverse depth of its points
    (makeCoarseDepthL0 averages them), in raster order. Columns 0..``width`` (a point up to half a pixel past the
    image's edge) have keys of their own."""
    if len(uv) == 0:
        return uv, idepth
    return _merge_by_pixel(np.ascontiguousarray(uv, dtype=float), np.ascontiguousarray(idepth, dtype=float), width)


@kernel
def _merge_by_pixel(uv, idepth, width):
    """Bins over the range of the pixels' raster keys, counted and summed in the points' order (np.bincount's
    sums; a sort took 1 ms a level, numpy's bincount and the passes around it 0.5 ms, on tracking's wait)."""
    stride = width + 1
    keys = np.empty(len(uv), np.int64)
    for i in range(len(uv)):
        keys[i] = np.int64(np.rint(uv[i, 1])) * stride + np.int64(np.rint(uv[i, 0]))
    first = keys.min()
    counts = np.zeros(keys.max() - first + 1, np.int64)
    sums = np.zeros(len(counts))
    for i in range(len(keys)):
        counts[keys[i] - first] += 1
        sums[keys[i] - first] += idepth[i]
    occupied = np.flatnonzero(counts)
    merged_uv = np.empty((len(occupied), 2))
    merged_idepth = np.empty(len(occupied))
    for j in range(len(occupied)):
        key = occupied[j] + first
        merged_uv[j, 0], merged_uv[j, 1] = key % stride, key // stride
        merged_idepth[j] = sums[occupied[j]] / counts[occupied[j]]
    return merged_uv, merged_idepth


@kernel
def _pattern_pixels(uv, idepth, pattern, width, height, margin):
    """The points whose whole pattern lies at least ``margin`` inside a ``width`` x ``height`` image (mask), and
    their pattern pixels (M, 2) with each its point's inverse depth. One compiled pass instead of numpy's
    (N, 8, 2) temporaries, masks and repeats, on the tracking thread's wait for the reference."""
    keep = np.zeros(len(uv), np.bool_)
    for i in range(len(uv)):
        inside = True
        for k in range(len(pattern)):
            u, v = uv[i, 0] + pattern[k, 0], uv[i, 1] + pattern[k, 1]
            inside &= u >= margin and v >= margin and u <= width - 1 - margin and v <= height - 1 - margin
        keep[i] = inside
    pixels = np.empty((np.count_nonzero(keep) * len(pattern), 2))
    pixel_idepth = np.empty(len(pixels))
    m = 0
    for i in np.flatnonzero(keep):
        for k in range(len(pattern)):
            pixels[m, 0], pixels[m, 1], pixel_idepth[m] = uv[i, 0] + pattern[k, 0], uv[i, 1] + pattern[k, 1], idepth[i]
            m += 1
    return keep, pixels, pixel_idepth


@kernel
def _rays_and_colors(pixels, intensity, intrinsics):
    """float32 K^-1 (u, v, 1) of each pixel and its bilinear intensity (the pixels lie inside the image)."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    rays = np.empty((len(pixels), 3), np.float32)
    color = np.empty(len(pixels), np.float32)
    for m in range(len(pixels)):
        u, v = pixels[m, 0], pixels[m, 1]
        rays[m, 0], rays[m, 1], rays[m, 2] = (u - cx) / fx, (v - cy) / fy, 1.0
        color[m] = bilinear1(intensity, u, v)
    return rays, color


def huber_weight(residual: np.ndarray, threshold: float) -> np.ndarray:
    """w = 1 inside the threshold, k/|r| outside; energy w r^2 (2 - w) is the Huber cost times 2."""
    absolute = np.abs(residual)
    return np.minimum(1.0, threshold / np.maximum(absolute, 1e-12)).astype(residual.dtype, copy=False)


class CoarseTracker:
    def __init__(self, config: TrackerConfig):
        self.config = config
        self._scale = self._step_scale()
        self.reference: ImagePyramid | None = None
        self.levels: list[_LevelPoints] = []
        self.reference_affine = np.zeros(2)
        self.reference_exposure: float | None = None

    # ------------------------------------------------------------------------------------ reference

    def set_reference(
        self,
        pyramid: ImagePyramid,
        points_uv: np.ndarray,
        inverse_depths: np.ndarray,
        affine: np.ndarray,
        exposure: float | None,
    ) -> None:
        """Points (level-0 pixels of the reference keyframe) with their inverse depths become the reference."""
        self.reference = pyramid
        self.reference_affine = np.asarray(affine, dtype=float)
        self.reference_exposure = exposure
        points_uv = np.asarray(points_uv, dtype=float).reshape(-1, 2)
        inverse_depths = np.asarray(inverse_depths, dtype=float).reshape(-1)
        self.levels = [self._level_points(pyramid, level, points_uv, inverse_depths) for level in range(len(pyramid))]

    @property
    def num_points(self) -> int:
        return len(self.levels[0].centre_idepth) if self.levels else 0

    @staticmethod
    def _level_points(pyramid: ImagePyramid, level: int, uv: np.ndarray, idepth: np.ndarray) -> _LevelPoints:
        level_data = pyramid[level]
        camera = level_data.camera
        uv_level = to_level(uv, level)
        if level > 0:
            uv_level, idepth = _merged_per_pixel(uv_level, idepth, camera.width)
        inside, pixel_uv, pixel_idepth = _pattern_pixels(uv_level, idepth, PATTERN, camera.width, camera.height,
                                                         WARP_BORDER + 1.0)
        if level > 0:
            # Neighbouring points' patterns overlap on coarse levels (a level-3 pattern spans 32 level-0 pixels):
            # each pixel is one residual, as in DSO's per-level inverse depth map, not one per pattern covering it.
            pixel_uv, pixel_idepth = _merged_per_pixel(pixel_uv, pixel_idepth, camera.width)
        rays, color = _rays_and_colors(pixel_uv, level_data.intensity, camera.intrinsics)
        return _LevelPoints(
            rays=rays,
            idepth=pixel_idepth.astype(np.float32),
            color=color,
            centre_rays=camera.unproject(uv_level[inside]),
            centre_idepth=idepth[inside],
            intrinsics=camera.intrinsics,
        )

    # ------------------------------------------------------------------------------------ residuals

    def _exposure_ratio(self, exposure: float | None) -> float:
        return exposure_ratio(self.reference_exposure, exposure)

    def _flow_indicators(self, camera, points: _LevelPoints, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """calcRes' keyframe indicators: mean squared pixel shift of every 32nd point under +-t and R, +-t."""
        rays = points.centre_rays[:: self.config.flow_sample_stride]
        idepth = points.centre_idepth[:: self.config.flow_sample_stride, None]
        if len(rays) == 0:
            return np.zeros(3)
        origin = np.stack([camera.fx * rays[:, 0] + camera.cx, camera.fy * rays[:, 1] + camera.cy], axis=1)

        def shift(points_3d: np.ndarray) -> float:
            with np.errstate(divide="ignore", invalid="ignore"):
                pixel = np.stack(
                    [
                        camera.fx * points_3d[:, 0] / points_3d[:, 2] + camera.cx,
                        camera.fy * points_3d[:, 1] / points_3d[:, 2] + camera.cy,
                    ],
                    axis=1,
                )
            return float(np.nansum((pixel - origin) ** 2))

        rotated = rays @ R.T
        num = 2.0 * len(rays) + 0.1
        translation = (shift(rays + idepth * t) + shift(rays - idepth * t)) / num
        both = (shift(rotated + idepth * t) + shift(rotated - idepth * t)) / num
        return np.array([translation, 0.0, both])

    def _step_scale(self) -> np.ndarray:
        c = self.config
        return np.array([c.scale_translation] * 3 + [c.scale_rotation] * 3 + [c.scale_a, c.scale_b])

    # ------------------------------------------------------------------------------------ tracking

    def rmse(
        self, frame: ImagePyramid, T_frame_ref: np.ndarray, affine: np.ndarray, exposure: float | None, level: int = 0
    ) -> float:
        """sqrt(mean Huber energy) of Eq. 2 at a given pose, with DSO's cutoff (calcRes)."""
        return self.fit(frame, T_frame_ref, affine, exposure, level)[0]

    def end_fit(self, frame: ImagePyramid, result: TrackingResult, exposure: float | None) -> tuple[float, float]:
        """``fit`` at a result's final pose: the finest level's own numbers where its cutoff was not raised (the same
        residuals), measured anew where it was."""
        if result.cutoff_repeat == 1.0:
            return result.rmse_after, result.saturated_share
        return self.fit(frame, result.T_frame_ref, result.affine, exposure)

    def fit(
        self, frame: ImagePyramid, T_frame_ref: np.ndarray, affine: np.ndarray, exposure: float | None, level: int = 0
    ) -> tuple[float, float]:
        """``rmse`` and the share of the terms beyond the cutoff (saturated: what the pose leaves unexplained)."""
        points = self.levels[level]
        _, _, num_terms, saturated, energy, _ = level_residuals(
            points.rays, points.idepth, points.color, np.ascontiguousarray(T_frame_ref, dtype=float),
            np.asarray(affine, dtype=float), points.intrinsics, WARP_BORDER, frame[level].packed,
            self._exposure_ratio(exposure), self.reference_affine, float(self.config.huber_threshold),
            float(self.config.cutoff_threshold))
        if not num_terms:
            return float("inf"), 1.0
        return float(np.sqrt(energy / num_terms)), saturated / num_terms

    def track(
        self,
        frame: ImagePyramid,
        T_frame_ref: np.ndarray,
        affine: np.ndarray,
        exposure: float | None,
        max_rmse_for_abort: np.ndarray | None = None,
        coarsest_level: int | None = None,
        measure_start: bool = True,
        coarse_optima: list[np.ndarray] | None = None,
    ) -> TrackingResult:
        """trackNewestCoarse from an initial pose and affine; ``max_rmse_for_abort`` is DSO's minResForAbort.
        ``measure_start``: the RMSE at the initial pose (``rmse_before``: FDMO's divergence test reads the first
        guess's only; NaN where not measured). ``coarse_optima``: where earlier guesses of the same frame ended on
        the coarsest level; a guess that ends there too would repeat their finer levels, and fails at once (ours:
        on a hard frame DSO's 31 guesses all ran every level, though they met in a handful of coarse optima)."""
        config = self.config
        num_levels = min(len(frame), len(self.levels))
        coarsest = num_levels - 1 if coarsest_level is None else min(coarsest_level, num_levels - 1)
        abort = np.full(num_levels, np.nan) if max_rmse_for_abort is None else np.asarray(max_rmse_for_abort)
        T = orthonormalized(T_frame_ref)
        ab = np.array(affine, dtype=float)
        rmse_before = self.rmse(frame, T, ab, exposure, level=0) if measure_start else float("nan")
        rmse_levels = np.full(num_levels, np.nan)
        flow = np.zeros(3)  # DSO's flow indicators come from the finest level only
        num_terms, saturated, cutoff_repeat = 0, 1.0, 1.0
        repeated = False
        level = coarsest
        while level >= 0:
            T, ab, mean_energy, num_terms, saturated, cutoff_repeat = self._align_level(frame, level, T, ab, exposure)
            rmse_levels[level] = np.sqrt(mean_energy)
            end = (saturated, cutoff_repeat)
            if not np.isfinite(rmse_levels[level]) or rmse_levels[level] > config.abort_factor * abort[level]:
                return self._result(False, T, ab, rmse_levels, rmse_before, flow, num_terms, *end)
            if cutoff_repeat > 1 and not repeated:
                repeated = True  # DSO: a level that needed a larger cutoff is optimized once more
                continue
            if coarse_optima is not None and level == coarsest:
                if self._reached_before(level, T, coarse_optima):
                    return self._result(False, T, ab, rmse_levels, rmse_before, flow, num_terms, *end)
                coarse_optima.append(T)
            level -= 1
        flow = self._flow_indicators(frame[0].camera, self.levels[0], T[:3, :3], T[:3, 3])
        success = (
            abs(ab[0]) <= config.max_abs_a
            and abs(ab[1]) <= config.max_abs_b
            and num_terms >= config.min_points_in_view
        )
        return self._result(success, T, ab, rmse_levels, rmse_before, flow, num_terms, *end)

    def _align_level(self, frame: ImagePyramid, level: int, T: np.ndarray, ab: np.ndarray, exposure: float | None):
        """One level's cutoff and DSO's Levenberg-Marquardt loop (photometric_kernels.align_level): (T, ab, mean
        energy, terms, their share saturated, the cutoff's repeat factor)."""
        c = self.config
        points = self.levels[level]
        max_iterations = c.max_iterations[min(level, len(c.max_iterations) - 1)]
        T, ab, mean_energy, num_terms, saturated, repeat = align_level(
            points.rays, points.idepth, points.color, np.ascontiguousarray(T), np.ascontiguousarray(ab),
            points.intrinsics, WARP_BORDER, frame[level].packed, self._exposure_ratio(exposure), self.reference_affine,
            float(c.huber_threshold), float(c.cutoff_threshold), float(c.max_saturated_ratio),
            float(c.max_cutoff_repeat), self._scale, float(c.initial_lambda), float(c.lambda_extrapolation_limit),
            float(c.lambda_decrease), float(c.lambda_increase), int(max_iterations), float(c.min_increment_norm),
        )
        return T, ab, float(mean_energy), int(num_terms), float(saturated), float(repeat)

    def _reached_before(self, level: int, T_frame_ref: np.ndarray, optima: list[np.ndarray]) -> bool:
        """Whether the level's points land within ``same_coarse_optimum_px`` (median, pixels of the level) of where
        one of ``optima`` puts them."""
        tolerance = self.config.same_coarse_optimum_px
        return any(self.image_motion_px(T_frame_ref, T, level) <= tolerance for T in optima)

    def image_motion_px(self, T_a_ref: np.ndarray, T_b_ref: np.ndarray, level: int = 0) -> float:
        """Median distance, in pixels of ``level``, between where the reference's points land in a frame at pose a
        and in one at pose b (those in front of both; inf with none)."""
        points = self.levels[level]
        fx, fy, cx, cy = points.intrinsics

        def pixels(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            warped = points.centre_rays @ T[:3, :3].T + points.centre_idepth[:, None] * T[:3, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                uv = np.stack([fx * warped[:, 0] / warped[:, 2] + cx, fy * warped[:, 1] / warped[:, 2] + cy], 1)
            return uv, warped[:, 2] > 0

        uv_a, front_a = pixels(T_a_ref)
        uv_b, front_b = pixels(T_b_ref)
        return median_shift_px(uv_a, uv_b, front_a & front_b)

    @staticmethod
    def _result(success, T, ab, rmse_levels, rmse_before, flow, num_terms, saturated, cutoff_repeat) -> TrackingResult:
        return TrackingResult(
            success=bool(success),
            T_frame_ref=T,
            affine=ab,
            rmse_per_level=rmse_levels,
            rmse_before=float(rmse_before),
            rmse_after=float(rmse_levels[0]) if np.isfinite(rmse_levels[0]) else float("nan"),
            flow=flow,
            num_terms=int(num_terms),
            saturated_share=float(saturated),
            cutoff_repeat=float(cutoff_repeat),
        )

    def project_points(self, T_frame_ref: np.ndarray) -> np.ndarray:
        """Level-0 pixels of the reference points in the frame at pose T_frame_ref (FrameResult.points_2d)."""
        points = self.levels[0]
        camera = self.reference[0].camera
        warped = points.centre_rays @ T_frame_ref[:3, :3].T + points.centre_idepth[:, None] * T_frame_ref[:3, 3]
        front = warped[:, 2] > 0
        return camera.project(warped[front])
