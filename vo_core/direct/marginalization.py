"""The marginalization prior of the window (DSO's EnergyFunctional::marginalizeFrame, FDMO section 4).

When a keyframe leaves the window its information is kept: the residuals of the points it hosts (in every
other keyframe) are linearized, the points are eliminated by the Schur complement, together with what the
prior already held, and then the leaving keyframe's own parameters are eliminated the same way. What is left
is a quadratic energy over the remaining keyframes' parameters,

    E_prior(delta) = b^T delta + 1/2 delta^T H delta,

in the increments delta of each keyframe from its linearization point x0 = (T0, a0, b0):
delta = (log(T T0^-1), a - a0, b - b0), left increments in the world frame as in window.py. H is frozen when it
is made (first-estimate Jacobians: later iterations move the state, never the prior's linearization), so the
prior stays consistent and does not invent information along the unobservable directions (DSO paper Sec. 2.3).
Residuals of points hosted elsewhere that observe the leaving keyframe are dropped, as DSO does.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vo_core.compiled import kernel
from vo_core.geometry.lie import se3_inverse_compiled, se3_log_compiled

PARAMS_PER_KEYFRAME = 8


@dataclass
class MarginalizationPrior:
    """H and b over the keyframes ``frame_ids`` (8 parameters each, in that order), about ``x0``."""

    frame_ids: list[int] = field(default_factory=list)
    H: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    b: np.ndarray = field(default_factory=lambda: np.zeros(0))
    x0: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # frame -> (T0, (a0, b0))

    def __len__(self) -> int:
        return len(self.frame_ids)

    def deltas(self, frame_ids: list[int], poses: list[np.ndarray], affines: list[np.ndarray]) -> np.ndarray:
        """(K, 8) increments of the window's keyframes from their linearization points (zero without one)."""
        out = np.zeros((len(frame_ids), PARAMS_PER_KEYFRAME))
        rows = [i for i, frame in enumerate(frame_ids) if frame in self.x0]
        if rows:
            x0 = [self.x0[frame_ids[i]] for i in rows]
            out[rows, :6] = _pose_increments(np.array([poses[i] for i in rows]), np.array([T0 for T0, _ in x0]))
            out[rows, 6:] = np.array([affines[i] for i in rows]) - np.array([ab0 for _, ab0 in x0])
        return out

    def _window_indices(self, frame_ids: list[int]) -> np.ndarray:
        """For each parameter of the prior, its index in the window's parameter vector."""
        position = {frame: i for i, frame in enumerate(frame_ids)}
        return np.concatenate(
            [np.arange(8) + PARAMS_PER_KEYFRAME * position[frame] for frame in self.frame_ids]
        ) if self.frame_ids else np.zeros(0, int)

    def add_to(self, H_kk: np.ndarray, b_k: np.ndarray, frame_ids, poses, affines) -> float:
        """Add the prior's Gauss-Newton terms at the current state to the window's system; its energy."""
        if not self.frame_ids:
            return 0.0
        index = self._window_indices(frame_ids)
        delta = self.deltas(frame_ids, poses, affines).reshape(-1)[index]
        H_kk[np.ix_(index, index)] += self.H
        b_k[index] += self.b + self.H @ delta
        return float(self.b @ delta + 0.5 * delta @ self.H @ delta)

    def marginalize(self, frame_ids, poses, affines, H: np.ndarray, b: np.ndarray, leaving: int,
                    damping: float) -> "MarginalizationPrior":
        """The prior after keyframe ``leaving`` (a window index) goes.

        ``H``, ``b`` are the points-eliminated Gauss-Newton system of the leaving keyframe's points over the whole
        window, linearized at the current state; keyframes new to the prior take the current state as x0."""
        x0 = dict(self.x0)
        for frame, T, ab in zip(frame_ids, poses, affines):
            x0.setdefault(frame, (T.copy(), np.asarray(ab, float).copy()))
        # Everything as a quadratic in delta about x0: a system linearized at delta_c becomes b - H delta_c.
        delta_c = MarginalizationPrior(x0=x0).deltas(frame_ids, poses, affines).reshape(-1)
        H_total = H.copy()
        b_total = b - H @ delta_c
        if self.frame_ids:
            index = self._window_indices(frame_ids)
            H_total[np.ix_(index, index)] += self.H
            b_total[index] += self.b
        # Schur complement of the leaving keyframe's parameters.
        gone = np.arange(8) + PARAMS_PER_KEYFRAME * leaving
        kept = np.setdiff1d(np.arange(len(b_total)), gone)
        H_gg = H_total[np.ix_(gone, gone)] + damping * np.eye(len(gone))
        coupling = H_total[np.ix_(kept, gone)] @ np.linalg.inv(H_gg)
        H_new = H_total[np.ix_(kept, kept)] - coupling @ H_total[np.ix_(gone, kept)]
        b_new = b_total[kept] - coupling @ b_total[gone]
        remaining = [frame for i, frame in enumerate(frame_ids) if i != leaving]
        return MarginalizationPrior(remaining, 0.5 * (H_new + H_new.T), b_new, {f: x0[f] for f in remaining})


@kernel
def _pose_increments(T, T0):
    """(K, 6) log(T_k T0_k^-1): each keyframe's left increment in the world frame from its linearization point."""
    increments = np.empty((len(T), 6))
    for k in range(len(T)):
        increments[k] = se3_log_compiled(np.ascontiguousarray(T[k]) @ se3_inverse_compiled(T0[k]))
    return increments
