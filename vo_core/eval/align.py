"""Alignment of an estimated trajectory to ground truth: Umeyama's closed form (Umeyama 1991, "Least-squares
estimation of transformation parameters between two point patterns", IEEE PAMI 13(4)).

A monocular estimate lives in its own world frame and scale; before comparing it to ground truth it is mapped
by the similarity S_gt_est = [sR t; 0 1] minimizing sum_i ||p_gt_i - (s R p_est_i + t)||^2 over the matched
camera positions ("sim3"), with s = 1 for a metric estimate ("se3"), or not at all ("none").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vo_core.errors import InputError
from vo_core.geometry.lie import sim3
from vo_core.trajectory import Trajectory

ALIGNMENTS = ("sim3", "se3", "none")
# Below this spread (m^2 per point) the estimate has not moved and no scale can be fitted to it.
MIN_POSITION_VARIANCE = 1e-12


@dataclass(frozen=True)
class Alignment:
    """The similarity ``transform`` = S_gt_est (4x4, [sR t; 0 1]) that maps estimated positions into the
    ground-truth frame, its ``scale`` s and the ``method`` that produced it."""

    transform: np.ndarray
    scale: float
    method: str

    @property
    def rotation(self) -> np.ndarray:
        return self.transform[:3, :3] / self.scale

    def apply(self, trajectory: Trajectory) -> Trajectory:
        """The trajectory in the ground-truth frame: positions s R p + t, orientations R R_world_cam."""
        poses = trajectory.poses.copy()
        poses[:, :3, :3] = self.rotation @ trajectory.poses[:, :3, :3]
        poses[:, :3, 3] = trajectory.positions @ self.transform[:3, :3].T + self.transform[:3, 3]
        return Trajectory(trajectory.timestamps, poses)


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) minimizing sum_i ||target_i - (s R source_i + t)||^2 for (N, 3) point sets (Umeyama 1991)."""
    mean_source, mean_target = source.mean(axis=0), target.mean(axis=0)
    centred_source, centred_target = source - mean_source, target - mean_target
    variance_source = np.mean(np.sum(centred_source**2, axis=1))  # sigma_x^2, eq. (36)
    covariance = centred_target.T @ centred_source / len(source)  # Sigma_xy, eq. (38)
    U, d, Vt = np.linalg.svd(covariance)
    # S = diag(1, 1, -1) when det(U) det(V) < 0: the best proper rotation, not a reflection, eq. (43)
    signs = np.array([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0])
    R = U @ np.diag(signs) @ Vt  # eq. (40)
    if with_scale:
        if variance_source < MIN_POSITION_VARIANCE:
            raise InputError("Sim(3) alignment: the estimated positions do not move, their scale is undefined")
        s = float(d @ signs / variance_source)  # c = tr(D S) / sigma_x^2, eq. (42)
    else:
        s = 1.0
    t = mean_target - s * R @ mean_source  # eq. (41)
    return R, t, s


def fit_alignment(
    estimate: Trajectory, ground_truth: Trajectory, method: str = "sim3", first_n: int | None = None
) -> Alignment:
    """The ``method`` ("sim3", "se3" or "none") alignment of matched trajectories (pose k with pose k), fitted
    on all poses or, with ``first_n``, on the first n only (the rest then shows how the estimate drifts away)."""
    if method not in ALIGNMENTS:
        raise InputError(f"unknown alignment '{method}' (known: {', '.join(ALIGNMENTS)})")
    if len(estimate) != len(ground_truth) or len(estimate) == 0:
        raise ValueError(f"align needs matched, non-empty trajectories ({len(estimate)} vs {len(ground_truth)})")
    if method == "none":
        return Alignment(np.eye(4), 1.0, method)
    used = slice(None) if first_n is None else slice(0, max(int(first_n), 1))
    R, t, s = umeyama(estimate.positions[used], ground_truth.positions[used], with_scale=method == "sim3")
    return Alignment(sim3(s, R, t), s, method)
