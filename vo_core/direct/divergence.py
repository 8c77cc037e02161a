"""Whether a direct alignment can be trusted (FDMO section 4.2.1).

FDMO's test: the optimization of Eq. 2 diverged when RMSE_after / RMSE_before > 1 + epsilon, epsilon = 0.1,
the RMSE before being the one at the constant-velocity guess, both measured alike (``DirectTracking.rmse_end``).
It misses a case that matters: after a jump the guess is so wrong that the optimization lowers the RMSE while
locking onto a wrong pose (teddy with 20 frames dropped at frame 100: RMSE 15.6 -> 13.5, ratio 0.87, a pose 20 cm
off). DSO itself knows something is off then: it tried every motion hypothesis and none came within
``retrack_threshold`` (1.5) of the last frame's RMSE (trackNewCoarse's stopping rule). That is not proof of
divergence (fast handheld motion does it in 4 % of teddy's frames), so such a result is SUSPECT: the system has it
checked by the feature map, which decides. So is every result after missed frames (the timestamps say so): the
motion across the gap is unknown, and a converged alignment with a fair RMSE proves little there (teddy, 45 frames
dropped: 14 of 27 degrees found, RMSE within the retrack threshold, ratio below 1.1). And so is a frame whose image
moved far more than the last frames' did (``sudden_motion_factor`` times their median): a jump the timestamps do not
show (a video's dropped frames, FDMO's own frame-drop protocol, a shake). There DSO's guesses can fit the new view
with a normal RMSE at a wrong pose (teddy, 20 frames dropped and retimed: RMSE 6.35 against 6.0 before, 85 % of the
translation missing, the image moved 22x the last frames' median), which nothing else notices.
A result whose final pose leaves most of its residuals beyond the cutoff explains too little of the image to be kept
unchecked, the RMSE ratio being blind there (both ends saturated): it is SUSPECT, and ``saturated`` says so (fdmo/decide
keeps it only where the feature map or the motion prior confirms it). A black frame leaves all of them; a right pose
after a jump can leave more than half too (parking, 3.15 m dropped: 54 %, 0.8 px from where the motion prior put it).
A result that did not converge at all is LOST (DSO's lost: no hypothesis converged, too few residuals).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the settings are read by vo_core.config, which must not load the direct half's kernels
    from vo_core.direct.odometry import DirectTracking


class Verdict(Enum):
    TRUSTED = "trusted"
    SUSPECT = "suspect"  # every motion hypothesis was worse than the last frame's fit: to be checked
    DIVERGED = "diverged"  # FDMO 4.2.1: the optimization made the RMSE worse
    LOST = "lost"  # no hypothesis converged


@dataclass
class DivergenceConfig:
    epsilon: float = 0.1  # FDMO 4.2.1: diverged when RMSE_after / RMSE_before > 1 + 0.1
    check_when_no_hypothesis_good_enough: bool = True  # ours (DSO's reTrackThreshold as a suspicion, see above)
    check_after_missed_frames: bool = True  # ours (see above; direct.tracker.time_gap_factor says what is missed)
    # Ours (see above): suspect when the image moved this many times the last frames' median motion. On the clean
    # shared folders a frame moves at most 3.9x (teddy), 2.3x (KITTI), 1.4x (parking) the median of the 10 before;
    # the first frame after a retimed jump 19-22x (teddy, 10-30 frames), 9x (KITTI, 5), 5.6x (parking, 10).
    sudden_motion_factor: float = 5.0
    # Suspect (saturated) where the final pose leaves more than this share of the terms beyond the tracker's cutoff:
    # the alignment then explains less than half of what it sees, and a truncated (cutoff) energy is decided by the
    # rest (its breakdown point). A black frame leaves all of them; clean frames of the shared folders at most 17 %,
    # TUM fr1/desk at half its frame rate at most 70 % (9 of 298 frames above a half), a right pose after parking's
    # 3.15 m drop 54 %.
    max_saturated_share: float = 0.5


@dataclass
class Judgement:
    verdict: Verdict
    ratio: float  # RMSE_after / RMSE_before (NaN when lost)
    threshold: float  # 1 + epsilon
    reason: str
    jump: bool = False  # suspect because the camera may have jumped (missed frames, a sudden motion)
    saturated: bool = False  # suspect because the final pose leaves most of the residuals beyond the cutoff

    def details(self, tracking: DirectTracking) -> dict:
        return {
            "verdict": self.verdict.value, "reason": self.reason, "ratio": rounded_rmse(self.ratio),
            "threshold": self.threshold, "rmse_before": rounded_rmse(tracking.rmse_before),
            "rmse_end": rounded_rmse(tracking.rmse_end), "rmse_after": rounded_rmse(tracking.rmse_after),
            "saturated_end": rounded_rmse(tracking.saturated_end),
            "last_rmse": rounded_rmse(tracking.last_rmse),
            "hypotheses_tried": tracking.hypotheses_tried,
        }


def judge(tracking: DirectTracking, config: DivergenceConfig) -> Judgement:
    threshold = 1.0 + config.epsilon
    if not tracking.converged:
        return Judgement(Verdict.LOST, float("nan"), threshold, "no motion hypothesis converged")
    ratio = tracking.rmse_end / tracking.rmse_before if tracking.rmse_before > 0 else float("inf")
    if ratio > threshold:
        return Judgement(Verdict.DIVERGED, ratio, threshold, f"RMSE after / before {ratio:.2f} > {threshold:.2f}")
    reasons, jump = [], False
    saturated = tracking.saturated_end > config.max_saturated_share
    if saturated:
        reasons.append(f"the final pose leaves {tracking.saturated_end:.0%} of the residuals beyond the cutoff: the "
                       "alignment explains less than half of the image")
    if config.check_when_no_hypothesis_good_enough and not tracking.good_enough:
        reasons.append(f"no motion hypothesis ({tracking.hypotheses_tried} tried) came within the retrack threshold "
                       f"of the last frame's RMSE ({tracking.rmse_after:.2f} against {tracking.last_rmse:.2f})")
    if config.check_after_missed_frames and tracking.intervals_missed is not None:
        reasons.append(f"{tracking.intervals_missed:.1f} frame intervals since the last tracked frame: frames were "
                       "missed")
        jump = True
    motion_ratio = tracking.motion_ratio
    if motion_ratio is not None and motion_ratio > config.sudden_motion_factor:
        # After a gap the timestamps show, the large motion is that gap's, not a jump they do not show.
        unseen = ": a jump the timestamps do not show" if tracking.intervals_missed is None else " across the gap"
        reasons.append(f"the image moved {tracking.image_motion_px:.0f} px, {motion_ratio:.1f}x the last frames' "
                       f"median of {tracking.typical_motion_px:.1f} px{unseen}")
        jump = True
    if reasons:
        return Judgement(Verdict.SUSPECT, ratio, threshold, "; ".join(reasons), jump, saturated)
    return Judgement(Verdict.TRUSTED, ratio, threshold, "")


def rounded_rmse(value: float) -> float | None:
    """An RMSE or ratio as the events give it: 3 decimals, None where it is not finite."""
    return round(float(value), 3) if np.isfinite(value) else None
