"""Windowed photometric bundle adjustment (DSO's FullSystem::optimize and EnergyFunctional, FDMO section 4).

The window's keyframes (pose T_world_cam, affine (a, b)) and the inverse depths of their active points are
optimized jointly over all photometric residuals: every point, an 8-pixel pattern in its host keyframe, is
compared with every other keyframe of the window it projects into (DSO Eq. 4, Huber weights times the
gradient-dependent weights). One iteration of Levenberg-Marquardt:

1. linearize each (host, target) pair of keyframes (photometric_kernels.pair_linearization: the local system
   over the relative pose increment and the affine parameters, and each point's inverse-depth terms);
2. map the local systems into the keyframes' absolute parameters: with left increments in the world frame,
   T_target_host = T_world_target^-1 T_world_host moves by xi = Ad(T_target_world) (delta_host - delta_target);
3. Schur complement over the points (each point one inverse depth, so its block is a scalar):
   H_s = H_kk - H_kp H_pp^-1 H_pk, b_s = b_k - H_kp H_pp^-1 b_p; solve the small dense keyframe system,
   then each point's step by back substitution;
4. accept the step if the energy drops (lambda / 4), otherwise reject it (lambda x 100), as DSO.

Gauge: the oldest keyframe of the window (pose and affine) is held fixed. Keyframes that left the window
are kept as a prior (marginalization.py), which also holds the scale: without it the scale is free in every
window and drifts.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from vo_core.direct.affine import relative_affine
from vo_core.direct.config import WindowConfig
from vo_core.direct.coarse_tracker import PATTERN
from vo_core.direct.marginalization import MarginalizationPrior
from vo_core.direct.photometric_kernels import pair_linearization
from vo_core.geometry.lie import se3_adjoint, se3_exp, se3_inverse

PARAMS_PER_KEYFRAME = 8  # pose increment (v, w), a, b
POINT_IN, POINT_OUT, POINT_OUTLIER = 0, 1, 2


@dataclass
class _HostPoints:
    """The active points of one host keyframe as the kernels need them."""

    rays: np.ndarray  # (N, 8, 3) K^-1 (u, v, 1) of the pattern pixels
    color: np.ndarray  # (N, 8) host intensities
    weight: np.ndarray  # (N, 8) host gradient weights sqrt(c / (c + |grad|^2))
    offset: int  # index of the host's first point in the window's point vector


@dataclass
class WindowReport:
    iterations: int
    energy_before: float
    energy_after: float
    points: int
    residuals: int
    removed_points: int
    ms: float

    def as_details(self) -> dict:
        return {
            "iterations": self.iterations, "energy_before": round(self.energy_before, 1),
            "energy_after": round(self.energy_after, 1), "points": self.points, "residuals": self.residuals,
            "removed_points": self.removed_points, "ms": round(self.ms, 1),
        }


class WindowOptimizer:
    """Optimizes a list of keyframes in place (their T_world_cam, affine and active_idepth)."""

    def __init__(self, config: WindowConfig, huber_threshold: float, outlier_threshold: float,
                 outlier_sum_component: float):
        self.config = config
        self.huber = huber_threshold
        self.outlier_energy = len(PATTERN) * outlier_threshold
        self.weight_component = outlier_sum_component

    def optimize(self, keyframes: list, prior: MarginalizationPrior) -> WindowReport:
        start = time.perf_counter()
        hosts = self._host_points(keyframes)
        idepth = np.concatenate([k.active_idepth for k in keyframes]) if keyframes else np.zeros(0)
        poses = [k.T_world_cam.copy() for k in keyframes]
        affines = [np.asarray(k.affine, float).copy() for k in keyframes]
        system = self._linearize(keyframes, hosts, poses, affines, idepth, prior)
        energy_before = energy = system.energy
        first = system
        lam = self.config.initial_lambda
        iterations = 0
        for iterations in range(1, self.config.max_iterations + 1):
            step_keyframes, step_points = self._solve(system, lam, len(keyframes))
            trial_poses = [se3_exp(step_keyframes[i, :6]) @ T for i, T in enumerate(poses)]
            trial_affines = [ab + step_keyframes[i, 6:] for i, ab in enumerate(affines)]
            trial_idepth = np.maximum(idepth + step_points, self.config.min_inverse_depth)
            trial = self._linearize(keyframes, hosts, trial_poses, trial_affines, trial_idepth, prior, start=first)
            if trial.energy < energy:
                poses, affines, idepth, system, energy = trial_poses, trial_affines, trial_idepth, trial, trial.energy
                lam *= self.config.lambda_decrease
                converged = np.abs(step_keyframes).max(initial=0.0) < self.config.min_step
                if converged:
                    break
            else:
                lam *= self.config.lambda_increase
        removed = self._write_back(keyframes, poses, affines, idepth, system)
        return WindowReport(
            iterations, energy_before, energy, len(idepth), system.residuals, removed,
            (time.perf_counter() - start) * 1000.0,
        )

    def marginalize(
        self, keyframes: list, leaving: int, prior: MarginalizationPrior
    ) -> tuple[MarginalizationPrior, int]:
        """The prior once keyframe ``leaving`` (a window index) goes, with the points it hosts (DSO's
        marginalizeFrame after marginalizePointsF); and how many points were marginalized."""
        hosts = self._host_points(keyframes)
        idepth = np.concatenate([k.active_idepth for k in keyframes])
        poses = [k.T_world_cam for k in keyframes]
        affines = [np.asarray(k.affine, float) for k in keyframes]
        system = self._linearize(keyframes, hosts, poses, affines, idepth, MarginalizationPrior(), only_host=leaving)
        H_pp = system.H_pp + self.config.idepth_regularization
        H = system.H_kk - (system.H_kp / H_pp) @ system.H_kp.T
        b = system.b_k - (system.H_kp / H_pp) @ system.b_p
        frame_ids = [k.frame_index for k in keyframes]
        new_prior = prior.marginalize(frame_ids, poses, affines, H, b, leaving, self.config.marginalization_damping)
        return new_prior, int(np.count_nonzero(system.inliers))

    # ------------------------------------------------------------------------------------ linearization

    def _host_points(self, keyframes: list) -> list[_HostPoints]:
        hosts, offset = [], 0
        for keyframe in keyframes:
            camera = keyframe.camera
            pattern_uv = keyframe.active_uv[:, None, :] + PATTERN[None]  # (N, 8, 2)
            sampled = keyframe.pyramid[0].sample(pattern_uv[..., 0], pattern_uv[..., 1])  # (N, 8, 3)
            color = np.nan_to_num(sampled[..., 0])
            grad_sq = np.nan_to_num(sampled[..., 1] ** 2 + sampled[..., 2] ** 2)
            weight = np.sqrt(self.weight_component / (self.weight_component + grad_sq))
            rays = camera.unproject(pattern_uv.reshape(-1, 2)).reshape(-1, len(PATTERN), 3)
            hosts.append(_HostPoints(rays, color, weight, offset))
            offset += len(keyframe.active_idepth)
        return hosts

    def _linearize(self, keyframes, hosts, poses, affines, idepth, prior, only_host: int | None = None,
                   start: "_System | None" = None) -> "_System":
        """The Gauss-Newton system and energy at a state. A residual that was in view at the ``start`` of the
        optimization and is out now is charged the outlier energy: a step must not look better by pushing points
        out of the images (DSO keeps the residual set of an optimization fixed)."""
        n_kf = len(keyframes)
        size = PARAMS_PER_KEYFRAME * n_kf
        system = _System(np.zeros((size, size)), np.zeros(size), np.zeros((size, len(idepth))),
                         np.zeros(len(idepth)), np.zeros(len(idepth)), np.zeros(len(idepth), int),
                         np.zeros(len(idepth), int), 0.0, 0, {})
        # First-estimate Jacobians: a keyframe in the prior is linearized at the prior's x0, the others where
        # they are now.
        first_estimates = [prior.x0[k.frame_index][0] if k.frame_index in prior.x0 else T
                           for k, T in zip(keyframes, poses)]
        for h, host in enumerate(hosts):
            count = len(keyframes[h].active_idepth)
            if count == 0 or (only_host is not None and h != only_host):
                continue
            points = slice(host.offset, host.offset + count)
            for t, target in enumerate(keyframes):
                if t != h:
                    self._add_pair(system, keyframes[h], target, h, t, host, points, poses, first_estimates,
                                   affines, idepth)
                    if start is not None:
                        left_view = (system.status[h, t] == POINT_OUT) & (start.status[h, t] == POINT_IN)
                        system.energy += self.outlier_energy * np.count_nonzero(left_view)
        frame_ids = [k.frame_index for k in keyframes]
        system.energy += prior.add_to(system.H_kk, system.b_k, frame_ids, poses, affines)
        return system

    def _add_pair(self, system, host_kf, target_kf, h, t, host, points, poses, first_estimates, affines,
                  idepth) -> None:
        T_target_host = se3_inverse(poses[t]) @ poses[h]
        T0_target_world = se3_inverse(first_estimates[t])
        T0_target_host = T0_target_world @ first_estimates[h]
        factor, offset = relative_affine(host_kf.exposure, target_kf.exposure, affines[h], affines[t])
        camera = target_kf.camera
        energy, status, M, m, C, Hdd, bd = pair_linearization(
            host.rays, idepth[points], host.color, host.weight, T_target_host[:3, :3], T_target_host[:3, 3],
            T0_target_host[:3, :3], T0_target_host[:3, 3], np.array([camera.fx, camera.fy, camera.cx, camera.cy]),
            self.config.border, target_kf.pyramid[0].packed,
            float(factor), float(offset), float(affines[h][1]), self.huber, self.outlier_energy,
            self.weight_component,
        )
        system.energy += energy
        system.status[h, t] = status
        system.residuals += int(np.count_nonzero(status == POINT_IN))
        system.inliers[points] += status == POINT_IN
        system.outliers[points] += status == POINT_OUTLIER
        # Local parameters [xi, a_t, b_t, b_h] -> absolute [delta_h, a_h, b_h, delta_t, a_t, b_t].
        A = np.zeros((9, 2 * PARAMS_PER_KEYFRAME))
        adjoint = se3_adjoint(T0_target_world)
        A[:6, :6], A[:6, 8:14] = adjoint, -adjoint
        A[6, 6], A[6, 14] = -1.0, 1.0  # a_host enters as -a_target
        A[7, 15] = 1.0
        A[8, 7] = 1.0
        columns = np.r_[_block(h), _block(t)]
        system.H_kk[np.ix_(columns, columns)] += A.T @ M @ A
        system.b_k[columns] += A.T @ m
        system.H_kp[columns, points] += A.T @ C.T
        system.H_pp[points] += Hdd
        system.b_p[points] += bd

    # ------------------------------------------------------------------------------------ solving

    def _solve(self, system: "_System", lam: float, n_kf: int) -> tuple[np.ndarray, np.ndarray]:
        """The LM step: Schur complement over the inverse depths, the keyframes' system, back substitution."""
        H_pp = system.H_pp * (1.0 + lam) + self.config.idepth_regularization
        H_kp_scaled = system.H_kp / H_pp
        H_s = system.H_kk - H_kp_scaled @ system.H_kp.T
        b_s = system.b_k - H_kp_scaled @ system.b_p
        H_s += np.diag(np.diag(H_s)) * lam
        free = np.arange(PARAMS_PER_KEYFRAME, PARAMS_PER_KEYFRAME * n_kf)  # the oldest keyframe is the gauge
        step = np.zeros(PARAMS_PER_KEYFRAME * n_kf)
        if len(free):
            try:
                step[free] = np.linalg.solve(H_s[np.ix_(free, free)], -b_s[free])
            except np.linalg.LinAlgError:
                step[free] = np.linalg.lstsq(H_s[np.ix_(free, free)], -b_s[free], rcond=None)[0]
        step_points = -(system.b_p + system.H_kp.T @ step) / H_pp
        return step.reshape(n_kf, PARAMS_PER_KEYFRAME), step_points

    # ------------------------------------------------------------------------------------ results

    def _write_back(self, keyframes, poses, affines, idepth, system) -> int:
        """New poses, affines and depths; points with no inlier residual left (or more outliers than inliers,
        DSO's flagPointsForRemoval) are removed from their host."""
        keep = (system.inliers > 0) & (system.outliers <= system.inliers) & (idepth > self.config.min_inverse_depth)
        removed = 0
        offset = 0
        for keyframe, T, ab in zip(keyframes, poses, affines):
            count = len(keyframe.active_idepth)
            kept = keep[offset:offset + count]
            keyframe.T_world_cam = T
            keyframe.affine = ab
            keyframe.active_uv = keyframe.active_uv[kept]
            keyframe.active_idepth = idepth[offset:offset + count][kept]
            removed += int(count - kept.sum())
            offset += count
        return removed


@dataclass
class _System:
    H_kk: np.ndarray  # (8K, 8K)
    b_k: np.ndarray
    H_kp: np.ndarray  # (8K, P)
    H_pp: np.ndarray  # (P,) the points' blocks are scalars
    b_p: np.ndarray
    inliers: np.ndarray  # (P,) residuals of each point that are in
    outliers: np.ndarray
    energy: float
    residuals: int
    status: dict[tuple[int, int], np.ndarray]  # (host, target) -> each point's POINT_IN / OUT / OUTLIER


def _block(index: int) -> np.ndarray:
    return np.arange(PARAMS_PER_KEYFRAME * index, PARAMS_PER_KEYFRAME * (index + 1))
