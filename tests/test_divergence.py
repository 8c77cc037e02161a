"""FDMO's divergence test (vo_core/direct/divergence.py) as a function of its evidence: a row per recorded case."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from vo_core.direct.divergence import DivergenceConfig, Verdict, judge


@dataclass
class Result:
    success: bool = True
    rmse_after: float = 6.0  # what the alignment reached, DSO's cutoff raised where it had to be


@dataclass
class Tracking:
    """The fields of DirectTracking the judgement reads."""

    rmse_before: float = 8.0
    rmse_end: float = 6.0
    saturated_end: float = 0.05
    good_enough: bool = True
    intervals_missed: float | None = None
    motion_ratio: float | None = 1.0
    image_motion_px: float | None = 3.0
    typical_motion_px: float | None = 3.0
    hypotheses_tried: int = 1
    last_rmse: float = 6.0
    result: Result | None = None

    def __post_init__(self):
        self.result = self.result or Result(rmse_after=self.rmse_end)

    @property
    def converged(self) -> bool:
        return self.result.success

    @property
    def rmse_after(self) -> float:
        return self.result.rmse_after


@pytest.mark.parametrize("case, tracking, verdict", [
    ("a steady frame", Tracking(), Verdict.TRUSTED),
    ("FDMO 4.2.1: the optimization made the RMSE worse", Tracking(rmse_before=8.0, rmse_end=9.0), Verdict.DIVERGED),
    # TUM fr1/desk at half its frame rate: DSO's cutoff raised on the finest level made the alignment's own RMSE
    # 1.26-1.39x the start's, at poses whose RMSE measured alike was 0.91-0.99x it.
    ("the same pose measured alike", Tracking(rmse_before=10.0, rmse_end=9.4, saturated_end=0.45,
                                             result=Result(rmse_after=13.9)), Verdict.TRUSTED),
    ("a black frame: both ends saturated", Tracking(rmse_before=12.0, rmse_end=12.0, saturated_end=1.0),
     Verdict.DIVERGED),
    ("no hypothesis converged", Tracking(result=Result(success=False)), Verdict.LOST),
    ("every hypothesis worse than the last frame", Tracking(good_enough=False), Verdict.SUSPECT),
    ("frames were missed", Tracking(intervals_missed=4.0), Verdict.SUSPECT),
    ("a jump the timestamps do not show", Tracking(motion_ratio=20.0, image_motion_px=60.0), Verdict.SUSPECT),
])
def test_the_verdict_of_each_recorded_case(case, tracking, verdict):
    assert judge(tracking, DivergenceConfig()).verdict is verdict, case


def test_the_ratio_is_rmse_end_over_rmse_before():
    judgement = judge(Tracking(rmse_before=10.0, rmse_end=10.5, result=Result(rmse_after=14.0)), DivergenceConfig())
    assert judgement.ratio == pytest.approx(1.05) and np.isfinite(judgement.threshold)
