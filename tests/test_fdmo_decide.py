"""FDMO's decision about a frame direct tracking did not trust (vo_core/fdmo/decide.py), as a table: each row is the
evidence of a recorded case (or the boundary beside one), written as numbers, and the decision the system takes on it:
the outcome, what is appended to the divergence test's reason where the direct pose is not kept, the check's measures
for the event where it is kept, and why a recovered pose is refused. The system's defaults throughout (agreement
0.8, overrule share 10 %, gap motion share 0.5, prior reliability 0.25, a jump 5 intervals; a recovery 30 inliers and
5 %, a search around the estimate 10 %).
"""

from __future__ import annotations

import dataclasses

import pytest

from vo_core.config import Config
from vo_core.direct.divergence import Verdict
from vo_core.fdmo.decide import Decision, Outcome, decide
from vo_core.fdmo.evidence import (DirectEvidence, Evidence, FeatureEvidence, FeaturePose, Motion, PriorEvidence,
                                   Search)

CONFIG = Config()
REASON = "the divergence test's reason"
NO_HYPOTHESIS = DirectEvidence(Verdict.SUSPECT, REASON, jump=False, good_enough=False, rmse_after=9.0, last_rmse=8.0)


def gap(intervals: float) -> DirectEvidence:
    """A suspect frame after missed frames (a jump the timestamps show), that fit as well as the last frame."""
    return DirectEvidence(Verdict.SUSPECT, REASON, jump=True, good_enough=True, rmse_after=12.1, last_rmse=12.0,
                          intervals_missed=intervals)


NOTHING = FeatureEvidence(succeeded=False)  # the feature map has no pose for the frame, and no search contradicts it
STEADY = 0.01 * 11 ** 0.5  # a car's or a rig's motion prior over 11 intervals (KITTI, parking: 0.01 a frame)
HANDHELD = 0.27 * 31 ** 0.5  # teddy's over 31


@dataclasses.dataclass(frozen=True)
class Row:
    name: str
    evidence: Evidence
    outcome: Outcome
    appended: str = ""  # what the decision appends to the divergence test's reason
    details: dict = dataclasses.field(default_factory=dict)
    refusal: str | None = None


ROWS = [
    Row("trusted: nothing to decide", Evidence(DirectEvidence(Verdict.TRUSTED, ""), NOTHING), Outcome.ACCEPT),
    # Teddy: direct poses the feature map confirmed explained 97-99.5 % of its recovery's inlier matches.
    Row("the feature map's recovery confirms the direct pose (teddy: 97 %)",
        Evidence(NO_HYPOTHESIS, FeatureEvidence(True, FeaturePose(120, 0.14, 0.97))),
        Outcome.ACCEPT, details={"explained": 0.97, "agreed": True}),
    Row("agreement is 80 % of the matches, not more",
        Evidence(NO_HYPOTHESIS, FeatureEvidence(True, FeaturePose(120, 0.14, 0.8))),
        Outcome.ACCEPT, details={"explained": 0.8, "agreed": True}),
    # Teddy, 20 frames dropped at 100: the pose locked 20 cm off explained 41 % of a recovery that found 13 %.
    Row("a conclusive recovery overrules the direct pose (teddy 100:20: 41 %, 13 % found)",
        Evidence(gap(21), FeatureEvidence(True, FeaturePose(95, 0.13, 0.41))),
        Outcome.RECOVER, "; the feature map disagrees (the direct pose explains 41% of its matches)"),
    # Parking, 3.15 m dropped: a global recovery at a look-alike place 30 frames back gathered 80 inliers, 5.6 % of the
    # points in view, against a right direct pose (1.42 m against direct's 0.0153 m), 0.3 px from the prediction.
    Row("a recovery too weakly anchored to overrule leaves the direct pose unverified (parking 3.15 m: 80, 5.6 %)",
        Evidence(gap(11), FeatureEvidence(True, FeaturePose(80, 0.056, 0.05)),
                 PriorEvidence(STEADY, direct=Motion(201.0, 200.8, 0.3))),
        Outcome.ACCEPT_UNVERIFIED, details={
            "explained": 0.05, "predicted_motion_px": 201.0, "direct_motion_px": 200.8, "from_prediction_px": 0.3,
            "why": "the feature map's pose (80 inliers, 5.6% of the points in view) disagrees but is too weakly "
                   "supported to overrule the direct one"}),
    Row("... and one off the prediction by more than half its motion is not kept, nor the weak recovery taken",
        Evidence(gap(11), FeatureEvidence(True, FeaturePose(80, 0.056, 0.05)),
                 PriorEvidence(STEADY, direct=Motion(200.0, 90.0, 110.0), recovered=Motion(200.0, 60.0, 140.0))),
        Outcome.LOST,
        "; over 11 frame intervals the direct pose moved the map 90 px where the last motion predicts 200 px (110 px "
        "apart); the feature map's pose (80 inliers, 5.6% of the points in view) is too weakly supported to confirm it",
        refusal="the recovered pose (80 inliers, 5.6% of the points in view) lies 140 px from where the last motion "
                "puts the camera after 11 frame intervals (200 px of motion predicted), and the motion has been that "
                "predictable"),
    # KITTI, 54 m dropped (60 frames): the search around a wrong direct pose found 5 of the 287 points it expected.
    Row("the search around the direct pose contradicts it (KITTI 54 m: 5 of 287)",
        Evidence(gap(61), FeatureEvidence(False, around_estimate=Search(5, 287))),
        Outcome.LOST, "; the feature map finds 5 of the 287 points it expects in view at the direct pose"),
    # KITTI, 20 m dropped: 5 of 49 (10 %) around a right one; the direct map still holds the far points the feature map
    # lost (direct alone 0.159 m; dropped as diverged until a new map: 8.59 m).
    Row("a search that finds a recovery's share does not (KITTI 20 m: 5 of 49), and the pose stands unverified",
        Evidence(gap(21), FeatureEvidence(False, around_estimate=Search(5, 49)),
                 PriorEvidence(STEADY, direct=Motion(300.0, 290.0, 20.0))),
        Outcome.ACCEPT_UNVERIFIED, details={
            "predicted_motion_px": 300.0, "direct_motion_px": 290.0, "from_prediction_px": 20.0,
            "why": "the feature map does not recognize this view, and does not contradict the direct pose"}),
    Row("a search that expects fewer points than a recovery's count contradicts nothing (0 of 29)",
        Evidence(gap(21), FeatureEvidence(False, around_estimate=Search(0, 29))),
        Outcome.ACCEPT_UNVERIFIED, details={
            "why": "the feature map does not recognize this view, and does not contradict the direct pose"}),
    # Parking, 9 m dropped: the direct pose moved 15 px where 584 px were predicted (the look-alike cars it had passed).
    Row("the direct pose stayed behind the prediction and nothing places the frame (parking 9 m: 15 px of 584)",
        Evidence(gap(31), NOTHING, PriorEvidence(STEADY, direct=Motion(584.0, 15.0, 570.0))),
        Outcome.LOST,
        "; over 31 frame intervals the direct pose moved the map 15 px where the last motion predicts 584 px (570 px "
        "apart), and the feature map cannot place the frame"),
    Row("the same gap rule holds where the motion prior is not reliable (it judges the direct pose unconfirmed)",
        Evidence(gap(31), NOTHING, PriorEvidence(HANDHELD, direct=Motion(584.0, 15.0, 570.0))),
        Outcome.LOST,
        "; over 31 frame intervals the direct pose moved the map 15 px where the last motion predicts 584 px (570 px "
        "apart), and the feature map cannot place the frame"),
    # KITTI live-like (1-4 frames missed every 2-5): right poses 13 px from where 34 px were predicted.
    Row("a gap shorter than a jump is not judged by the prior (KITTI live-like: 13 px of 34 over 3 intervals)",
        Evidence(gap(3), NOTHING, PriorEvidence(STEADY, direct=Motion(34.0, 13.0, 21.0))),
        Outcome.ACCEPT_UNVERIFIED, details={
            "predicted_motion_px": 34.0, "direct_motion_px": 13.0, "from_prediction_px": 21.0,
            "why": "the feature map does not recognize this view, and does not contradict the direct pose"}),
    Row("a frame too poor in features to say anything keeps the direct pose, checked",
        Evidence(gap(31), FeatureEvidence(False, feature_deprived=True),
                 PriorEvidence(STEADY, direct=Motion(584.0, 15.0, 570.0))),
        Outcome.ACCEPT, details={"agreed": None}),
    # Teddy, 30 frames dropped and retimed: the lock left an RMSE of 13.7 against 6.0.
    Row("after a sudden motion the timestamps do not show, a pose that fits worse than the last frame is not kept",
        Evidence(DirectEvidence(Verdict.SUSPECT, REASON, jump=True, good_enough=False, rmse_after=13.7, last_rmse=6.0),
                 NOTHING),
        Outcome.LOST, "; after the sudden motion the direct pose fits worse than the last frame (RMSE 13.70 against "
                      "6.00), and the feature map cannot place the frame"),
    Row("... one that fits as well stands unverified",
        Evidence(DirectEvidence(Verdict.SUSPECT, REASON, jump=True, good_enough=True, rmse_after=6.35, last_rmse=6.0),
                 NOTHING),
        Outcome.ACCEPT_UNVERIFIED, details={
            "why": "the feature map does not recognize this view, and does not contradict the direct pose"}),
    Row("DSO's retrack threshold alone (no jump): the direct pose stands unverified (4 % of teddy's frames)",
        Evidence(NO_HYPOTHESIS, NOTHING), Outcome.ACCEPT_UNVERIFIED, details={
            "why": "the feature map does not recognize this view, and does not contradict the direct pose"}),
    Row("a feature pose that agrees but is no recovery confirms a pose that may stand unconfirmed",
        Evidence(NO_HYPOTHESIS, FeatureEvidence(False, FeaturePose(25, 0.04, 0.9))),
        Outcome.ACCEPT, details={"explained": 0.9, "agreed": True}),
    Row("... but does not spare it the gap rule: after a jump off the prediction, not kept",
        Evidence(gap(11), FeatureEvidence(False, FeaturePose(25, 0.04, 0.9)),
                 PriorEvidence(STEADY, direct=Motion(200.0, 20.0, 180.0))),
        Outcome.LOST,
        "; over 11 frame intervals the direct pose moved the map 20 px where the last motion predicts 200 px (180 px "
        "apart); the feature map's pose (25 inliers, 4.0% of the points in view) is too weakly supported to confirm "
        "it"),
    Row("a feature pose under a RANSAC's 10 inliers is not compared at all",
        Evidence(NO_HYPOTHESIS, FeatureEvidence(False, FeaturePose(9, 0.3, None))), Outcome.ACCEPT_UNVERIFIED,
        details={"why": "the feature map does not recognize this view, and does not contradict the direct pose"}),
    # Parking, 5 m dropped at frame 100: the feature map confirmed a direct pose by the cars the camera had passed.
    Row("a confirmed direct pose that stayed behind a reliable prediction is not kept (parking 5 m), nor the recovery",
        Evidence(gap(11), FeatureEvidence(True, FeaturePose(150, 0.12, 0.95)),
                 PriorEvidence(STEADY, direct=Motion(300.0, 10.0, 290.0), recovered=Motion(300.0, 12.0, 288.0))),
        Outcome.LOST,
        "; the direct pose, which the feature map confirms, stayed behind (10 px from the last pose): lies 290 px from "
        "where the last motion puts the camera after 11 frame intervals (300 px of motion predicted), and the motion "
        "has been that predictable",
        refusal="the recovered pose (150 inliers, 12.0% of the points in view) stayed behind (12 px from the last "
                "pose): lies 288 px from where the last motion puts the camera after 11 frame intervals (300 px of "
                "motion predicted), and the motion has been that predictable"),
    Row("... where the motion is a handheld camera's, the confirmed pose stands",
        Evidence(gap(31), FeatureEvidence(True, FeaturePose(150, 0.12, 0.95)),
                 PriorEvidence(HANDHELD, direct=Motion(300.0, 10.0, 290.0))),
        Outcome.ACCEPT, details={"explained": 0.95, "agreed": True}),
    # KITTI with 1-4 frames missed every 2-5: right poses 19 px from a 33 px prediction, both halves agreeing.
    Row("a confirmed pose off the prediction after a gap shorter than a jump stands (KITTI live-like: 19 px of 33)",
        Evidence(gap(3), FeatureEvidence(True, FeaturePose(150, 0.2, 0.9)),
                 PriorEvidence(0.01 * 3 ** 0.5, direct=Motion(33.0, 14.0, 19.0))),
        Outcome.ACCEPT, details={"explained": 0.9, "agreed": True}),
    # Parking, 9.15 m dropped along rows of parked cars: a 5.0 % recovery at a look-alike place 9 m behind.
    Row("a weak recovery off a reliable prediction is refused (parking 9.15 m: 5.0 %)",
        Evidence(DirectEvidence(Verdict.DIVERGED, REASON, intervals_missed=31.0),
                 FeatureEvidence(True, FeaturePose(40, 0.05)),
                 PriorEvidence(STEADY, recovered=Motion(600.0, 30.0, 570.0))),
        Outcome.LOST, refusal="the recovered pose (40 inliers, 5.0% of the points in view) lies 570 px from where the "
                              "last motion puts the camera after 31 frame intervals (600 px of motion predicted), and "
                              "the motion has been that predictable"),
    # Teddy, 30 frames dropped: the 6.4 % recovery was right, the prediction was not.
    Row("... and taken where the motion is a handheld camera's (teddy 30 dropped: 6.4 %)",
        Evidence(DirectEvidence(Verdict.DIVERGED, REASON, intervals_missed=31.0),
                 FeatureEvidence(True, FeaturePose(60, 0.064)),
                 PriorEvidence(HANDHELD, recovered=Motion(600.0, 30.0, 570.0))),
        Outcome.RECOVER),
    Row("a strong recovery that went past the prediction is taken (only staying behind refuses it)",
        Evidence(DirectEvidence(Verdict.DIVERGED, REASON, intervals_missed=11.0),
                 FeatureEvidence(True, FeaturePose(150, 0.15)),
                 PriorEvidence(STEADY, recovered=Motion(300.0, 500.0, 200.0))),
        Outcome.RECOVER),
    Row("diverged, no feature pose: lost",
        Evidence(DirectEvidence(Verdict.DIVERGED, REASON), NOTHING), Outcome.LOST),
    Row("lost (no hypothesis converged) and a recovery: recover",
        Evidence(DirectEvidence(Verdict.LOST, "no motion hypothesis converged"),
                 FeatureEvidence(True, FeaturePose(90, 0.2))), Outcome.RECOVER),
]


@pytest.mark.parametrize("row", ROWS, ids=[row.name for row in ROWS])
def test_decide(row):
    decision = decide(row.evidence, CONFIG)
    assert decision == Decision(row.outcome, row.evidence.direct.reason + row.appended, row.details, row.refusal)
    assert decision.kept == (row.outcome in (Outcome.ACCEPT, Outcome.ACCEPT_UNVERIFIED))


def test_every_outcome_has_a_row():
    assert {row.outcome for row in ROWS} == set(Outcome)
    assert any(row.refusal for row in ROWS) and any(row.appended and not row.refusal for row in ROWS)


def test_decide_changes_nothing_and_answers_alike():
    """A pure function: the evidence is frozen, and the same evidence gives the same decision."""
    row = ROWS[4]
    with pytest.raises(dataclasses.FrozenInstanceError):
        row.evidence.direct.reason = "changed"  # type: ignore[misc]
    assert decide(row.evidence, CONFIG) == decide(row.evidence, CONFIG)
