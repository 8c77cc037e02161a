"""Coarse-to-fine direct image alignment of a frame against the reference keyframe (FDMO Eq. 2).

Follows DSO's CoarseTracker (trackNewestCoarse, calcRes, calcGSSSE): Levenberg-Marquardt over the SE(3)
increment and the frame's affine brightness (a, b), left-multiplicative updates T <- exp(inc) T, Huber
weights, a cutoff above which residuals count as saturated (doubled while more than 60% are), DSO's lambda
schedule and stopping rules, and an abort when a level ends worse than the best hypothesis tried so far.

Every reference point is DSO's 8-pixel pattern around a pixel of the reference keyframe, all pattern pixels
warped with the point's inverse depth. On coarser levels, points falling into the same pixel are merged
(their inverse depths averaged), as DSO's makeCoarseDepthL0 does. The per-pixel loops (warp, bilinear lookup,
Huber residual, normal equations) are compiled kernels (photometric_kernels.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vo_core.direct.affine import relative_affine
from vo_core.direct.config import PATTERN_8, TrackerConfig
from vo_core.direct.photometric_kernels import normal_equations, warp_residuals
from vo_core.direct.pyramid import ImagePyramid, to_level
from vo_core.geometry.lie import se3_exp

PATTERN = np.array(PATTERN_8, dtype=float)  # (8, 2)
WARP_BORDER = 2.0  # calcRes: Ku > 2 && Ku < w - 3


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
class _Residuals:
    energy: float
    num_terms: int
    saturated_ratio: float
    # The non-saturated terms for the normal equations (calcGSSSE): the first ``count`` rows of
    # photometric_kernels.warp_residuals' buffer.
    terms: np.ndarray = field(default_factory=lambda: np.zeros((0, 8), np.float32))
    count: int = 0

    @property
    def mean_energy(self) -> float:
        return self.energy / self.num_terms if self.num_terms else np.inf


@dataclass
class TrackingResult:
    success: bool
    T_frame_ref: np.ndarray  # 4x4, reference keyframe -> frame
    affine: np.ndarray  # (a, b) of the frame (DSO's aff_g2l)
    rmse_per_level: np.ndarray  # (levels,) sqrt of the mean Huber energy at the end of each level, NaN if unused
    rmse_before: float  # finest level, at the initial pose (FDMO's divergence test)
    rmse_after: float  # finest level, after the optimization
    flow: np.ndarray  # (3,) DSO's flow indicators (mean squared shift in px^2: T, R (0), RT)
    num_terms: int  # residual terms used at the finest level


def orthonormalized(T: np.ndarray) -> np.ndarray:
    """T with its rotation projected back onto SO(3): composing guesses from poses amplifies rounding
    (the constant-velocity guess multiplies three of them every frame), so each start is cleaned."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = np.array(T, dtype=float)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return out


def huber_weight(residual: np.ndarray, threshold: float) -> np.ndarray:
    """w = 1 inside the threshold, k/|r| outside; energy w r^2 (2 - w) is the Huber cost times 2."""
    absolute = np.abs(residual)
    return np.minimum(1.0, threshold / np.maximum(absolute, 1e-12)).astype(residual.dtype, copy=False)


class CoarseTracker:
    def __init__(self, config: TrackerConfig):
        self.config = config
        self._scale = self._step_scale()
        self._scale_outer = np.outer(self._scale, self._scale)
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
        if level > 0 and len(uv_level):
            # Merge points that fall into one pixel of this level (makeCoarseDepthL0 averages them).
            pixel = np.round(uv_level).astype(np.int64)
            key = pixel[:, 1] * (camera.width + 1) + pixel[:, 0]
            unique, inverse = np.unique(key, return_inverse=True)
            counts = np.bincount(inverse)
            idepth = np.bincount(inverse, weights=idepth) / counts
            uv_level = np.stack([unique % (camera.width + 1), unique // (camera.width + 1)], axis=1).astype(float)
        pattern_uv = uv_level[:, None, :] + PATTERN[None, :, :]  # (N, 8, 2)
        margin = WARP_BORDER + 1.0
        inside = camera.in_image(pattern_uv.reshape(-1, 2), border=margin).reshape(-1, len(PATTERN)).all(axis=1)
        pattern_uv, uv_level, idepth = pattern_uv[inside], uv_level[inside], idepth[inside]
        color = level_data.sample_intensity(pattern_uv[..., 0], pattern_uv[..., 1]).reshape(-1)
        flat_uv = pattern_uv.reshape(-1, 2)
        return _LevelPoints(
            rays=camera.unproject(flat_uv).astype(np.float32),
            idepth=np.repeat(idepth, len(PATTERN)).astype(np.float32),
            color=color.astype(np.float32),
            centre_rays=camera.unproject(uv_level),
            centre_idepth=idepth,
            intrinsics=np.array([camera.fx, camera.fy, camera.cx, camera.cy]),
        )

    # ------------------------------------------------------------------------------------ residuals

    def _relative_affine(self, affine: np.ndarray, exposure: float | None) -> tuple[float, float]:
        return relative_affine(self.reference_exposure, exposure, self.reference_affine, affine)

    def _residuals(
        self,
        frame: ImagePyramid,
        level: int,
        T_frame_ref: np.ndarray,
        affine: np.ndarray,
        exposure: float | None,
        cutoff: float,
    ) -> _Residuals:
        """calcRes: Huber energy of all warped pattern pixels, saturated beyond ``cutoff`` (float32 throughout)."""
        config = self.config
        points = self.levels[level]
        factor, offset = self._relative_affine(affine, exposure)
        if not (np.isfinite(factor) and np.isfinite(offset)):
            return _Residuals(energy=np.inf, num_terms=0, saturated_ratio=1.0)
        terms, count, num_terms, saturated, energy = warp_residuals(
            points.rays, points.idepth, points.color, T_frame_ref[:3, :3], T_frame_ref[:3, 3],
            points.intrinsics, WARP_BORDER, frame[level].packed,
            float(factor), float(offset), float(config.huber_threshold), float(cutoff),
        )
        return _Residuals(energy, num_terms, saturated / max(num_terms, 1), terms, count)

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

    def _normal_equations(
        self, frame: ImagePyramid, level: int, res: _Residuals, affine: np.ndarray, exposure: float | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """calcGSSSE: H and b of the 8 parameters (v, w, a, b), averaged per term and scaled as DSO."""
        fx, fy = self.levels[level].intrinsics[:2]
        factor, _ = self._relative_affine(affine, exposure)
        H, b = normal_equations(res.terms, res.count, fx, fy, factor, self.reference_affine[1])
        return H * self._scale_outer, b * self._scale

    def _step_scale(self) -> np.ndarray:
        c = self.config
        return np.array([c.scale_translation] * 3 + [c.scale_rotation] * 3 + [c.scale_a, c.scale_b])

    # ------------------------------------------------------------------------------------ tracking

    def rmse(
        self, frame: ImagePyramid, T_frame_ref: np.ndarray, affine: np.ndarray, exposure: float | None, level: int = 0
    ) -> float:
        """sqrt(mean Huber energy) of Eq. 2 at a given pose, with DSO's cutoff."""
        res = self._residuals(frame, level, T_frame_ref, affine, exposure, self.config.cutoff_threshold)
        return float(np.sqrt(res.mean_energy))

    def track(
        self,
        frame: ImagePyramid,
        T_frame_ref: np.ndarray,
        affine: np.ndarray,
        exposure: float | None,
        max_rmse_for_abort: np.ndarray | None = None,
        coarsest_level: int | None = None,
    ) -> TrackingResult:
        """trackNewestCoarse from an initial pose and affine; ``max_rmse_for_abort`` is DSO's minResForAbort."""
        config = self.config
        num_levels = min(len(frame), len(self.levels))
        coarsest = num_levels - 1 if coarsest_level is None else min(coarsest_level, num_levels - 1)
        abort = np.full(num_levels, np.nan) if max_rmse_for_abort is None else np.asarray(max_rmse_for_abort)
        T = orthonormalized(T_frame_ref)
        ab = np.array(affine, dtype=float)
        rmse_before = self.rmse(frame, T, ab, exposure, level=0)
        rmse_levels = np.full(num_levels, np.nan)
        flow = np.zeros(3)  # DSO's flow indicators come from the finest level only
        num_terms = 0
        repeated = False
        level = coarsest
        while level >= 0:
            res, cutoff_repeat = self._residuals_with_cutoff(frame, level, T, ab, exposure)
            T, ab, res = self._optimize_level(frame, level, T, ab, exposure, res, cutoff_repeat)
            rmse_levels[level] = np.sqrt(res.mean_energy)
            num_terms = res.num_terms
            if not np.isfinite(rmse_levels[level]) or rmse_levels[level] > config.abort_factor * abort[level]:
                return self._result(False, T, ab, rmse_levels, rmse_before, flow, num_terms)
            if cutoff_repeat > 1 and not repeated:
                repeated = True  # DSO: a level that needed a larger cutoff is optimized once more
                continue
            level -= 1
        flow = self._flow_indicators(frame[0].camera, self.levels[0], T[:3, :3], T[:3, 3])
        success = (
            abs(ab[0]) <= config.max_abs_a
            and abs(ab[1]) <= config.max_abs_b
            and num_terms >= config.min_points_in_view
        )
        return self._result(success, T, ab, rmse_levels, rmse_before, flow, num_terms)

    def _residuals_with_cutoff(self, frame, level, T, ab, exposure) -> tuple[_Residuals, float]:
        config = self.config
        repeat = 1.0
        res = self._residuals(frame, level, T, ab, exposure, config.cutoff_threshold)
        while res.saturated_ratio > config.max_saturated_ratio and repeat < config.max_cutoff_repeat:
            repeat *= 2.0
            res = self._residuals(frame, level, T, ab, exposure, config.cutoff_threshold * repeat)
        return res, repeat

    def _optimize_level(self, frame, level, T, ab, exposure, res: _Residuals, cutoff_repeat: float):
        """DSO's LM loop of one level: accept when the mean energy drops, lambda x0.5 / x4."""
        config = self.config
        cutoff = config.cutoff_threshold * cutoff_repeat
        H, b = self._normal_equations(frame, level, res, ab, exposure)
        lam = config.initial_lambda
        scale = self._scale
        max_iterations = config.max_iterations[min(level, len(config.max_iterations) - 1)]
        for _ in range(max_iterations):
            H_damped = H + np.diag(np.diag(H)) * lam
            try:
                inc = np.linalg.solve(H_damped, -b)
            except np.linalg.LinAlgError:
                break
            if lam < config.lambda_extrapolation_limit:
                inc *= np.sqrt(np.sqrt(config.lambda_extrapolation_limit / lam))
            with np.errstate(over="ignore", invalid="ignore"):  # a degenerate system: the step is dropped below
                step = inc * scale
            if not np.all(np.isfinite(step)):
                step = np.zeros(8)
            T_new = se3_exp(step[:6]) @ T
            ab_new = ab + step[6:]
            res_new = self._residuals(frame, level, T_new, ab_new, exposure, cutoff)
            if res_new.mean_energy < res.mean_energy:
                T, ab, res = T_new, ab_new, res_new
                H, b = self._normal_equations(frame, level, res, ab, exposure)
                lam *= config.lambda_decrease
            else:
                lam = max(lam * config.lambda_increase, config.lambda_extrapolation_limit)
            if not np.linalg.norm(inc) > config.min_increment_norm:
                break
        return T, ab, res

    @staticmethod
    def _result(success, T, ab, rmse_levels, rmse_before, flow, num_terms) -> TrackingResult:
        return TrackingResult(
            success=bool(success),
            T_frame_ref=T,
            affine=ab,
            rmse_per_level=rmse_levels,
            rmse_before=float(rmse_before),
            rmse_after=float(rmse_levels[0]) if np.isfinite(rmse_levels[0]) else float("nan"),
            flow=flow,
            num_terms=int(num_terms),
        )

    def project_points(self, T_frame_ref: np.ndarray) -> np.ndarray:
        """Level-0 pixels of the reference points in the frame at pose T_frame_ref (FrameResult.points_2d)."""
        points = self.levels[0]
        camera = self.reference[0].camera
        warped = points.centre_rays @ T_frame_ref[:3, :3].T + points.centre_idepth[:, None] * T_frame_ref[:3, 3]
        front = warped[:, 2] > 0
        return camera.project(warped[front])
