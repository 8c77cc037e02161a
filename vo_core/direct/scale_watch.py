"""The scale watch: at every new keyframe, is the direct map still at the scale it had?

A monocular map's scale is its own, and nothing in the photometric energy holds it: a wrong start, a window
optimization that slid along the scale direction or points activated at a shrunk depth can let it collapse,
and every frame still gets a pose. Two numbers say it, both in the map's units and both reported at every
keyframe (FrameResult.scale_ratio, FrameResult.mean_inverse_depth):

* the step ratio: the new keyframe's speed (its translation from the previous keyframe over the time between
  them) over the median of the recent keyframes' speeds; speeds, not steps, because keyframes come every frame or
  every other one at the same speed (KITTI), which makes steps vary by 2x;
* the depth ratio: the window's mean inverse depth over the median of the recent keyframes' values.

The motion itself moves both, but not together and not at once: the depths change between two keyframes by at
most the step (about a tenth of the depth, DSO making a keyframe when the optical flow passes a threshold), and a
camera that slows down or only turns leaves the depths as they were. The scale changing moves both at once and
in opposite directions (a map shrunk by 2 has half the speed and twice the inverse depths). A jump is the
geometric mean of the two changes beyond ``jump_factor``, with the depths moving by at least ``min_depth_factor``.
After a jump the history starts again, so a collapse that goes on is reported again once there is something to
compare with. A jump is a warning to the user (a SCALE_JUMP event, counted as reported by the silent-failure
measure), not evidence for FDMO's decisions: the window's points changing (near ones leaving the view) moves the
mean inverse depth as a scale change would (the drone clip: 4-6x at a speed changed 1.2x, every run), and the
feature map's own check of each keyframe is what decides (fdmo/decide.judge_keyframe).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vo_core.direct.config import ScaleWatchConfig


@dataclass
class ScaleReading:
    """One keyframe's numbers; the ratios are None until there are enough recent keyframes."""

    speed: float
    mean_inverse_depth: float
    step_ratio: float | None = None
    depth_ratio: float | None = None
    jump: bool = False

    @property
    def factor(self) -> float | None:
        """How much the map shrank (> 1) or grew (< 1), as the geometric mean of both ratios."""
        if self.step_ratio is None:
            return None
        return float(np.sqrt(self.depth_ratio / max(self.step_ratio, 1e-12)))

    def details(self) -> dict:
        return {
            "speed": round(self.speed, 6), "step_ratio": _rounded(self.step_ratio),
            "mean_inverse_depth": round(self.mean_inverse_depth, 4), "depth_ratio": _rounded(self.depth_ratio),
            "factor": _rounded(self.factor),
        }


@dataclass
class ScaleWatch:
    config: ScaleWatchConfig
    speeds: list[float] = field(default_factory=list)
    inverse_depths: list[float] = field(default_factory=list)

    def reset(self) -> None:
        self.speeds, self.inverse_depths = [], []

    def observe(self, speed: float, mean_inverse_depth: float) -> ScaleReading:
        """The reading of a new keyframe: its ``speed`` since the previous keyframe (map units per second), its
        window's mean inverse depth."""
        config = self.config
        reading = ScaleReading(speed, mean_inverse_depth)
        recent_speeds = self.speeds[-config.recent_keyframes:]
        recent_depths = self.inverse_depths[-config.recent_keyframes:]
        if len(recent_speeds) >= config.min_recent and np.median(recent_speeds) > 0 and np.median(recent_depths) > 0:
            reading.step_ratio = float(speed / np.median(recent_speeds))
            reading.depth_ratio = float(mean_inverse_depth / np.median(recent_depths))
            reading.jump = _is_jump(reading, config)
        if reading.jump:
            self.reset()
        self.speeds.append(speed)
        self.inverse_depths.append(mean_inverse_depth)
        return reading


def _is_jump(reading: ScaleReading, config: ScaleWatchConfig) -> bool:
    log_depth = np.log(reading.depth_ratio)
    opposite = log_depth * np.log(max(reading.step_ratio, 1e-12)) < 0
    depth_moved = abs(log_depth) >= np.log(config.min_depth_factor)
    return bool(opposite and depth_moved and abs(np.log(reading.factor)) >= np.log(config.jump_factor))


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(float(value), 4)
