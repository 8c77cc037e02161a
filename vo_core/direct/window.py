"""Windowed photometric bundle adjustment (DSO's FullSystem::optimize and EnergyFunctional, FDMO section 4).

The window's keyframes (pose T_world_cam, affine (a, b)) and the inverse depths of their active points are
optimized jointly over all photometric residuals: every point, an 8-pixel pattern in its host keyframe, is
compared with every other keyframe of the window it projects into (DSO Eq. 4, Huber weights times the
gradient-dependent weights). One iteration of Levenberg-Marquardt:

1. linearize every (host, target) pair of keyframes in one compiled pass (photometric_kernels.
   window_linearization): each pair's local system over the relative pose increment and the affine parameters,
   and each point's inverse-depth terms, mapped at once into the keyframes' absolute parameters (with left
   increments in the world frame, T_target_host = T_world_target^-1 T_world_host moves by
   xi = Ad(T_target_world) (delta_host - delta_target)). As DSO, a point's pixel motion is taken at its centre
   and shared by its 8 pattern pixels, so each pattern reduces to a few sums before it meets the pose
   parameters; one kernel call per energy evaluation (per-pair Python bookkeeping cost as much as the
   arithmetic when it ran pair by pair), blocks of its points on numba's threads (a captured 2,563-point window:
   6.7-8.3 -> 3.3-4.1 ms a call on 2 cores with the targets read as intensities; the same result on any number
   of threads);
2. Schur complement over the points (each point one inverse depth, so its block is a scalar):
   H_s = H_kk - H_kp H_pp^-1 H_pk, b_s = b_k - H_kp H_pp^-1 b_p; solve the small dense keyframe system,
   then each point's step by back substitution;
3. accept the step if the energy drops (lambda / 4), otherwise reject it (lambda x 100): DSO's test, which its
   default (setting_forceAceptStep) skips, taking every step; taking every step here moved the real folders both
   ways (BENCHMARKS.md, Tried and not kept).

A residual that is out of view when an optimization ends (its pattern leaves the target image, or the point is
behind the target camera) is dropped for good (``Keyframe.dropped_residuals``), as DSO deletes residuals that are out
of bounds then: a point at the edge of a keyframe's view no longer flickers in and out of the energy from one
optimization to the next. DSO deletes the outliers too; that made parking's ATE twice as large (median of 5
seeds, BENCHMARKS.md), and outliers stay in the set, to be judged again at each optimization. DSO makes a new
point's residuals only where its activation's ended in: an option here (ImmatureConfig.residuals_only_where_activated).

Gauge: the oldest keyframe of the window (pose and affine) is held fixed. The photometric energy does not see
the scale either: keyframes that left the window are kept as a prior (marginalization.py) that holds it, and
once there is one, from the second step of an optimization on, the keyframe step loses its component along the
window's scale (DSO's SOLVER_ORTHOGONALIZE_X_LATER).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
from threadpoolctl import ThreadpoolController

from vo_core.compiled import kernel
from vo_core.direct.affine import relative_affines
from vo_core.direct.config import WindowConfig
from vo_core.direct.coarse_tracker import PATTERN, pattern_rays
from vo_core.direct.marginalization import MarginalizationPrior
from vo_core.direct.photometric_kernels import PARALLEL_LAUNCH, window_linearization
from vo_core.geometry.lie import se3_adjoint_compiled, se3_exp, se3_inverse_compiled

PARAMS_PER_KEYFRAME = 8  # pose increment (v, w), a, b
# The window's dense products are small (8K x P with P ~ 2000): threaded BLAS gains nothing there, and when the
# cores are shared (a viewer, the image reader, another job) its spinning threads made window optimizations 8x
# slower (parking: 389 ms instead of 52 ms per optimization beside a running pytest, 2 cores).
_BLAS = ThreadpoolController()
POINT_IN, POINT_OUT, POINT_OUTLIER = 0, 1, 2


@dataclass
class _WindowPoints:
    """The active points of all keyframes, host by host, and the keyframes' images, as the kernel needs them."""

    pattern_rays: np.ndarray  # (8, 3) K^-1 (du, dv, 0): each pattern pixel's ray minus its point's
    center_rays: np.ndarray  # (P, 3) K^-1 (u, v, 1) of the points
    color: np.ndarray  # (P, 8) host intensities
    weight: np.ndarray  # (P, 8) host gradient weights sqrt(c / (c + |grad|^2))
    host_start: np.ndarray  # (K + 1,) the points of keyframe h are host_start[h]:host_start[h + 1]
    # (S, H, W) the window's level-0 intensities in their slots (the kernel takes the gradients from them), keyframe k
    # in images[image_slots[k]]: one array, not a numba typed list, whose first construction in a process costs 0.6 s.
    images: np.ndarray
    image_slots: np.ndarray  # (K,) int64
    dropped: np.ndarray  # (K, P) bool: point i's residual in keyframe k is no longer evaluated (dropped_residuals)


@dataclass
class WindowReport:
    """An optimization's outcome. Its energies are the photometric ones (robust squared residuals, outliers charged
    the outlier energy): never negative, comparable from one optimization to the next. The marginalization prior's
    term is reported apart: it is the quadratic b^T d + d^T H d / 2 in the step d from the prior's linearization
    point, whose constant DSO drops too, so it is negative wherever the window moved the way the prior pulls (the
    sum of both is what the optimization lowers)."""

    iterations: int
    energy_before: float
    energy_after: float
    prior_energy_before: float
    prior_energy_after: float
    points: int
    residuals: int
    outliers: int  # residuals in view beyond their outlier threshold (WindowConfig.adaptive_outlier_threshold)
    newest_threshold: float  # the newest keyframe's outlier threshold on a point's energy, as the optimization left it
    kept: np.ndarray  # (points,) bool: which of the window's points (host by host, in order) are still active
    ms: float

    @property
    def removed_points(self) -> int:
        return int(np.count_nonzero(~self.kept))

    def as_details(self) -> dict:
        return {
            "iterations": self.iterations, "energy_before": round(self.energy_before, 1),
            "energy_after": round(self.energy_after, 1), "prior_energy_before": round(self.prior_energy_before, 1),
            "prior_energy_after": round(self.prior_energy_after, 1), "points": self.points, "residuals": self.residuals,
            "outliers": self.outliers, "newest_threshold": round(self.newest_threshold, 1),
            "removed_points": self.removed_points, "ms": round(self.ms, 1),
        }


class WindowOptimizer:
    """Optimizes a list of keyframes in place (their T_world_cam, affine and active_idepth). A keyframe's points
    bring their host pattern (active_color, active_grad_sq): the window reads only the keyframes' intensities."""

    def __init__(self, config: WindowConfig, huber_threshold: float, outlier_threshold: float,
                 outlier_sum_component: float):
        self.config = config
        self.huber = huber_threshold
        self.outlier_energy = len(PATTERN) * outlier_threshold
        self.weight_component = outlier_sum_component
        # The window's images, each copied once into a slot when its keyframe joins (window_images): stacking the
        # whole window again at every keyframe cost 1.4 ms on parking, 3 ms on KITTI, while tracking waited.
        self._image_store: np.ndarray | None = None
        self._slot_holders: list = []  # the keyframe whose image each slot holds, None where free

    @_BLAS.wrap(limits=1, user_api="blas")
    def optimize(self, keyframes: list, prior: MarginalizationPrior) -> WindowReport:
        start = time.perf_counter()
        points = self._window_points(keyframes)
        idepth = np.concatenate([k.active_idepth for k in keyframes])
        poses = [k.T_world_cam.copy() for k in keyframes]
        affines = [np.asarray(k.affine, float).copy() for k in keyframes]
        thresholds = self._energy_thresholds(keyframes)
        system = self._linearize(keyframes, points, poses, affines, idepth, prior, thresholds)
        if self.config.adaptive_outlier_threshold:
            thresholds[-1] = self._newest_energy_threshold(system)
            system = system.recapped(_residual_thresholds(thresholds, points.host_start))
        energy = system.energy
        first = system
        lam = self.config.initial_lambda
        iterations = 0
        for iterations in range(1, self.config.max_iterations + 1):
            fixed_scale = len(prior) > 0 and 0 < self.config.scale_fixed_from_step <= iterations
            step_keyframes, step_points = self._solve(system, lam, poses, fixed_scale)
            trial_poses = [se3_exp(step_keyframes[i, :6]) @ T for i, T in enumerate(poses)]
            trial_affines = [ab + step_keyframes[i, 6:] for i, ab in enumerate(affines)]
            trial_idepth = np.maximum(idepth + step_points, self.config.min_inverse_depth)
            small_step = np.abs(step_keyframes).max(initial=0.0) < self.config.min_step
            # The last step's trial (or one after which the loop ends, if accepted) needs only its energy: no step is
            # solved from its system.
            last = iterations == self.config.max_iterations or small_step
            trial = self._linearize(keyframes, points, trial_poses, trial_affines, trial_idepth, prior, thresholds,
                                    start=first, with_terms=not last)
            if trial.energy < energy:
                # Relative to the photometric energy: the total can be negative (the prior's term; WindowReport).
                small_gain = energy - trial.energy < self.config.min_relative_decrease * system.photometric_energy
                poses, affines, idepth, system, energy = trial_poses, trial_affines, trial_idepth, trial, trial.energy
                lam *= self.config.lambda_decrease
                if small_gain or small_step:
                    break
            else:
                lam *= self.config.lambda_increase
        kept = self._write_back(keyframes, poses, affines, idepth, system)
        for keyframe, threshold in zip(keyframes, thresholds):
            keyframe.energy_threshold = float(threshold)
        if self.config.adaptive_outlier_threshold:  # as DSO, the newest keyframe keeps the one of its final state
            keyframes[-1].energy_threshold = self._newest_energy_threshold(system)
        return WindowReport(
            iterations, first.photometric_energy, system.photometric_energy, first.prior_energy, system.prior_energy,
            len(idepth), system.residuals, int(system.outliers.sum()), keyframes[-1].energy_threshold, kept,
            (time.perf_counter() - start) * 1000.0,
        )

    @_BLAS.wrap(limits=1, user_api="blas")
    def marginalize(
        self, keyframes: list, leaving: int, prior: MarginalizationPrior
    ) -> tuple[MarginalizationPrior, int]:
        """The prior once keyframe ``leaving`` (a window index) goes, with the points it hosts (DSO's
        marginalizeFrame after marginalizePointsF); and how many points were marginalized."""
        points = self._window_points(keyframes)
        idepth = np.concatenate([k.active_idepth for k in keyframes])
        poses = [k.T_world_cam for k in keyframes]
        affines = [np.asarray(k.affine, float) for k in keyframes]
        system = self._linearize(keyframes, points, poses, affines, idepth, MarginalizationPrior(), only_host=leaving)
        hosted = slice(points.host_start[leaving], points.host_start[leaving + 1])  # the other points' rows are zero
        H_kp_scaled = system.H_kp[:, hosted] / (system.H_pp[hosted] + self.config.idepth_regularization)
        H = system.H_kk - H_kp_scaled @ system.H_kp[:, hosted].T
        b = system.b_k - H_kp_scaled @ system.b_p[hosted]
        frame_ids = [k.frame_index for k in keyframes]
        new_prior = prior.marginalize(frame_ids, poses, affines, H, b, leaving, self.config.marginalization_damping)
        return new_prior, int(np.count_nonzero(system.inliers))

    # ------------------------------------------------------------------------------------ linearization

    def window_images(self, keyframes: list) -> tuple[np.ndarray, np.ndarray]:
        """(store (S, H, W), slots (K,)): keyframe k's level-0 intensity is store[slots[k]]. A keyframe's image is
        copied into a free slot when it first comes; the slots of keyframes no longer given are free again."""
        intensity = keyframes[0].pyramid[0].intensity
        store = self._image_store
        if store is None or store.shape[1:] != intensity.shape or store.dtype != intensity.dtype:
            self._image_store, self._slot_holders = np.empty((0, *intensity.shape), intensity.dtype), []
        given = {id(k) for k in keyframes}
        holders = [h if h is not None and id(h) in given else None for h in self._slot_holders]
        slots = np.empty(len(keyframes), np.int64)
        for i, keyframe in enumerate(keyframes):
            slot = next((j for j, h in enumerate(holders) if h is keyframe), None)
            if slot is None:
                slot = next((j for j, h in enumerate(holders) if h is None), len(holders))
                if slot == len(holders):
                    holders.append(None)
                    self._image_store = np.concatenate([self._image_store, intensity[None]])
                self._image_store[slot] = keyframe.pyramid[0].intensity
                holders[slot] = keyframe
            slots[i] = slot
        self._slot_holders = holders
        return self._image_store, slots

    def _window_points(self, keyframes: list) -> _WindowPoints:
        counts = [len(k.active_idepth) for k in keyframes]
        uv = np.concatenate([k.active_uv for k in keyframes])
        grad_sq = np.concatenate([k.active_grad_sq for k in keyframes])
        camera = keyframes[0].camera
        host_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        return _WindowPoints(
            pattern_rays(camera.intrinsics), camera.unproject(uv),
            np.concatenate([k.active_color for k in keyframes]),
            np.sqrt(self.weight_component / (self.weight_component + grad_sq)),
            host_start, *self.window_images(keyframes), _dropped_residuals(keyframes, host_start),
        )

    def _energy_thresholds(self, keyframes: list) -> np.ndarray:
        """(K,) each keyframe's outlier threshold on a point's energy: its own once it has been the newest of an
        optimization, else the one before it's (DSO's makeKeyFrame copies the last keyframe's); fixed without
        ``adaptive_outlier_threshold``."""
        if not self.config.adaptive_outlier_threshold:
            return np.full(len(keyframes), self.outlier_energy)
        thresholds = []
        for keyframe in keyframes:
            inherited = thresholds[-1] if thresholds else self.config.initial_energy_threshold
            thresholds.append(inherited if keyframe.energy_threshold is None else keyframe.energy_threshold)
        return np.array(thresholds, float)

    def _newest_energy_threshold(self, system: "_System") -> float:
        """setNewFrameEnergyTH: from the energies of the residuals in the newest keyframe (the last)."""
        config = self.config
        energies = system.residual_energy[-1][system.status[-1] != POINT_OUT]
        if len(energies) == 0:
            return self.outlier_energy  # DSO: 12 * 12 * patternNum
        nth = int(config.energy_threshold_quantile * len(energies))
        root = np.sqrt(np.partition(energies, nth)[nth]) * config.energy_threshold_factor
        weight = config.energy_threshold_constant_weight
        return float((weight * config.energy_threshold_constant + (1.0 - weight) * root) ** 2)

    def _linearize(self, keyframes, points: _WindowPoints, poses, affines, idepth, prior,
                   thresholds: np.ndarray | None = None, only_host: int | None = None, start: "_System | None" = None,
                   with_terms: bool = True) -> "_System":
        """The Gauss-Newton system and energy at a state (without ``with_terms``: the energy and the residuals'
        status, the system zero), with the keyframes' outlier ``thresholds`` (by default, their own). A residual that
        was in view at the ``start`` of the optimization and is out now is charged its outlier threshold: a step must
        not look better by pushing points out of the images (DSO keeps the residual set of an optimization fixed)."""
        n_kf = len(keyframes)
        thresholds = self._energy_thresholds(keyframes) if thresholds is None else thresholds
        # First-estimate Jacobians: a keyframe in the prior is linearized at the prior's x0, the others where
        # they are now.
        first_estimates = np.array([prior.x0[k.frame_index][0] if k.frame_index in prior.x0 else T
                                    for k, T in zip(keyframes, poses)])
        R, t = _relative_poses(np.array(poses))
        R0, t0 = _relative_poses(first_estimates)
        adjoint0 = _inverse_adjoints(first_estimates)
        factor, offset = relative_affines([k.exposure for k in keyframes], np.array(affines, float))
        active = np.ones(n_kf, bool) if only_host is None else np.arange(n_kf) == only_host
        with PARALLEL_LAUNCH:
            energy, status, residual_energy, H_kk, b_k, H_pk, H_pp, b_p = window_linearization(
                points.pattern_rays, points.center_rays, idepth, points.color, points.weight, points.host_start,
                points.images, points.image_slots, R, t, R0, t0, adjoint0, factor, offset,
                np.array([ab[1] for ab in affines], float), active, points.dropped, keyframes[0].camera.intrinsics,
                self.config.border, self.huber, thresholds, self.weight_component, with_terms,
            )
        if start is not None:
            left_view = (status == POINT_OUT) & (start.status == POINT_IN)
            energy += _residual_thresholds(thresholds, points.host_start)[left_view].sum()
        frame_ids = [k.frame_index for k in keyframes]
        prior_energy = prior.add_to(H_kk, b_k, frame_ids, poses, affines)
        return _System(H_kk, b_k, H_pk.T, H_pp, b_p, energy, prior_energy, status, residual_energy)

    # ------------------------------------------------------------------------------------ solving

    def _solve(self, system: "_System", lam: float, poses: list, fixed_scale: bool) -> tuple[np.ndarray, np.ndarray]:
        """The LM step: Schur complement over the inverse depths, the keyframes' system (without its scale
        component when ``fixed_scale``), back substitution."""
        n_kf = len(poses)
        H_pp = system.H_pp * (1.0 + lam) + self.config.idepth_regularization
        # H_kp H_pp^-1 H_pk as S^T S with S = H_pp^-1/2 H_pk: BLAS then computes one triangle (syrk; 0.65 -> 0.52 ms a
        # step on parking's windows).
        root = np.sqrt(H_pp)
        S = system.H_kp.T / root[:, None]
        H_s = system.H_kk - S.T @ S
        b_s = system.b_k - S.T @ (system.b_p / root)
        H_s += np.diag(np.diag(H_s)) * lam
        free = np.arange(PARAMS_PER_KEYFRAME, PARAMS_PER_KEYFRAME * n_kf)  # the oldest keyframe is the gauge
        step = np.zeros(PARAMS_PER_KEYFRAME * n_kf)
        if len(free):
            try:
                step[free] = np.linalg.solve(H_s[np.ix_(free, free)], -b_s[free])
            except np.linalg.LinAlgError:
                step[free] = np.linalg.lstsq(H_s[np.ix_(free, free)], -b_s[free], rcond=None)[0]
        if fixed_scale:
            direction = _scale_direction(poses)
            step -= (step @ direction) / max(direction @ direction, 1e-30) * direction
        step_points = -(system.b_p + system.H_kp.T @ step) / H_pp
        return step.reshape(n_kf, PARAMS_PER_KEYFRAME), step_points

    # ------------------------------------------------------------------------------------ results

    def _write_back(self, keyframes, poses, affines, idepth, system) -> np.ndarray:
        """New poses, affines and depths; points with no inlier residual left (or more outliers than inliers,
        DSO's flagPointsForRemoval) are removed from their host. Returns which points stay."""
        keep = (system.inliers > 0) & (system.outliers <= system.inliers) & (idepth > self.config.min_inverse_depth)
        offset = 0
        for keyframe, T, ab in zip(keyframes, poses, affines):
            count = len(keyframe.active_idepth)
            kept = keep[offset:offset + count]
            keyframe.T_world_cam = T
            keyframe.affine = ab
            keyframe.active_uv = keyframe.active_uv[kept]
            keyframe.active_idepth = idepth[offset:offset + count][kept]
            keyframe.active_color = keyframe.active_color[kept]
            keyframe.active_grad_sq = keyframe.active_grad_sq[kept]
            keyframe.dropped_residuals = {
                target.frame_index: system.status[k, offset:offset + count][kept] == POINT_OUT
                for k, target in enumerate(keyframes) if target is not keyframe
            }
            offset += count
        return keep


@dataclass
class _System:
    H_kk: np.ndarray  # (8K, 8K)
    b_k: np.ndarray
    H_kp: np.ndarray  # (8K, P)
    H_pp: np.ndarray  # (P,) the points' blocks are scalars
    b_p: np.ndarray
    photometric_energy: float
    prior_energy: float
    status: np.ndarray  # (K, P) each point's POINT_IN / OUT / OUTLIER in each keyframe (OUT in its host)
    residual_energy: np.ndarray  # (K, P) each residual's energy before the outlier cap (0 where out)

    def recapped(self, residual_thresholds: np.ndarray) -> "_System":
        """The same system with its photometric energy capped at new outlier thresholds (K, P); its statuses and
        terms stay those of the old ones (the first step of an optimization is solved from them)."""
        in_view = self.status != POINT_OUT
        energy = float(np.minimum(self.residual_energy, residual_thresholds)[in_view].sum())
        return dataclasses.replace(self, photometric_energy=energy)

    @property
    def energy(self) -> float:
        """What the optimization lowers: the photometric energy and the prior's term."""
        return self.photometric_energy + self.prior_energy

    @property
    def inliers(self) -> np.ndarray:
        """(P,) how many of each point's residuals are in."""
        return np.count_nonzero(self.status == POINT_IN, axis=0)

    @property
    def outliers(self) -> np.ndarray:
        return np.count_nonzero(self.status == POINT_OUTLIER, axis=0)

    @property
    def residuals(self) -> int:
        return int(np.count_nonzero(self.status == POINT_IN))


def _residual_thresholds(thresholds: np.ndarray, host_start: np.ndarray) -> np.ndarray:
    """(K, P) the outlier threshold of each residual: the larger of its host's and its target's."""
    host = np.repeat(np.arange(len(thresholds)), np.diff(host_start))
    return np.maximum(thresholds[:, None], thresholds[host][None, :])


def _dropped_residuals(keyframes: list, host_start: np.ndarray) -> np.ndarray:
    """(K, P) the residuals each host keyframe has dropped, by target (Keyframe.dropped_residuals): none for a
    target it has no entry for (one new to the window) or for points newer than the entry (activated since)."""
    dropped = np.zeros((len(keyframes), host_start[-1]), bool)
    for host, keyframe in enumerate(keyframes):
        for target, other in enumerate(keyframes):
            entry = keyframe.dropped_residuals.get(other.frame_index)
            if entry is not None:
                dropped[target, host_start[host]:host_start[host] + len(entry)] = entry
    return dropped


def _scale_direction(poses: list) -> np.ndarray:
    """How the keyframes' parameters move when the window is scaled about the gauge keyframe (DSO's scale
    nullspace): with left increments in the world frame, each keyframe's translation moves along its offset
    from the gauge keyframe; rotations and affines stay."""
    direction = np.zeros(PARAMS_PER_KEYFRAME * len(poses))
    for i, T in enumerate(poses):
        direction[PARAMS_PER_KEYFRAME * i: PARAMS_PER_KEYFRAME * i + 3] = T[:3, 3] - poses[0][:3, 3]
    return direction


@kernel
def _relative_poses(T_world_cam):
    """T_target_host = T_world_target^-1 T_world_host of every pair, indexed [host, target], as its rotation
    (K, K, 3, 3) and translation (K, K, 3): R_target^T R_host and R_target^T (t_host - t_target)."""
    n = len(T_world_cam)
    R = np.empty((n, n, 3, 3))
    t = np.empty((n, n, 3))
    for h in range(n):
        for tg in range(n):
            for i in range(3):
                for j in range(3):
                    R[h, tg, i, j] = (T_world_cam[tg, 0, i] * T_world_cam[h, 0, j] + T_world_cam[tg, 1, i] *
                                      T_world_cam[h, 1, j] + T_world_cam[tg, 2, i] * T_world_cam[h, 2, j])
                t[h, tg, i] = (T_world_cam[tg, 0, i] * (T_world_cam[h, 0, 3] - T_world_cam[tg, 0, 3]) +
                               T_world_cam[tg, 1, i] * (T_world_cam[h, 1, 3] - T_world_cam[tg, 1, 3]) +
                               T_world_cam[tg, 2, i] * (T_world_cam[h, 2, 3] - T_world_cam[tg, 2, 3]))
    return R, t


@kernel
def _inverse_adjoints(T_world_cam):
    """(K, 6, 6) Ad(T_cam_world) of each keyframe."""
    adjoints = np.empty((len(T_world_cam), 6, 6))
    for k in range(len(T_world_cam)):
        adjoints[k] = se3_adjoint_compiled(se3_inverse_compiled(T_world_cam[k]))
    return adjoints
