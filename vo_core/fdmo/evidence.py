"""What each half says about a frame the divergence test did not trust, as plain numbers (FDMO Fig. 2).

``decide.py`` judges only these; ``gather`` is the one place that asks the halves for them. Nothing here decides:
a measure that is not taken (no feature pose, no missed frames) is None, and the thresholds live in decide.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vo_core.direct.divergence import Judgement, Verdict
from vo_core.direct.odometry import DirectTracking
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.motion_model import extrapolate
from vo_core.geometry.multiview import image_motion_px


@dataclass(frozen=True)
class DirectEvidence:
    """What direct tracking says: the divergence test's verdict and reason, and the alignment's fit."""

    verdict: Verdict
    reason: str  # the divergence test's (decide.py appends why a pose is not kept)
    jump: bool = False  # suspect because the camera may have jumped (missed frames, a sudden motion)
    saturated: bool = False  # the direct pose leaves most of the residuals beyond the cutoff (Judgement.saturated)
    good_enough: bool = True  # a hypothesis came within DSO's retrack threshold of the last frame's RMSE
    rmse_after: float = float("nan")
    last_rmse: float = float("nan")
    intervals_missed: float | None = None  # frame intervals since the last tracked frame, where frames were missed


@dataclass(frozen=True)
class FeaturePose:
    """The feature map's pose for the frame (an accepted recovery, or the best candidate of one that fell short)."""

    inliers: int
    found_fraction: float  # inliers per map point in view
    # The share of its inlier matches the direct pose explains; None where the pose has fewer inliers than a RANSAC
    # needs (features.recovery.min_ransac_inliers), or the direct pose is not suspect (diverged or lost): they are
    # then not compared.
    explained: float | None = None


@dataclass(frozen=True)
class Search:
    """The feature map's search around the system's estimate, where it ran and failed: what it found of what it
    expected in view there."""

    inliers: int
    in_view: int

    @property
    def found_fraction(self) -> float:
        return self.inliers / max(self.in_view, 1)


@dataclass(frozen=True)
class FeatureEvidence:
    """What the feature map says about the frame."""

    succeeded: bool  # its recovery gave a pose it accepts
    pose: FeaturePose | None = None
    feature_deprived: bool = False  # too few ORB features in the frame to say anything
    around_estimate: Search | None = None


@dataclass(frozen=True)
class Motion:
    """A pose against the motion prior after missed frames, in image motion of the reference's points from the last
    posed frame (pixels): what the prior predicts, what the pose moved, and how far apart the two poses are."""

    predicted_px: float
    found_px: float
    apart_px: float


@dataclass(frozen=True)
class PriorEvidence:
    """The motion prior: the last motion kept up over the time that passed."""

    # The median relative error of its one-frame predictions over the recent posed frames, times the square root of
    # the intervals missed (a random walk over the gap); None without missed frames or with too few posed frames.
    error: float | None = None
    direct: Motion | None = None  # the direct pose against it (a suspect frame after missed frames)
    recovered: Motion | None = None  # the recovered pose against it (a recovery after missed frames)


@dataclass(frozen=True)
class Evidence:
    direct: DirectEvidence
    features: FeatureEvidence
    prior: PriorEvidence = PriorEvidence()


def prior_error(posed: list[tuple[float, np.ndarray]], intervals_missed: float | None,
                min_prior_frames: int) -> float | None:
    """How well the last motion, kept up over the frames missed, predicts where the camera is: the median relative
    error of its one-frame predictions over ``posed`` (how far each frame's position was from the one its two
    predecessors predicted, over how far it moved), grown as a random walk over the gap (times the square root of
    the intervals missed). None without missed frames or with fewer than ``min_prior_frames`` such predictions."""
    if intervals_missed is None:
        return None
    errors = []
    for (t2, T2), (t1, T1), (t0, T0) in zip(posed, posed[1:], posed[2:]):
        moved = np.linalg.norm(T0[:3, 3] - T1[:3, 3])
        if moved > 0:
            predicted = extrapolate([(t2, T2), (t1, T1)], t0)
            errors.append(np.linalg.norm(predicted[:3, 3] - T0[:3, 3]) / moved)
    if len(errors) < min_prior_frames:
        return None
    return float(np.median(errors)) * np.sqrt(intervals_missed)


def against_prior(camera: PinholeCamera, tracking: DirectTracking, posed: list[tuple[float, np.ndarray]],
                  predicted: np.ndarray | None, T_world_cam: np.ndarray) -> Motion | None:
    """After missed frames, how a pose for the frame compares with the prior's ``predicted`` pose, in image motion of
    the reference's points from the last posed frame; None without missed frames or a last motion."""
    if tracking.intervals_missed is None or predicted is None or len(posed) < 2:
        return None
    points, T_world_last = tracking.reference.points_world(), posed[-1][1]
    return Motion(image_motion_px(camera, points, T_world_last, predicted),
                  image_motion_px(camera, points, T_world_last, T_world_cam),
                  image_motion_px(camera, points, predicted, T_world_cam))


def gather(features, camera: PinholeCamera, tracking: DirectTracking, judgement: Judgement, outcome,
           posed: list[tuple[float, np.ndarray]], predicted: np.ndarray | None, config) -> Evidence:
    """The evidence about a frame direct tracking did not trust: ``judgement`` of ``tracking``, the feature map's
    ``outcome`` for the frame (features.recover), and the motion prior (``posed``, the map's last poses, and the pose
    they ``predicted`` for the frame). ``features`` (the feature half) is asked how much of its pose's matches the
    direct pose explains; ``config``: the system's."""
    pose = outcome.pose
    suspect = judgement.verdict is Verdict.SUSPECT  # only a suspect direct pose (converged) is compared
    feature_pose = None
    if pose is not None:
        explained = None
        if suspect and pose.num_inliers >= config.features.recovery.min_ransac_inliers:
            explained = features.explained(pose, tracking.T_world_cam, outcome.features)
        feature_pose = FeaturePose(pose.num_inliers, pose.found_fraction, explained)
    around = outcome.around_estimate
    feature_evidence = FeatureEvidence(
        outcome.succeeded, feature_pose, outcome.feature_deprived,
        None if around is None else Search(around.num_inliers, around.in_view))
    prior = PriorEvidence(
        prior_error(posed, tracking.intervals_missed, config.fdmo.min_prior_frames),
        against_prior(camera, tracking, posed, predicted, tracking.T_world_cam) if suspect else None,
        against_prior(camera, tracking, posed, predicted, outcome.T_world_cam) if outcome.succeeded else None)
    direct = DirectEvidence(judgement.verdict, judgement.reason, judgement.jump, judgement.saturated,
                            tracking.good_enough, tracking.rmse_after, tracking.last_rmse, tracking.intervals_missed)
    return Evidence(direct, feature_evidence, prior)


# ---------------------------------------------------------------------------------------------- after a recovery


@dataclass(frozen=True)
class Alignment:
    """A direct alignment of the frame: whether it converged, and its fit."""

    converged: bool
    rmse_after: float


@dataclass(frozen=True)
class RecoveredEvidence:
    """What the halves say about going back to direct from a recovered pose (FDMO 4.2.2): the motion model's
    alignment (``direct``) and the one from the recovered pose (``retracked``), None where there was no direct
    alignment (feature tracking, a scale jump, an old map after a reinitialization); how they compare with the
    recovery; and the feature points a restart would get its depths from."""

    found_fraction: float  # the recovery's inliers per map point in view
    direct: Alignment | None = None
    retracked: Alignment | None = None
    direct_explained: float | None = None  # the share of the recovery's inliers the motion model's alignment explains
    retracked_explained: float | None = None  # ... and the one from the recovered pose
    # How far apart the two alignments put the recovery's inliers (median pixels), where both converged.
    shift_px: float | None = None
    # Feature points in view, observed by fdmo.min_restart_observations keyframes or more, at the recovered pose and
    # at the alignment from it (where it converged).
    restart_points: int = 0
    restart_points_retracked: int | None = None


def gather_recovered(features, outcome, direct: DirectTracking | None, retracked: DirectTracking | None,
                     config) -> RecoveredEvidence:
    """The evidence about going back to direct from ``outcome``'s recovered pose: the feature half is asked how much of
    the recovery each alignment explains, how far apart they put its inliers, and which of its points a restart could
    take depths from at either pose."""
    pose, frame = outcome.pose, outcome.features
    min_observations = config.fdmo.min_restart_observations

    def points_at(T_world_cam: np.ndarray) -> int:
        return len(features.depths_in_view(pose, T_world_cam, min_observations)[0])

    both = direct is not None and direct.converged and retracked.converged
    converged_retracked = retracked is not None and retracked.converged
    return RecoveredEvidence(
        pose.found_fraction,
        None if direct is None else Alignment(direct.converged, direct.rmse_after),
        None if retracked is None else Alignment(retracked.converged, retracked.rmse_after),
        features.explained(pose, direct.T_world_cam, frame) if direct is not None and direct.converged else None,
        features.explained(pose, retracked.T_world_cam, frame) if converged_retracked else None,
        features.reprojection_shift(pose, direct.T_world_cam, retracked.T_world_cam) if both else None,
        points_at(outcome.T_world_cam),
        points_at(retracked.T_world_cam) if converged_retracked else None)
