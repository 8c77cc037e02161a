"""FDMO's divergence test (vo_core/direct/divergence.py) as a function of its evidence: a row per recorded case."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from vo_core.direct.divergence import DivergenceConfig, Verdict, judge
from vo_core.direct.odometry import DirectTracking


def tracking(rmse_before=8.0, rmse_end=6.0, saturated_end=0.05, rmse_after=None, converged=True, good_enough=True,
             intervals_missed=None, image_motion_px=3.0) -> DirectTracking:
    """A direct tracking result of the given measures (the alignment's own RMSE ``rmse_after`` is ``rmse_end`` unless
    given), whose image moved ``image_motion_px`` where the last frames moved 3 px."""
    result = SimpleNamespace(success=converged, rmse_after=rmse_end if rmse_after is None else rmse_after)
    return DirectTracking(reference=None, result=result, rmse_before=rmse_before, rmse_end=rmse_end,
                          saturated_end=saturated_end, achieved_rmse=np.array([result.rmse_after]), last_rmse=6.0,
                          good_enough=good_enough, hypotheses_tried=1, from_prior=False, ms=1.0,
                          intervals_missed=intervals_missed, image_motion_px=image_motion_px, typical_motion_px=3.0)


@pytest.mark.parametrize("case, evidence, verdict", [
    ("a steady frame", tracking(), Verdict.TRUSTED),
    ("FDMO 4.2.1: the optimization made the RMSE worse", tracking(rmse_before=8.0, rmse_end=9.0), Verdict.DIVERGED),
    # TUM fr1/desk at half its frame rate: DSO's cutoff raised on the finest level made the alignment's own RMSE
    # 1.26-1.39x the start's, at poses whose RMSE measured alike was 0.91-0.99x it.
    ("the same pose measured alike", tracking(rmse_before=10.0, rmse_end=9.4, saturated_end=0.45,
                                             rmse_after=13.9), Verdict.TRUSTED),
    # A black frame leaves every residual beyond the cutoff; a right pose 3.15 m on after 20 frames dropped on parking
    # 54 % of them (0.8 px from where the motion prior put it): neither is trusted, both go to the feature map and the
    # prior (fdmo/decide.py).
    ("a black frame: both ends saturated", tracking(rmse_before=12.0, rmse_end=12.0, saturated_end=1.0),
     Verdict.SUSPECT),
    ("parking, 3.15 m dropped: a right pose leaves 54 % beyond the cutoff",
     tracking(rmse_before=14.4, rmse_end=13.6, saturated_end=0.54, good_enough=False, intervals_missed=21.0),
     Verdict.SUSPECT),
    ("no hypothesis converged", tracking(converged=False), Verdict.LOST),
    ("every hypothesis worse than the last frame", tracking(good_enough=False), Verdict.SUSPECT),
    ("frames were missed", tracking(intervals_missed=4.0), Verdict.SUSPECT),
    ("a jump the timestamps do not show", tracking(image_motion_px=60.0), Verdict.SUSPECT),
])
def test_the_verdict_of_each_recorded_case(case, evidence, verdict):
    assert judge(evidence, DivergenceConfig()).verdict is verdict, case


def test_only_a_pose_that_leaves_most_residuals_beyond_the_cutoff_is_saturated():
    assert judge(tracking(saturated_end=1.0), DivergenceConfig()).saturated
    assert not judge(tracking(saturated_end=0.45, good_enough=False), DivergenceConfig()).saturated


def test_the_ratio_is_rmse_end_over_rmse_before():
    judgement = judge(tracking(rmse_before=10.0, rmse_end=10.5, rmse_after=14.0), DivergenceConfig())
    assert judgement.ratio == pytest.approx(1.05) and np.isfinite(judgement.threshold)
