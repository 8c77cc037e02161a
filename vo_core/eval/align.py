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
from vo_core.geometry.sim3_solver import umeyama as closed_form_umeyama
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
    """(R, t, s) minimizing sum_i ||target_i - (s R source_i + t)||^2 for (N, 3) point sets: geometry's closed form
    (vo_core/geometry/sim3_solver.umeyama, Umeyama 1991), refused with an InputError where the estimate has not
    moved enough to have a scale."""
    if with_scale:
        spread = np.mean(np.sum((source - source.mean(axis=0)) ** 2, axis=1))  # Umeyama's sigma_x^2
        if spread < MIN_POSITION_VARIANCE:
            raise InputError("Sim(3) alignment: the estimated positions do not move, their scale is undefined")
    return closed_form_umeyama(source, target, with_scale)


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
