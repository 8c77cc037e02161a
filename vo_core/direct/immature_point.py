"""Immature points: candidate pixels of a keyframe whose inverse depth is found by epipolar search.

Follows DSO's ImmaturePoint::traceOn, vectorized over all points of one host keyframe. Each trace projects
the current inverse-depth interval [idepth_min, idepth_max] into the new frame, searches the epipolar segment
in 1-px steps with the 8-pixel pattern (Huber energy), refines the best step by Gauss-Newton along the line,
and shrinks the interval to the pixel error bound of the result. The quality is the ratio of the second-best
energy (outside +-2 steps) to the best. A point may become active (used for tracking) when its last trace is
good, its interval is below 8 px and its quality above 3 (FullSystem::activatePointsMT).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numba
import numpy as np

from vo_core.compiled import kernel
from vo_core.direct.config import ImmatureConfig
from vo_core.direct.coarse_tracker import PATTERN, pattern_rays
from vo_core.direct.photometric_kernels import (
    PARALLEL_LAUNCH, bilinear3, bilinear_gradient, host_pixel_in_view, inside, pattern_shifts, prefetch_patch,
    search_line, warp_ray,
)
from vo_core.direct.pyramid import ImagePyramid, PyramidLevel, squared_gradient
from vo_core.geometry.camera import PinholeCamera

MISSING_ENERGY = 1e5  # traceOn: energy of a pattern pixel that falls outside the image


class TraceStatus(IntEnum):
    """DSO's ImmaturePointStatus."""

    UNINITIALIZED = 0
    GOOD = 1  # traced, interval updated
    OOB = 2  # out of bounds (or too large a scale change): dropped
    OUTLIER = 3  # energy too high
    SKIPPED = 4  # interval already below 1.5 px: nothing to learn
    BAD_CONDITION = 5  # the epipolar line runs along an edge: the search would not shrink the interval


ACTIVATABLE = (TraceStatus.GOOD, TraceStatus.SKIPPED, TraceStatus.BAD_CONDITION, TraceStatus.OOB)
# Whether each status (its value as index) is ACTIVATABLE: one look-up per point (np.isin sorted the statuses).
_IS_ACTIVATABLE = np.isin(np.arange(max(TraceStatus) + 1), ACTIVATABLE)


@dataclass
class ImmaturePoints:
    """All immature points of one host keyframe (struct of arrays)."""

    uv: np.ndarray  # (N, 2) level-0 pixels in the host
    kind: np.ndarray  # (N,) selector type 1/2/4
    color: np.ndarray  # (N, 8) host intensities of the pattern
    weight: np.ndarray  # (N, 8) gradient-dependent pattern weights (GN energy)
    grad_h: np.ndarray  # (N, 2, 2) sum over the pattern of g g^T
    host_grad_sq: np.ndarray  # (N, 8) float32 |grad I|^2 of the pattern, carried into the window on activation
    energy_threshold: np.ndarray  # (N,)
    idepth_min: np.ndarray
    idepth_max: np.ndarray  # NaN until the first successful trace
    quality: np.ndarray
    status: np.ndarray  # TraceStatus values
    pixel_interval: np.ndarray  # length of the last interval in px
    last_uv: np.ndarray  # (N, 2) last traced position, -1 when unknown

    def __len__(self) -> int:
        return len(self.uv)

    @classmethod
    def create(cls, host: ImagePyramid, uv: np.ndarray, kind: np.ndarray, config: ImmatureConfig) -> "ImmaturePoints":
        """ImmaturePoint's constructor: sample the pattern in the host; drop points whose pattern leaves it."""
        pattern, inside = PatternPoints.sample(host, uv, config)
        n = len(pattern.uv)
        return cls(
            uv=pattern.uv,
            kind=np.asarray(kind)[inside],
            color=pattern.color,
            weight=pattern.weight,
            grad_h=pattern.grad_h,
            host_grad_sq=pattern.host_grad_sq,
            energy_threshold=pattern.energy_threshold,
            idepth_min=np.zeros(n),
            idepth_max=np.full(n, np.nan),
            quality=np.full(n, 10000.0),
            status=np.full(n, TraceStatus.UNINITIALIZED, dtype=np.int8),
            pixel_interval=np.zeros(n),
            last_uv=np.full((n, 2), -1.0),
        )

    def subset(self, keep: np.ndarray) -> "ImmaturePoints":
        """The points where the mask ``keep`` is True (turned into rows once: thirteen arrays are indexed)."""
        rows = np.flatnonzero(keep)
        return ImmaturePoints(**{name: getattr(self, name)[rows] for name in self.__dataclass_fields__})

    # ---------------------------------------------------------------------------------- activation

    def activatable(self, config: ImmatureConfig) -> np.ndarray:
        """activatePointsMT's test: traced well, a narrow interval, an unambiguous match, positive depth."""
        return (
            _IS_ACTIVATABLE[self.status]
            & (self.pixel_interval < config.max_activation_interval)
            & (self.quality > config.min_trace_quality)
            & (self.idepth_max + self.idepth_min > 0)
        )

    def hopeless(self) -> np.ndarray:
        """Points DSO deletes: never traced successfully, outliers, or out of bounds without a result."""
        return ~np.isfinite(self.idepth_max) | (self.status == TraceStatus.OUTLIER)

    @property
    def idepth(self) -> np.ndarray:
        """The estimate used on activation: the middle of the interval."""
        return 0.5 * (self.idepth_min + self.idepth_max)

    # ---------------------------------------------------------------------------------- tracing

    def trace(
        self, frame: PyramidLevel, T_frame_host: np.ndarray, affine: tuple[float, float], config: ImmatureConfig
    ) -> None:
        """traceOn for every point not yet out of bounds, against level 0 of a new frame."""
        todo = np.flatnonzero(self.status != TraceStatus.OOB)
        if len(todo) == 0:
            return
        camera = frame.camera
        K = camera.K
        KRKi = K @ T_frame_host[:3, :3] @ np.linalg.inv(K)
        Kt = K @ T_frame_host[:3, 3]
        pr = np.column_stack([self.uv[todo], np.ones(len(todo))]) @ KRKi.T
        rotated = PATTERN @ KRKi[:2, :2].T  # the pattern turned by the in-plane part of the warp (rotatetPattern)
        factor, offset = affine
        _trace_points(
            todo, pr, Kt, rotated, frame.intensity, frame.packed, float(factor), float(offset), self.color,
            self.weight, self.grad_h, self.energy_threshold, self.idepth_min, self.idepth_max, self.quality,
            self.status, self.pixel_interval, self.last_uv, camera.width, camera.height, config.border,
            (camera.width + camera.height) * config.max_pixel_search, config.min_scale_change, config.max_scale_change,
            config.trace_slack_interval, config.trace_stepsize, config.trace_min_improvement, config.max_steps,
            config.huber_threshold, MISSING_ENERGY, config.min_trace_test_radius, config.trace_gn_iterations,
            config.trace_gn_threshold, config.trace_extra_slack,
        )


# The trace of one host's points, one compiled loop (each point's traceOn in turn): in numpy, the thirty array
# operations around the searches cost a third of the tracing, seven hosts a frame. Division by zero gives inf or NaN
# (vo_core.compiled), which the tests below turn into a status.
@kernel
def _trace_points(todo, pr, Kt, rotated, intensity, packed, factor, offset, color, weight, grad_h, energy_threshold,
                  idepth_min, idepth_max, quality, status, pixel_interval, last_uv, width, height, border, max_search,
                  min_scale_change, max_scale_change, slack_interval, stepsize, min_improvement, max_steps, huber,
                  missing_energy, test_radius, gn_iterations, gn_threshold, extra_slack):
    """For each point ``todo[j]`` (``pr[j]``: K R K^-1 of its host pixel, Kt: K t): project its inverse-depth
    interval, then, unless the projection leaves the image or the depth ratio [min, max]_scale_change (OOB), the
    interval is already below ``slack_interval`` px (SKIPPED) or the epipolar line runs along the gradient
    (BAD_CONDITION; both keep the projected interval's midpoint), search the segment (``search_line``), refine
    along it (``_refine_on_line``) and shrink the interval to the pixel error bound of the result (GOOD), or mark the
    point OUTLIER (OOB when it already was one). An unbounded interval is searched ``max_search`` px from its
    projection at infinity."""
    energies = np.empty(max_steps)
    radius = int(np.ceil(np.abs(rotated).max()))
    for j in range(len(todo)):
        i = todo[j]
        if j + 1 < len(todo):  # where the next point's search starts, asked for while this one's runs (5-10 %)
            id_next = idepth_min[todo[j + 1]]
            z_next = pr[j + 1, 2] + id_next * Kt[2]
            if z_next > 0.0:
                prefetch_patch(intensity, (pr[j + 1, 0] + id_next * Kt[0]) / z_next,
                               (pr[j + 1, 1] + id_next * Kt[1]) / z_next, radius)
        id_min = idepth_min[i]
        z_min = pr[j, 2] + id_min * Kt[2]
        u_min = (pr[j, 0] + id_min * Kt[0]) / z_min
        v_min = (pr[j, 1] + id_min * Kt[1]) / z_min
        bounded = np.isfinite(idepth_max[i])
        far = idepth_max[i] if bounded else 0.01  # unbounded: any depth gives the direction
        z_max = pr[j, 2] + far * Kt[2]
        u_max = (pr[j, 0] + far * Kt[0]) / z_max
        v_max = (pr[j, 1] + far * Kt[1]) / z_max
        dist = np.hypot(u_max - u_min, v_max - v_min)
        if not bounded:
            u_max, v_max = u_min + max_search * (u_max - u_min) / dist, v_min + max_search * (v_max - v_min) / dist
            dist = max_search
        scale_ok = id_min < 0 or (z_min > min_scale_change and z_min < max_scale_change)
        if not (inside(u_min, v_min, width, height, border) and inside(u_max, v_max, width, height, border)
                and scale_ok and np.isfinite(dist)):
            _lose(i, TraceStatus.OOB, status, last_uv, pixel_interval)
            continue
        if bounded and dist < slack_interval:
            _keep_midpoint(i, TraceStatus.SKIPPED, u_min, v_min, u_max, v_max, dist, status, last_uv, pixel_interval)
            continue
        # Error bound in pixels: large when the gradient is parallel to the epipolar line.
        dx, dy = stepsize * (u_max - u_min), stepsize * (v_max - v_min)
        along = grad_h[i, 0, 0] * dx * dx + 2 * grad_h[i, 0, 1] * dx * dy + grad_h[i, 1, 1] * dy * dy
        across = grad_h[i, 0, 0] * dy * dy - 2 * grad_h[i, 0, 1] * dx * dy + grad_h[i, 1, 1] * dx * dx
        error_px = 0.2 + 0.2 * (along + across) / along
        if bounded and not (error_px * min_improvement <= dist):
            _keep_midpoint(i, TraceStatus.BAD_CONDITION, u_min, v_min, u_max, v_max, dist, status, last_uv,
                           pixel_interval)
            continue
        error_px = np.minimum(error_px, 10.0)
        dx, dy = dx / dist, dy / dist
        num_steps = min(int(1.9999 + min(dist, max_search) / stepsize), max_steps - 1)
        shift = u_min * 1000.0 - np.floor(u_min * 1000.0)  # traceOn's random shift of the first step
        best_u, best_v, new_quality = search_line(intensity, u_min - shift * dx, v_min - shift * dy, dx, dy,
                                                  num_steps, rotated, color[i], factor, offset, huber,
                                                  missing_energy, test_radius, energies)
        if new_quality < quality[i] or num_steps > 10:
            quality[i] = new_quality
        best_u, best_v, best_energy = _refine_on_line(packed, best_u, best_v, dx, dy, rotated, color[i], weight[i],
                                                      factor, offset, huber, missing_energy, gn_iterations,
                                                      gn_threshold)
        if not best_energy < energy_threshold[i] * extra_slack:
            _lose(i, TraceStatus.OOB if status[i] == TraceStatus.OUTLIER else TraceStatus.OUTLIER, status, last_uv,
                  pixel_interval)
            continue
        # The new interval from the pixel error bound, along the dominant image axis of the line.
        if dx * dx > dy * dy:
            lo, hi = best_u - error_px * dx, best_u + error_px * dx
            id_lo = (pr[j, 2] * lo - pr[j, 0]) / (Kt[0] - Kt[2] * lo)
            id_hi = (pr[j, 2] * hi - pr[j, 0]) / (Kt[0] - Kt[2] * hi)
        else:
            lo, hi = best_v - error_px * dy, best_v + error_px * dy
            id_lo = (pr[j, 2] * lo - pr[j, 1]) / (Kt[1] - Kt[2] * lo)
            id_hi = (pr[j, 2] * hi - pr[j, 1]) / (Kt[1] - Kt[2] * hi)
        new_min, new_max = np.minimum(id_lo, id_hi), np.maximum(id_lo, id_hi)
        if not (np.isfinite(new_min) and np.isfinite(new_max)) or new_max < 0:
            _lose(i, TraceStatus.OUTLIER, status, last_uv, pixel_interval)
            continue
        idepth_min[i], idepth_max[i] = new_min, new_max
        status[i] = TraceStatus.GOOD
        pixel_interval[i] = 2.0 * error_px
        last_uv[i, 0], last_uv[i, 1] = best_u, best_v


@kernel
def _lose(i, new_status, status, last_uv, pixel_interval):
    """The point's trace gave no position."""
    status[i] = new_status
    last_uv[i, 0] = last_uv[i, 1] = -1.0
    pixel_interval[i] = 0.0


@kernel
def _keep_midpoint(i, new_status, u_min, v_min, u_max, v_max, dist, status, last_uv, pixel_interval):
    status[i] = new_status
    last_uv[i, 0], last_uv[i, 1] = (u_min + u_max) * 0.5, (v_min + v_max) * 0.5
    pixel_interval[i] = dist


@kernel
def _refine_on_line(packed, start_u, start_v, dx, dy, rotated, color, weight, factor, offset, huber, missing_energy,
                    iterations, threshold):
    """traceOn's Gauss-Newton refinement of one point's position along its epipolar direction (dx, dy).

    The energy is the pattern's Huber energy with the gradient-dependent weights squared; a pattern pixel outside
    the image costs ``missing_energy``. A step that lowers the energy is taken (clamped to +-0.5 px,
    H = 1 + sum w (d r / d step)^2); one that raises it goes back half way from the last good position. It stops
    when its last step is below ``threshold``. Returns the position and its energy."""
    best_u, best_v = start_u, start_v
    best_energy = missing_energy
    backup_u, backup_v = best_u, best_v
    step_back = 0.0
    for _ in range(iterations):
        energy = 0.0
        H = 1.0
        b = 0.0
        for k in range(rotated.shape[0]):
            pu = best_u + rotated[k, 0]
            pv = best_v + rotated[k, 1]
            if not (pu >= 0.0 and pv >= 0.0 and pu < packed.shape[1] - 1 and pv < packed.shape[0] - 1):
                energy += missing_energy
                continue
            intensity, gx, gy = bilinear3(packed, pu, pv)
            residual = intensity - (factor * color[k] + offset)
            magnitude = abs(residual)
            w = 1.0 if magnitude <= huber else huber / magnitude
            energy += weight[k] * weight[k] * w * residual * residual * (2.0 - w)
            d_residual = dx * gx + dy * gy
            H += w * d_residual * d_residual
            b += w * residual * d_residual
        if energy > best_energy:
            step_back *= 0.5
            best_u = backup_u + step_back * dx
            best_v = backup_v + step_back * dy
        else:
            step = -b / H
            step = min(max(step, -0.5), 0.5) if np.isfinite(step) else 0.0
            backup_u, backup_v = best_u, best_v
            step_back = step
            best_u += step * dx
            best_v += step * dy
            best_energy = energy
        if not abs(step_back) >= threshold:
            break
    return best_u, best_v, best_energy


@dataclass
class ActivationTargets:
    """The other keyframes of the window as seen from a host: their level-0 intensities, poses and brightness
    transfers. The images are the window's (WindowOptimizer.window_images), shared by its hosts; target j is
    ``images[image_index[j]]``."""

    camera: PinholeCamera
    images: np.ndarray  # (S, H, W) float32
    image_index: np.ndarray  # (T,) int64
    T_target_host: np.ndarray  # (T, 4, 4)
    affine: np.ndarray  # (T, 2) (factor, offset) predicting target intensities from host intensities


@dataclass
class PatternPoints:
    """Host-side data of points whose inverse depth is optimized: pattern intensities and weights."""

    uv: np.ndarray  # (N, 2) level-0 host pixels
    color: np.ndarray  # (N, 8)
    weight: np.ndarray  # (N, 8) gradient-dependent weights (setting_outlierTHSumComponent)
    energy_threshold: np.ndarray  # (N,)
    grad_h: np.ndarray  # (N, 2, 2) sum over the pattern of g g^T (the epipolar search's error bound)
    host_grad_sq: np.ndarray  # (N, 8) float32 |grad I|^2 of the pattern (host_pattern's, for the window)

    @classmethod
    def sample(cls, host: ImagePyramid, uv: np.ndarray, config: ImmatureConfig) -> tuple["PatternPoints", np.ndarray]:
        """The pattern of each pixel in the host; also the mask of pixels whose pattern lies inside."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        sampled = _sample_pattern(host[0], uv)
        inside = np.all(np.isfinite(sampled[..., 0]), axis=1)
        sampled = sampled[inside]
        gradient = sampled[..., 1:].astype(float)
        grad_sq = np.sum(gradient**2, axis=2)
        points = cls(
            uv=uv[inside],
            color=sampled[..., 0].astype(np.float32),
            weight=np.sqrt(config.outlier_sum_component / (config.outlier_sum_component + grad_sq)),
            energy_threshold=np.full(int(inside.sum()), len(PATTERN) * config.outlier_threshold),
            grad_h=gradient.transpose(0, 2, 1) @ gradient,  # batched matmul: 0.2 ms where einsum took 0.6
            host_grad_sq=squared_gradient(sampled),  # float32, as the window weighs its residuals
        )
        return points, inside


def host_pattern(level: PyramidLevel, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What an active point carries from its host into the window (DSO's PointHessian color and weights): the
    pattern's intensities and squared gradient magnitudes around level-0 pixels ``uv``, (N, 8) float32 each, zero
    where the pattern leaves the image. Taken while the host still has its gradients."""
    sampled = _sample_pattern(level, np.asarray(uv, dtype=float).reshape(-1, 2))
    return np.nan_to_num(sampled[..., 0]), np.nan_to_num(squared_gradient(sampled))


def _sample_pattern(level: PyramidLevel, uv: np.ndarray) -> np.ndarray:
    """(N, 8, 3) float32 intensity and gradients at the pattern around each pixel; NaN outside the image."""
    pattern_uv = uv[:, None, :] + PATTERN[None]
    return level.sample(pattern_uv[..., 0], pattern_uv[..., 1])


@dataclass
class ActivationCandidates:
    """One host's points to activate: ``index`` into its immature ``points``, optimized in its ``targets``."""

    points: ImmaturePoints
    index: np.ndarray
    targets: ActivationTargets


def optimize_for_activation(
    candidates: list[ActivationCandidates], config: ImmatureConfig
) -> list[tuple[np.ndarray, np.ndarray]]:
    """optimizeImmaturePoint for every host's candidates, from the middle of their traced interval: LM on each
    point's inverse depth over all its host's targets, poses held fixed. The hosts' targets share the window's images
    and are as many for each host (the window's other keyframes).

    Returns, per host, (inverse depths, usable, inliers): a point is usable when its inverse-depth Hessian reaches
    ``min_idepth_hessian`` and at least ``activation_min_observations`` targets are inliers; inliers (n, targets) says
    in which of its host's targets (in their order) its residual was in at the end."""
    counts = [len(c.index) for c in candidates]
    idepth = np.concatenate([np.asarray(c.points.idepth[c.index], float) for c in candidates] or [np.zeros(0)])
    targets = [c.targets for c in candidates]
    usable = np.zeros(len(idepth), dtype=bool)
    inliers = np.zeros((len(idepth), len(targets[0].image_index) if targets else 0), dtype=bool)
    if len(idepth) and len(targets[0].image_index):
        if any(t.images is not targets[0].images for t in targets):
            raise ValueError("optimize_for_activation: the hosts' targets must share the window's images")
        camera = targets[0].camera
        T_target_host = np.stack([t.T_target_host for t in targets])  # (hosts, targets, 4, 4)
        affine = np.stack([t.affine for t in targets])

        def gathered(field: str) -> np.ndarray:
            return np.concatenate([getattr(c.points, field)[c.index] for c in candidates])

        with PARALLEL_LAUNCH:
            usable, inliers = _optimize_inverse_depths(
                camera.unproject(gathered("uv")), np.repeat(np.arange(len(candidates)), counts),
                pattern_rays(camera.intrinsics), idepth, gathered("color"), gathered("weight") ** 2,
                gathered("energy_threshold"), targets[0].images, np.stack([t.image_index for t in targets]),
                np.ascontiguousarray(T_target_host[..., :3, :3]), np.ascontiguousarray(T_target_host[..., :3, 3]),
                np.ascontiguousarray(affine[..., 0]), np.ascontiguousarray(affine[..., 1]), camera.intrinsics,
                float(config.huber_threshold), float(config.first_outlier_slack), int(config.activation_gn_iterations),
                float(config.min_idepth_hessian), int(config.activation_min_observations),
            )
    split = np.cumsum(counts)[:-1]
    return list(zip(np.split(idepth, split), np.split(usable, split), np.split(inliers, split)))


@kernel
def half_resolution_pixels(uv, idepth, T_viewer_host, intrinsics, width, height):
    """Where host pixels ``uv`` at inverse depths ``idepth`` land in a viewer: the viewer's pixel at half resolution
    (level 1, rounded half to even as np.rint), and whether they land in front of it and inside its ``width`` x
    ``height`` image. activatePointsMT's distance map and candidates, in one compiled pass (numpy's dozen passes
    over each host's points cost about 2 ms a keyframe)."""
    R, t = T_viewer_host[:3, :3], T_viewer_host[:3, 3]
    pixel = np.empty((len(uv), 2), np.int64)
    inside = np.empty(len(uv), np.bool_)
    for i in range(len(uv)):
        u, v, inside[i] = host_pixel_in_view(R, t, intrinsics, uv[i, 0], uv[i, 1], idepth[i], width, height)
        pixel[i, 0], pixel[i, 1] = int(np.rint((u + 0.5) / 2.0 - 0.5)), int(np.rint((v + 0.5) / 2.0 - 0.5))
    return pixel, inside


# optimizeImmaturePoint stops once a step moves the inverse depth by less than this share of it.
CONVERGED_STEP_SHARE = 1e-4
# Points per block of the activation's parallel loop: a keyframe activates several hundred points of all its hosts in
# one compiled call (one launch of numba's threads a keyframe; a launch per host cost parking's threaded run 1.2 s of
# CPU), and each point's LM is independent of the others, so the blocks' split does not change a result.
ACTIVATION_BLOCK = 32


@kernel(parallel=True)
def _optimize_inverse_depths(rays, host, pattern_rays, idepth, color, weight_sq, threshold, images, image_index, R, t,
                             factor, offset, intrinsics, huber, first_outlier_slack, iterations, min_hessian,
                             min_observations):
    """optimize_for_activation's LM, point by point, blocks of points on numba's threads. ``rays`` (n, 3) are the
    points' K^-1 (u, v, 1) in their host ``host[i]``, pattern pixel k's ray is that + ``pattern_rays[k]``; target j
    of host h is ``images[image_index[h, j]]`` at (R[h, j], t[h, j]) = T_target_host with the affine transfer
    (factor[h, j], offset[h, j]). ``idepth`` is optimized in place; returns the usable mask and the inlier targets."""
    usable, inliers, pattern_shift = _activation_buffers(len(idepth), R, pattern_rays)
    for block in numba.prange((len(idepth) + ACTIVATION_BLOCK - 1) // ACTIVATION_BLOCK):
        first = block * ACTIVATION_BLOCK
        _optimize_points(first, min(first + ACTIVATION_BLOCK, len(idepth)), rays, host, pattern_shift, idepth, color,
                         weight_sq, threshold, images, image_index, R, t, factor, offset, intrinsics, huber,
                         first_outlier_slack, iterations, min_hessian, min_observations, usable, inliers)
    return usable, inliers


@kernel
def _activation_buffers(n, R, pattern_rays):
    """The usable mask, the inlier targets and each (host, target) pair's pattern_shifts (outside the parallel
    function: numba makes its array expressions parallel regions of their own)."""
    pattern_shift = np.empty((R.shape[0], R.shape[1], len(pattern_rays), 3))
    for h in range(R.shape[0]):
        for j in range(R.shape[1]):
            pattern_shifts(R[h, j], pattern_rays, pattern_shift[h, j])
    return np.zeros(n, np.bool_), np.zeros((n, R.shape[1]), np.bool_), pattern_shift


@kernel
def _optimize_points(first, end, rays, host, pattern_shift, idepth, color, weight_sq, threshold, images, image_index,
                     R, t, factor, offset, intrinsics, huber, first_outlier_slack, iterations, min_hessian,
                     min_observations, usable, inliers):
    """_optimize_inverse_depths for points first..end-1."""
    n_targets, pattern = image_index.shape[1], pattern_shift.shape[2]
    in_bounds = np.empty(n_targets, np.bool_)  # a target once out of bounds stays out (ResState OOB)
    inlier = np.empty(n_targets, np.bool_)
    trial_inlier = np.empty(n_targets, np.bool_)
    residuals = np.empty(pattern)
    d_idepth = np.empty(pattern)
    for i in range(first, end):
        h = host[i]
        in_bounds[:] = True
        inlier[:] = False
        energy, H, b = _depth_system(i, idepth[i], first_outlier_slack, rays, pattern_shift[h], color, weight_sq,
                                     threshold, images, image_index[h], R[h], t[h], factor[h], offset[h], intrinsics,
                                     huber, in_bounds, inlier, residuals, d_idepth)
        running = np.isfinite(energy) and H >= min_hessian
        usable[i] = running
        lam = 0.1
        for _ in range(iterations):
            if not running:
                break
            step = b / (H * (1.0 + lam))
            trial = idepth[i] - step
            e_new, H_new, b_new = _depth_system(i, trial, 1.0, rays, pattern_shift[h], color, weight_sq, threshold,
                                                images, image_index[h], R[h], t[h], factor[h], offset[h], intrinsics,
                                                huber, in_bounds, trial_inlier, residuals, d_idepth)
            usable[i] = H_new >= min_hessian
            if e_new < energy:
                idepth[i], energy, H, b = trial, e_new, H_new, b_new
                inlier[:] = trial_inlier
                lam *= 0.5
            else:
                lam *= 5.0
            running = usable[i] and not abs(step) < CONVERGED_STEP_SHARE * abs(idepth[i])
        usable[i] = usable[i] and np.isfinite(idepth[i]) and idepth[i] > 0 and inlier.sum() >= min_observations
        inliers[i] = inlier


@kernel
def _depth_system(i, idepth, outlier_slack, rays, pattern_shift, color, weight_sq, threshold, images, image_index, R,
                  t, factor, offset, intrinsics, huber, in_bounds, inlier, residuals, d_idepth):
    """linearizeResidual of point i at ``idepth``, summed over the targets in order: (energy, H_dd, b_d); sets
    ``inlier`` per target and clears ``in_bounds`` where the pattern leaves the image (a 1 px margin, 2 px on the
    right and bottom, where the gradients at the four corners need a pixel beyond them) or the point falls behind
    the camera. The targets are older keyframes, which keep only their intensities (``PyramidLevel.release_packed``)."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    height, width = images.shape[1], images.shape[2]
    point_threshold = threshold[i] * outlier_slack
    energy = H = b = 0.0
    for j in range(len(image_index)):
        inlier[j] = False
        if not in_bounds[j]:
            continue
        intensity = images[image_index[j]]
        Rj, tj = R[j], t[j]
        xc, yc, zc = warp_ray(Rj, tj, rays[i, 0], rays[i, 1], rays[i, 2], idepth)
        for k in range(len(residuals)):
            x, y, z = xc + pattern_shift[j, k, 0], yc + pattern_shift[j, k, 1], zc + pattern_shift[j, k, 2]
            inverse_z = 1.0 / z if z != 0.0 else -1.0
            u, v = x * inverse_z, y * inverse_z
            Ku, Kv = fx * u + cx, fy * v + cy
            if not (inverse_z > 0.0 and Ku >= 1.0 and Kv >= 1.0 and Ku < width - 2 and Kv < height - 2):
                in_bounds[j] = False
                break
            value, gx, gy = bilinear_gradient(intensity, Ku, Kv)
            residuals[k] = value - (factor[j] * color[i, k] + offset[j])
            # d residual / d inverse depth through the projection (u, v) = (x, y) / z
            d_idepth[k] = gx * fx * (tj[0] - tj[2] * u) * inverse_z + gy * fy * (tj[1] - tj[2] * v) * inverse_z
        if not in_bounds[j]:
            continue
        e = 0.0
        for k in range(len(residuals)):
            residual = residuals[k]
            magnitude = abs(residual)
            w = 1.0 if magnitude <= huber else huber / magnitude
            e += weight_sq[i, k] * w * residual * residual * (2.0 - w)
            hw = w * weight_sq[i, k]
            H += hw * d_idepth[k] * d_idepth[k]
            b += hw * residual * d_idepth[k]
        inlier[j] = e <= point_threshold
        energy += min(e, point_threshold)
    return energy, H, b
