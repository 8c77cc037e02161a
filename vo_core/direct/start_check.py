"""The check of a new start over the first window optimizations after the hand-over.

An initializer's own acceptance rules look at two views; a start can pass them and still be wrong (the wrong one
of a plane's two motions, a coarse initialization snapped to a wrong depth map), and a wrong start gives poses
that look like a result while the map's scale collapses (a wrong structure absorbs the translation into
rotation). So a start stays on probation for the first ``window_optimizations`` window optimizations after the
hand-over's own, and is discarded at the first of them where:

* the first keyframe pair's parallax, the baseline times the median inverse depth of the initializer's points
  (a number that does not depend on the map's scale), moved by more than ``max_parallax_change`` from the
  hand-over: the window optimizations rebuilt the initializer's structure instead of refining it;
* at the last of them: the energy per residual in view grew by more than ``max_energy_growth`` from its lowest
  since the hand-over (each new frame fits the map worse), or fewer than ``min_inlier_ratio`` of the residuals
  in view are inliers. Only at the last: right after a right start the first windows often hold many outliers
  (points whose initial depths were off: half the residuals on a synthetic room with the coarse initializer),
  which the window optimizations then remove.
* after the last of them: the ORB matches between the window's keyframes contradict the direct poses' motion
  (vo_core/init/epipolar_check.py, handed in with the initializers), the one measure that does not come from the
  direct map itself. This witness runs on a thread of its own from the last optimization on, and the start stays on
  probation until it answers: with live input (``EpipolarCheckConfig.beside_mapping``) when it is done, while
  mapping goes on; otherwise at the next window optimization, waiting for it there if need be, so that a run is the
  same at any speed (its images' measures run beside the tracking of the frames in between instead of holding up the
  last optimization's keyframe: 195 ms on teddy's start).
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from vo_core.direct.config import StartCheckConfig
from vo_core.direct.initialization import StartWitness
from vo_core.direct.window import WindowReport


@dataclass
class StartCheck:
    config: StartCheckConfig
    first_frame_index: int
    second_frame_index: int
    initializer: str  # which initializer made the start (for the event, and the next attempt)
    handover_parallax: float | None = None
    optimizations: int = 0  # window optimizations seen after the hand-over's own
    energies: list[float] = field(default_factory=list)  # their energies per residual in view
    measures: dict = field(default_factory=dict)  # for the event: the latest energy and inliers, the worst change
    posed_timestamps: list[float] = field(default_factory=list)  # the frames posed in this start's map so far
    witness: Future | None = None  # the epipolar witness, from the last optimization on: (reason or None, measures)
    witness_due: bool = False  # a window optimization came after the witness started (its answer is due)
    epipolar: StartWitness | None = field(default=None, repr=False)  # measures images as they come; None: no witness

    @property
    def passed(self) -> bool:
        if self.optimizations < self.config.window_optimizations:
            return False
        return self.witness is None or (self._witness_answered() and self.witness_failure() is None)

    def witness_failure(self) -> str | None:
        """Why the witness refuses the start, once it has answered (its measures join the event's); None before,
        where it agrees, and where none runs."""
        if not self._witness_answered():
            return None
        reason, measures = self.witness.result()
        self.measures.update(measures)
        return reason

    def _witness_answered(self) -> bool:
        """Beside mapping: once it is done. Otherwise at the optimization after the one that started it, whenever
        it got done: the verdict then falls at the same keyframe at any speed."""
        if self.witness is None:
            return False
        return self.witness.done() if self.config.epipolar.beside_mapping else self.witness_due

    def close(self) -> None:
        """The start's map goes (it failed, or gave way to another): its witness stops measuring."""
        if self.epipolar is not None:
            self.epipolar.close()

    def observe(self, report: WindowReport, keyframes: list) -> str | None:
        """One window optimization's outcome; returns why the start fails, or None."""
        parallax = self._parallax(keyframes)
        if self.epipolar is not None and self.witness is None:
            self.epipolar.prepare(keyframes, keyframes[0].camera)
        if self.handover_parallax is None:
            self.handover_parallax = parallax
            return None
        if self.witness is not None:  # past the last optimization: only the witness has yet to answer
            self.witness_due = True
            return None if self.config.epipolar.beside_mapping else self.witness_failure()
        self.optimizations += 1
        self.energies.append(report.energy_after / max(report.residuals, 1))
        growth = self.energies[-1] / max(min(self.energies), 1e-12)
        inliers = report.residuals / max(report.residuals + report.outliers, 1)
        change = _change(parallax, self.handover_parallax)
        self.measures.update(energy_per_residual=self.energies[-1], energy_growth=growth, inlier_ratio=inliers)
        if change is not None:
            self.measures["parallax_change"] = max(change, self.measures.get("parallax_change", 1.0))
        config = self.config
        if change is not None and change > config.max_parallax_change:
            return f"the first keyframe pair's parallax changed {change:.1f}x since the hand-over"
        if self.optimizations < config.window_optimizations:
            return None
        if growth > config.max_energy_growth:
            return f"the energy per residual grew {growth:.1f}x during the first window optimizations"
        if inliers < config.min_inlier_ratio:
            return f"inlier ratio {inliers:.2f} below {config.min_inlier_ratio}"
        if self.epipolar is not None:
            executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fdmo-start-witness")
            self.witness = executor.submit(self.epipolar.disagreement, [_KeyframeView(k) for k in keyframes],
                                           keyframes[0].camera)
            executor.shutdown(wait=False)  # its thread ends with the witness
        return None

    def posed(self, timestamp: float) -> None:
        """A frame got a pose in this start's map while it is on probation (retracted if the start fails)."""
        self.posed_timestamps.append(float(timestamp))

    def details(self) -> dict:
        return {
            "initializer": self.initializer, "first_frame": self.first_frame_index,
            "second_frame": self.second_frame_index, "window_optimizations": self.optimizations,
            **{key: round(value, 4) if isinstance(value, float) else value for key, value in self.measures.items()},
        }

    def _parallax(self, keyframes: list) -> float | None:
        """Baseline x median inverse depth of the first keyframe's points, while both keyframes are in the window."""
        by_index = {k.frame_index: k for k in keyframes}
        first, second = by_index.get(self.first_frame_index), by_index.get(self.second_frame_index)
        if first is None or second is None or len(first.active_idepth) == 0:
            return None
        baseline = np.linalg.norm(second.T_world_cam[:3, 3] - first.T_world_cam[:3, 3])
        return float(baseline * np.median(first.active_idepth))


class _KeyframeView:
    """What the witness reads of a keyframe, as it was when the witness started (the window goes on moving)."""

    def __init__(self, keyframe):
        self.frame_index, self.image = keyframe.frame_index, keyframe.image
        self.T_world_cam = keyframe.T_world_cam.copy()


def _change(value: float | None, reference: float | None) -> float | None:
    """The factor between two positive numbers, >= 1 whichever is larger."""
    if value is None or reference is None or value <= 0 or reference <= 0:
        return None
    return float(max(value / reference, reference / value))
