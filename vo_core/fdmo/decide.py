"""FDMO's decisions, pure functions of the evidence (evidence.py) and the config: they change nothing and ask no half;
the system carries them out. ``decide``: what becomes of a frame direct tracking did not trust (Odometry._carry_out);
``after_recovery``: how tracking goes back to direct from a recovered pose (Odometry._continue_from).

    verdict suspect (the camera may have jumped, no motion hypothesis fit as well as the last frame, or the pose
    leaves most of the residuals beyond the cutoff):
        the feature map's pose (10+ inliers), compared with the direct one (the share of its inliers it explains):
            agrees (>= fdmo.agreement)                                     ACCEPT (checked) where it is a recovery or
                                                                           the direct pose may stand unconfirmed,
                                                                           unless that stayed behind a reliable prior
            disagrees with a conclusive share of the points in view         not kept
            (features.recovery.conclusive_found_fraction)
            disagrees, too weak to overrule                                ACCEPT_UNVERIFIED where the direct pose
                                                                           may stand unconfirmed, else not kept
        no feature pose:
            the frame is feature-deprived, the pose not saturated          ACCEPT (checked, nothing to check with)
            the search around the direct pose finds under a recovery's
            share of the points it expects there                          not kept
            else                                                           ACCEPT_UNVERIFIED where the direct pose
                                                                           may stand unconfirmed, else not kept
    not kept (a suspect pose refused, or the verdict diverged or lost):
        the feature map recovered a pose                                   RECOVER, unless it lies off a reliable
                                                                           motion prior: LOST (refused)
        else                                                               LOST

"May stand unconfirmed": after missed frames as long as a jump (divergence.sudden_motion_factor intervals), the direct
pose lies within fdmo.gap_motion_share of the image motion the prior predicts, from the predicted pose; after a sudden
motion the timestamps do not show, it fits the images as well as the last frame did (DSO's retrack threshold). A
saturated pose (most residuals beyond the cutoff) only after missed frames, within fdmo.gap_motion_share of a reliable
prior's prediction.
"Off a reliable prior": the prior's error over the gap is at most fdmo.prior_reliability and the pose lies further than
fdmo.gap_motion_share of the predicted motion from the predicted pose; a pose the feature map supports (a direct pose
it confirms, a recovery with a conclusive share) only where, after a gap as long as a jump, it stayed behind (moved
less than fdmo.gap_motion_share of the predicted motion from the last pose).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

from vo_core.direct.divergence import Verdict
from vo_core.fdmo.evidence import Evidence, Motion, RecoveredEvidence
from vo_core.features.mapping import KeyframeCheck


class Outcome(Enum):
    ACCEPT = "accept"  # the direct pose is kept, checked: the feature map confirms it (or cannot, feature-deprived)
    ACCEPT_UNVERIFIED = "accept_unverified"  # kept: the feature map can neither confirm nor overrule it
    RECOVER = "recover"  # not kept: back to direct from the feature map's pose (Odometry._continue_from)
    LOST = "lost"  # not kept, and no pose: the recovery failed, or was refused (Decision.refusal)


@dataclass(frozen=True)
class Decision:
    outcome: Outcome
    reason: str  # the divergence test's reason, with why the direct pose is not kept where it is not
    # The check's measures for the event of a kept pose (tracking_checked, tracking_unverified), beside the verdict's
    # and the feature map's: explained, the motion against the prior, and "agreed" or "why".
    details: dict = field(default_factory=dict)
    refusal: str | None = None  # why a recovered pose is not taken (recovery_failed's reason)

    @property
    def kept(self) -> bool:
        return self.outcome in (Outcome.ACCEPT, Outcome.ACCEPT_UNVERIFIED)


def decide(evidence: Evidence, config) -> Decision:
    """What becomes of the frame (``config``: the system's Config, its fdmo and features.recovery settings)."""
    verdict = evidence.direct.verdict
    if verdict is Verdict.TRUSTED:
        return Decision(Outcome.ACCEPT, evidence.direct.reason)
    reason = evidence.direct.reason
    if verdict is Verdict.SUSPECT:
        kept = _suspect(evidence, config)
        if isinstance(kept, Decision):
            return kept
        reason += kept
    return _recovery(evidence, reason, config)


def _suspect(evidence: Evidence, config) -> Decision | str:
    """Whether a suspect direct pose is kept (its Decision), else why not (to append to the reason). The feature
    map's pose confirms it where the two agree; it overrules it only with a conclusive share of the map points in
    view; below that share, or with no feature pose at all, the direct pose is kept, reported as unverified, unless
    the search around it finds almost none of the points the map expects there, or, after a jump, it may not stand
    unconfirmed. A frame with too few features to say anything keeps it too (FDMO's point: the direct estimate is
    then all there is)."""
    fdmo, recovery = config.fdmo, config.features.recovery
    features, reason = evidence.features, evidence.direct.reason
    details: dict = {}
    pose = features.pose
    if pose is not None and pose.inliers >= recovery.min_ransac_inliers:
        explained = pose.explained
        details["explained"] = round(explained, 3)
        agrees = explained >= fdmo.agreement
        # A feature pose confirms only as a recovery (its inliers and share), and overrules only with a conclusive
        # share; a weaker one, agreeing or not, leaves the direct pose to the motion check.
        conclusive = features.succeeded if agrees else pose.found_fraction >= recovery.conclusive_found_fraction
        if conclusive and not agrees:
            return f"; the feature map disagrees (the direct pose explains {explained:.0%} of its matches)"
        if not conclusive:
            unconfirmed = _may_not_stand_unconfirmed(evidence, config, details)
            if unconfirmed is not None:
                return (f"{unconfirmed}; the feature map's pose ({pose.inliers} inliers, {pose.found_fraction:.1%} "
                        "of the points in view) is too weakly supported to confirm it")
        if agrees:
            lock = _off_reliable_prediction(evidence, evidence.prior.direct,
                                            "the direct pose, which the feature map confirms,", True, config)
            if lock is not None:
                return f"; {lock}"
            return Decision(Outcome.ACCEPT, reason, {**details, "agreed": True})
        return Decision(Outcome.ACCEPT_UNVERIFIED, reason, {**details, "why": (
            f"the feature map's pose ({pose.inliers} inliers, {pose.found_fraction:.1%} of the points in view) "
            "disagrees but is too weakly supported to overrule the direct one")})
    if features.feature_deprived and not evidence.direct.saturated:
        return Decision(Outcome.ACCEPT, reason, {"agreed": None})
    around = features.around_estimate
    if around is not None and around.in_view >= recovery.min_inliers \
            and around.found_fraction < recovery.min_found_fraction:
        return (f"; the feature map finds {around.inliers} of the {around.in_view} points it expects in view at the "
                "direct pose")
    unconfirmed = _may_not_stand_unconfirmed(evidence, config, details)
    if unconfirmed is not None:
        return f"{unconfirmed}, and the feature map cannot place the frame"
    # No feature pose, and nothing that contradicts the converged alignment: after a long forward jump the direct map
    # still holds the far points the feature map lost.
    return Decision(Outcome.ACCEPT_UNVERIFIED, reason, {
        **details, "why": "the feature map does not recognize this view, and does not contradict the direct pose"})


def judge_keyframe(check: KeyframeCheck | None, start_on_probation: bool, held: bool, config) -> str | None:
    """Why a new direct keyframe does not join the feature map (one of a start on probation: why the start fails), None
    where it joins. The evidence is a suspect frame's (``_suspect``): the feature map's pose for the keyframe, searched
    around the direct one (KeyframeCheck). The feature map is the reference the direct map is judged by only where it
    sees the view: at least a recovery's 30 points in view (``features.recovery.min_inliers``, FDMO's 30).

    - It overrules the direct pose where it would be taken as a recovery (30 inliers), found a conclusive share of the
      map points in view (``features.recovery.conclusive_found_fraction``), and most of its matches contradict the
      direct pose (it explains under ``fdmo.agreement`` of them). Checked at every keyframe, it catches the direct map
      drifting from the feature map's points where no frame's tracking looks suspect.
    - The direct half's scale watch (direct/scale_watch.py) is not evidence here, only a warning to the user: on the
      drone clip it saw a jump in every run where the window's near points left the view (its mean inverse depth fell
      4-6x while the speed changed 1.2x) and the feature map confirmed the keyframe (99-100 % of 101-178 matches
      explained, 53-60 % of the map points in view found); refusing those keyframes restarted the direct map for
      nothing. On TUM fr1/desk, where it was meant to catch the collapse, the matrix came out the same within the
      seeds' spread without it.
    - Once it overruled one, it is ``held``: it takes no direct keyframe until it agrees with one again (a recovery's
      30 inliers, ``agreement`` of them explained) or the view has left it (nothing to judge by: the direct
      map is then all there is), or a frame went on from its pose (system.py). A feature map that followed the next
      keyframes would hold the wrong map's points, and every later recovery would bring its scale back.
    - A keyframe of a start on probation is judged as if nothing were held, and where the feature map disagrees the
      start fails (system.py; direct/start_check.py judges it too): the feature map then holds only that start's own
      points, triangulated at its first poses, so a window that moved its keyframes away from them has rebuilt the
      start's structure rather than refined it, the two halves of one start that no longer agree. Overruling the
      keyframe instead, and restarting the direct map from the feature map, restarted the wrong start (the drone clip
      at half its frame rate, seed 1: 10 % explained 3 optimizations after the hand-over, restarted from 86 feature
      depths, 0.060 -> 0.478 m; the start check refused that start later on its own). Across the real-data matrix
      (fdmo, seeds 0-2, strides 1-3) two starts fail so: that one (12 % of 95 matches, at its third keyframe) and
      fr1/desk's at half its frame rate, seed 2 (28 % of 54, at its second), a start the start check had kept while its
      map shrank 16-47x (0.598 -> 0.428 m)."""
    fdmo, recovery = config.fdmo, config.features.recovery
    held = held and not start_on_probation
    if check is None or check.in_view < recovery.min_inliers:
        return None
    recovery_grade = check.inliers >= recovery.min_inliers
    agrees = recovery_grade and check.explained >= fdmo.agreement
    measured = (f"the direct pose explains {check.explained:.0%} of its {check.inliers} matches, "
                f"{check.found_fraction:.0%} of the map points in view")
    if held:
        return None if agrees else f"the feature map holds still: it does not confirm the direct keyframe ({measured})"
    if agrees or not recovery_grade or check.found_fraction < recovery.conclusive_found_fraction:
        return None
    return f"the feature map disagrees with the direct keyframe ({measured})"


def _may_not_stand_unconfirmed(evidence: Evidence, config, details: dict) -> str | None:
    """Why a direct pose that nothing confirms may not stand after a jump (to append to the reason), None where it
    may. Direct alignment after a large jump locks onto what looks alike near where it started, and nothing else tells
    that lock from a right pose when the feature map cannot place the frame:

    - after missed frames, the motion prior does: the pose must lie within ``gap_motion_share`` of the image motion it
      predicts, from the predicted pose. A gap shorter than a jump (fewer than ``divergence.sudden_motion_factor``
      intervals) is not judged so: the prediction's own error is as large there;
    - after a sudden motion the timestamps do not show, there is no such prediction: the pose must fit the images as
      well as the last frames did (DSO's retrack threshold).

    A pose that leaves most of the residuals beyond the cutoff (``saturated``: the alignment explains less than half
    of the image, and says nothing of itself) stands only where the motion prior confirms it: after missed frames,
    with a prior reliable enough to judge by (``prior_reliable``), within ``gap_motion_share`` of its prediction
    (parking, 3.15 m dropped: 54 % saturated, 0.8 px from the prediction, right). A black frame, with no gap, is not
    kept. Other frames pass. ``details`` gets the motion measures either way."""
    direct = evidence.direct
    if direct.saturated:
        return _unless_the_prior_confirms(evidence, config, details)
    if direct.intervals_missed is None:
        if not direct.jump or direct.good_enough:
            return None
        return (f"; after the sudden motion the direct pose fits worse than the last frame (RMSE "
                f"{direct.rmse_after:.2f} against {direct.last_rmse:.2f})")
    off = evidence.prior.direct
    if off is None:
        return None
    _record_motion(off, details)
    shorter_than_a_jump = direct.intervals_missed < config.fdmo.divergence.sudden_motion_factor
    if shorter_than_a_jump or not _strays(off, config):
        return None
    return (f"; over {direct.intervals_missed:.0f} frame intervals the direct pose moved the map {off.found_px:.0f} px "
            f"where the last motion predicts {off.predicted_px:.0f} px ({off.apart_px:.0f} px apart)")


def _unless_the_prior_confirms(evidence: Evidence, config, details: dict) -> str | None:
    """Why a pose may not stand on the motion prior alone (to append to the reason), None where the prior confirms
    it: after missed frames, a reliable prior predicts it within ``gap_motion_share`` of its image motion."""
    unconfirmed = "; neither the feature map nor the motion prior confirms it"
    off = evidence.prior.direct
    if off is None:
        return unconfirmed
    _record_motion(off, details)
    return None if prior_reliable(evidence.prior.error, config) and not _strays(off, config) else unconfirmed


def _record_motion(off: Motion, details: dict) -> None:
    """The direct pose's motion against the prior, for the event of a kept pose."""
    details.update(predicted_motion_px=round(off.predicted_px, 1), direct_motion_px=round(off.found_px, 1),
                   from_prediction_px=round(off.apart_px, 1))


def _recovery(evidence: Evidence, reason: str, config) -> Decision:
    """The direct pose is not kept: the feature map's recovered pose is taken, unless it lies off a reliable motion
    prior (a look-alike place: the recovery is refused)."""
    features = evidence.features
    if not features.succeeded:
        return Decision(Outcome.LOST, reason)
    pose = features.pose
    refusal = _off_reliable_prediction(
        evidence, evidence.prior.recovered,
        f"the recovered pose ({pose.inliers} inliers, {pose.found_fraction:.1%} of the points in view)",
        pose.found_fraction >= config.features.recovery.conclusive_found_fraction, config)
    if refusal is not None:
        return Decision(Outcome.LOST, reason, refusal=refusal)
    return Decision(Outcome.RECOVER, reason)


def _off_reliable_prediction(evidence: Evidence, off: Motion | None, whose: str, supported: bool,
                             config) -> str | None:
    """After missed frames, why a pose (``whose``: the recovered one, or a direct one the feature map confirmed; ``off``
    its motion against the prior) is not taken: it lies off the motion the time implies (further than
    ``gap_motion_share`` of the predicted image motion), and that motion has been predictable enough to say so
    (``prior_reliable``). A pose the feature map ``supported`` (a recovery with a conclusive share of the points in
    view, a direct pose it confirmed) is refused only where it stayed behind after a gap as long as a jump: it moved
    less than ``gap_motion_share`` of the predicted motion from the last pose, the signature of direct alignment's lock
    onto the view it left (where the view repeats, the feature map's matches find the same look-alike place). A
    supported pose that moved as far elsewhere is a place recognized, as FDMO's jump back to a sequence's start
    (KITTI played twice: 248 px from the last pose where 177 px were predicted, right). None where it may be
    taken."""
    if not prior_reliable(evidence.prior.error, config):
        return None
    if off is None or not _strays(off, config):
        return None
    intervals_missed = evidence.direct.intervals_missed
    if supported:
        if (intervals_missed < config.fdmo.divergence.sudden_motion_factor
                or off.found_px >= config.fdmo.gap_motion_share * off.predicted_px):
            return None
        whose += f" stayed behind ({off.found_px:.0f} px from the last pose):"
    return (f"{whose} lies {off.apart_px:.0f} px from where the last motion puts the camera after "
            f"{intervals_missed:.0f} frame intervals ({off.predicted_px:.0f} px of motion predicted), and the "
            "motion has been that predictable")


def prior_reliable(error: float | None, config) -> bool:
    """Whether the motion prior predicts where the camera is well enough to judge a pose by: its error over the gap
    (evidence.prior_error) is at most ``fdmo.prior_reliability`` (KITTI and parking's steady motion: 0.01 a frame;
    teddy's handheld: 0.27)."""
    return error is not None and error <= config.fdmo.prior_reliability


def _strays(off: Motion, config) -> bool:
    """The gap rule: the pose lies further from the predicted one than ``gap_motion_share`` of the predicted image
    motion."""
    return off.apart_px > config.fdmo.gap_motion_share * off.predicted_px


# ---------------------------------------------------------------------------------------------- after a recovery


class Next(Enum):
    RESUME = "resume"  # the same window goes on, with Continuation.alignment
    RESTART = "restart"  # the direct map restarts at the recovered pose (refined where Continuation.refined)
    FEATURE_TRACKING = "feature_tracking"  # the frame gets the feature pose; feature tracking takes the next frames


@dataclass(frozen=True)
class Continuation:
    next: Next
    alignment: str | None = None  # RESUME: "direct" (the motion model's) or "retracked" (from the recovered pose)
    why: str = ""  # RESUME: why the window goes on
    refined: bool = False  # the alignment from the recovered pose agrees with the feature map: the pose to go on from
    points: int = 0  # the restart's feature points (at the pose it goes on from)


def after_recovery(evidence: RecoveredEvidence, config) -> Continuation:
    """Back to direct from a recovered pose (FDMO 4.2.2). Where the alignment from the recovered pose ends where the
    motion model's ended (``fdmo.same_optimum_px``), two starts found the same optimum and the same window goes on;
    where it ends elsewhere but fits the images no better, there is no lock to leave: the motion model's alignment goes
    on. Unless the recovery puts the camera elsewhere than the motion model's alignment (it explains under
    ``fdmo.elsewhere_share`` of a conclusive recovery's inliers), which is then not kept. Otherwise the direct map
    restarts at the recovered pose (at the alignment from it where that agrees with the feature map,
    ``fdmo.agreement``) with as many feature depths as a start needs well-triangulated points
    (``init.two_view.min_triangulated``: a restart is a start from the feature map's depths) or more; with fewer, the
    better fit of the converged alignments goes on; with none, feature tracking."""
    fdmo = config.fdmo
    direct, retracked = evidence.direct, evidence.retracked
    elsewhere = (direct is not None and direct.converged
                 and evidence.found_fraction >= config.features.recovery.conclusive_found_fraction
                 and evidence.direct_explained < fdmo.elsewhere_share)
    if direct is not None and direct.converged and retracked.converged:
        if evidence.shift_px <= fdmo.same_optimum_px:
            return Continuation(Next.RESUME, "retracked", "both alignments reached the same optimum")
        if not (retracked.rmse_after < direct.rmse_after or elsewhere):
            return Continuation(Next.RESUME, "direct",
                                "the alignment from the recovered pose fits the images no better than the motion "
                                "model's")
    refined = (retracked is not None and retracked.converged
               and evidence.retracked_explained >= fdmo.agreement)
    points = evidence.restart_points_retracked if refined else evidence.restart_points
    if points >= config.init.two_view.min_triangulated:
        return Continuation(Next.RESTART, refined=refined, points=points)
    converged = [(name, a) for name, a in (("direct", direct), ("retracked", retracked))
                 if a is not None and a.converged and not (name == "direct" and elsewhere)]
    if converged:  # the window's points, however weak here, against depths the feature map has not settled
        name = min(converged, key=lambda named: named[1].rmse_after)[0]
        why = (f"{points} of the feature points in view are seen by {fdmo.min_restart_observations} keyframes or "
               "more: too few to restart from (the better fit of the two alignments goes on)")
        return Continuation(Next.RESUME, name, why, refined, points)
    return Continuation(Next.FEATURE_TRACKING, refined=refined, points=points)
