"""Trajectory error metrics, each with the equation it implements.

- ATE, the absolute trajectory error (Sturm et al. 2012, "A Benchmark for the Evaluation of RGB-D SLAM Systems",
  sec. "Evaluation metrics"; Zhang & Scaramuzza 2018, "A Tutorial on Quantitative Trajectory Evaluation").
- RPE, the relative pose error over a delta in frames or metres (Sturm et al. 2012, the same section).
- The drifts of the TUM monoVO benchmark (Engel, Usenko & Cremers 2016, "A Photometrically Calibrated
  Benchmark For Monocular Visual Odometry", sec. "Evaluation Metrics"), also at the end of each loop of a
  sequence played several times in a row (FDMO sec. 5.3.1).
- The frame-drop error of FDMO (Younes, Asmar & Zelek 2019, sec. 5.3.2).

``evaluate`` combines them into the JSON-ready dictionary that ``metrics.json`` and ``fdmo eval`` show.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from vo_core.errors import InputError
from vo_core.eval.align import Alignment, fit_alignment
from vo_core.eval.associate import DEFAULT_MAX_DT_S, associate, associate_timestamps
from vo_core.geometry.lie import sim3_inverse, sim3_scale
from vo_core.trajectory import Trajectory

RPE_UNITS = ("frames", "m")


@dataclass(frozen=True)
class EvalConfig:
    """What ``evaluate`` computes beyond the alignment."""

    # RPE over consecutive matched poses (Sturm et al. 2012: delta = 1 frame measures the drift per frame; a delta
    # in metres compares sequences recorded at different rates).
    rpe_delta: float = 1
    rpe_unit: str = "frames"
    # TUM monoVO drifts (Engel et al. 2016) need ground truth over a start and an end segment. Ground
    # truth that only covers both ends (a gap between its poses this many times longer than their median
    # spacing, as in TUM monoVO) gives the segments itself. Over ground truth that covers the whole run, the
    # segments are this share of the matched poses each, if set; unset, no drifts are reported there, since
    # short segments with little motion give ill-conditioned Sim(3)s (the paper asks for segments with
    # "a significant amount of camera translation").
    drift_gap_factor: float = 10.0
    drift_segment_fraction: float | None = None
    # The Sim(3) of a segment needs a few positions that span a volume (Umeyama 1991); fewer: no drift reported.
    drift_min_segment_poses: int = 3


# ------------------------------------------------------------------------------------------ statistics


def error_statistics(errors: np.ndarray) -> dict[str, float]:
    """rmse, mean, median, std, min and max of a set of errors, the statistics evo and the TUM tools print."""
    errors = np.asarray(errors, dtype=float)
    return {
        "rmse": float(np.sqrt(np.mean(errors**2))),
        "mean": float(np.mean(errors)),
        "median": float(np.median(errors)),
        "std": float(np.std(errors)),
        "min": float(np.min(errors)),
        "max": float(np.max(errors)),
    }


def rotation_angles(rotations: np.ndarray) -> np.ndarray:
    """(N,) angles (rad) of (N, 3, 3) rotations, |log(R)| (accurate near 0 and pi, unlike acos((tr R - 1)/2))."""
    return Rotation.from_matrix(rotations).magnitude()


# ------------------------------------------------------------------------------------------------- ATE


def ate_errors(aligned_estimate: Trajectory, ground_truth: Trajectory) -> np.ndarray:
    """(N,) translational ATE of matched poses already aligned: ||trans(F_i)|| with F_i = Q_i^-1 S P_i, i.e.
    ||q_i - (s R p_i + t)|| (Sturm et al. 2012); ATE_rmse = sqrt(1/n sum_i ||trans(F_i)||^2) is what the TUM
    benchmark reports."""
    return np.linalg.norm(ground_truth.positions - aligned_estimate.positions, axis=1)


def ate_per_map(estimate: Trajectory, ground_truth: Trajectory, map_starts_s: np.ndarray,
                max_dt: float = DEFAULT_MAX_DT_S, min_poses: int = 3) -> tuple[float, int, int]:
    """(ATE_rmse, maps, poses) of a run made of separate maps: the poses from each of ``map_starts_s`` (a new map
    began, at a scale and place of its own) to the next are aligned by a Sim(3) of their own, as ORB-SLAM3's maps are
    evaluated one by one, and the RMSE taken over all of them: sqrt(1/n sum_m sum_i ||q_i - (s_m R_m p_i + t_m)||^2).
    A map with fewer than ``min_poses`` matched poses has no Sim(3) and is left out. One map: the ATE."""
    errors = [ate_errors(fit_alignment(piece, truth, "sim3").apply(piece), truth)
              for piece, truth in maps_of(*associate(estimate, ground_truth, max_dt), map_starts_s)
              if len(piece) >= min_poses]
    if not errors:
        return float("nan"), 0, 0
    squared = np.concatenate(errors) ** 2
    return float(np.sqrt(squared.mean())), len(errors), len(squared)


def maps_of(matched: Trajectory, truth: Trajectory, map_starts_s: np.ndarray) -> list[tuple[Trajectory, Trajectory]]:
    """Associated poses (``associate``'s pair) cut where each new map began: (estimate, truth) per map, in time."""
    boundaries = np.searchsorted(matched.timestamps, np.asarray(map_starts_s, float))
    return [(matched.subset(rows), truth.subset(rows)) for rows in np.split(np.arange(len(matched)), boundaries)]


# ------------------------------------------------------------------------------------------------- RPE


def rpe_pairs(ground_truth: Trajectory, delta: float, unit: str) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j) of the relative poses: every i with j = i + delta frames, or with j the first pose at
    least ``delta`` metres of ground-truth path after i (evo's ``all_pairs`` for frames)."""
    n = len(ground_truth)
    if unit == "frames":
        step = int(delta)
        if step < 1:
            raise InputError(f"RPE delta must be at least 1 frame, not {delta}")
        first = np.arange(max(n - step, 0))
        return first, first + step
    if unit != "m":
        raise InputError(f"unknown RPE unit '{unit}' (known: {', '.join(RPE_UNITS)})")
    steps = np.linalg.norm(np.diff(ground_truth.positions, axis=0), axis=1)
    path = np.concatenate([[0.0], np.cumsum(steps)])  # metres travelled up to each pose
    second = np.searchsorted(path, path + delta, side="left")
    first = np.flatnonzero(second < n)
    return first, second[first]


def rpe_errors(
    aligned_estimate: Trajectory, ground_truth: Trajectory, first: np.ndarray, second: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(translation m, rotation rad) of E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) (Sturm et al. 2012) for each
    pair. The estimate must already carry the alignment's scale; its rotation and translation do not matter."""
    estimated_motion = np.linalg.inv(aligned_estimate.poses[first]) @ aligned_estimate.poses[second]
    true_motion = np.linalg.inv(ground_truth.poses[first]) @ ground_truth.poses[second]
    errors = np.linalg.inv(true_motion) @ estimated_motion
    return np.linalg.norm(errors[:, :3, 3], axis=1), rotation_angles(errors[:, :3, :3])


# ------------------------------------------------------------------------------------ TUM monoVO drifts


@dataclass(frozen=True)
class Drift:
    """The drifts of Engel et al. 2016 from the alignments S_s and S_e of the start and end segments."""

    alignment_error: float  # e_align (m)
    rotation_drift_deg: float  # e_r: the angle of T_drift = S_e S_s^-1
    scale_drift: float  # e_s: the scale of T_drift (1 = none; e_s and 1/e_s are the same amount)
    translation_drift: float  # e_t: ||translation(T_drift)|| (m)
    start: Alignment = field(repr=False)
    end: Alignment = field(repr=False)

    def as_dict(self) -> dict[str, float]:
        return {
            "alignment_error": self.alignment_error,
            "rotation_drift_deg": self.rotation_drift_deg,
            "scale_drift": self.scale_drift,
            "translation_drift": self.translation_drift,
        }


def tum_mono_drift(
    estimate: Trajectory, start: tuple[Trajectory, Trajectory], end: tuple[Trajectory, Trajectory]
) -> Drift:
    """Drifts of a whole ``estimate`` from its matched (estimate, ground truth) ``start`` and ``end`` segments.

    S_s = argmin_S sum_{i in start} ||S p_i - p^_i||^2 and S_e likewise over the end (Sim(3)); the
    accumulated drift is T_drift = S_e S_s^-1, and e_align = sqrt(1/n sum_{i=1..n} ||S_s p_i - S_e p_i||^2)
    over all n estimated positions: how far apart the two alignments put the trajectory, which weighs
    scale, rotation and translation drift together. All n, not only the segments' frames: the paper's p_1..p_n
    are the tracked positions of frames 1..n with S, E subsets of them, and the benchmark's own evaluation
    (efficientEvalDrift.m of the TUM monoVO tools) divides by the number of estimated positions."""
    S_start, S_end = fit_alignment(*start, method="sim3"), fit_alignment(*end, method="sim3")
    T_drift = S_end.transform @ sim3_inverse(S_start.transform)
    scale = sim3_scale(T_drift)
    gap = S_start.apply(estimate).positions - S_end.apply(estimate).positions
    return Drift(
        alignment_error=float(np.sqrt(np.mean(np.sum(gap**2, axis=1)))),
        rotation_drift_deg=float(np.degrees(rotation_angles(T_drift[None, :3, :3] / scale)[0])),
        scale_drift=scale,
        translation_drift=float(np.linalg.norm(T_drift[:3, 3])),
        start=S_start,
        end=S_end,
    )


def drift_segments(
    truth_timestamps: np.ndarray, matched_timestamps: np.ndarray, config: EvalConfig
) -> tuple[np.ndarray, np.ndarray] | None:
    """Index arrays of the start and end segments among the matched poses (``matched_timestamps``, those of the
    ground truth): before and after the longest gap of a ground truth that covers only both ends (TUM monoVO),
    else the first and last ``drift_segment_fraction`` of them; None when neither applies. The gap is looked
    for in the ground truth itself: a gap in the estimate (lost tracking, dropped frames) is not a segment."""
    gap_end = ground_truth_gap_end(truth_timestamps, config)
    if gap_end is not None:
        after = matched_timestamps >= gap_end
        return np.flatnonzero(~after), np.flatnonzero(after)
    if config.drift_segment_fraction is None:
        return None
    n = len(matched_timestamps)
    size = int(round(config.drift_segment_fraction * n))
    return np.arange(min(size, n)), np.arange(max(n - size, 0), n)


def ground_truth_gap_end(truth_timestamps: np.ndarray, config: EvalConfig) -> float | None:
    """Where a ground truth that covers only a start and an end segment (TUM monoVO's groundtruthSync.txt) resumes
    after its longest gap, a gap ``drift_gap_factor`` times longer than its median spacing; None for ground truth
    that covers the whole run."""
    spacing = np.diff(truth_timestamps)
    if len(spacing) and spacing.max() > config.drift_gap_factor * np.median(spacing):
        return float(truth_timestamps[int(np.argmax(spacing)) + 1])
    return None


def loop_drifts(
    estimate: Trajectory,
    ground_truth: Trajectory,
    loops: list[tuple[float, float]],
    config: EvalConfig = EvalConfig(),
    max_dt: float = DEFAULT_MAX_DT_S,
) -> list[Drift | None]:
    """The drifts at the end of each loop of a sequence played several times in a row (FDMO sec. 5.3.1's two-loop
    experiment, after Engel et al. 2016). ``loops`` are the time spans (first, last) of each loop's frames.

    Each loop's start and end segments are found within it as ``evaluate`` finds them in a whole run
    (``drift_segments``). At the end of loop k, S_s is fitted on the start segment of the FIRST loop and S_e on
    the end segment of loop k, and e_align runs over the whole estimate up to the end of loop k: so the drift
    at the end of loop 2 holds the first loop's drift, the second's and the error of the jump between them.
    None for a loop in which a segment has too few poses (or does not move)."""
    segments = [_segments(estimate.within(first, last), ground_truth.within(first, last), config, max_dt)
                for first, last in loops]
    return [
        None if segments[0] is None or segment is None
        else _drift_between(estimate.within(-np.inf, last), segments[0][0], segment[1])
        for (_, last), segment in zip(loops, segments)
    ]


def _segments(estimate: Trajectory, ground_truth: Trajectory, config: EvalConfig, max_dt: float):
    """The matched (estimate, ground truth) poses of the start and the end segment of a run; None without them."""
    try:
        matched_estimate, matched_truth = associate(estimate, ground_truth, max_dt)
    except InputError:  # no estimated pose near the ground truth: the run was lost there
        return None
    return _matched_segments(matched_estimate, matched_truth, ground_truth.timestamps, config)


def _matched_segments(matched_estimate: Trajectory, matched_truth: Trajectory, truth_timestamps: np.ndarray,
                      config: EvalConfig):
    segments = drift_segments(truth_timestamps, matched_truth.timestamps, config)
    if segments is None or min(len(segment) for segment in segments) < config.drift_min_segment_poses:
        return None
    return tuple((matched_estimate.subset(segment), matched_truth.subset(segment)) for segment in segments)


def _drift_between(estimate: Trajectory, start, end) -> Drift | None:
    try:
        return tum_mono_drift(estimate, start, end)
    except InputError:  # a segment in which the camera does not move has no Sim(3)
        return None


# ------------------------------------------------------------------------------------- frame-drop error


@dataclass(frozen=True)
class FrameDropError:
    """FDMO sec. 5.3.2: the motion between the frames F_i before and F_j after a drop, estimated and true, and
    100 |measured - true| / true for its translation distance and rotation angle."""

    translation: float  # ||F_i - F_j|| estimated, in ground-truth units (see frame_drop_error)
    true_translation: float
    rotation_deg: float
    true_rotation_deg: float

    @property
    def translation_percent(self) -> float:
        return _percent_error(self.translation, self.true_translation)

    @property
    def rotation_percent(self) -> float:
        return _percent_error(self.rotation_deg, self.true_rotation_deg)

    def as_dict(self) -> dict[str, float]:
        return {
            "translation": self.translation,
            "true_translation": self.true_translation,
            "translation_percent": self.translation_percent,
            "rotation_deg": self.rotation_deg,
            "true_rotation_deg": self.true_rotation_deg,
            "rotation_percent": self.rotation_percent,
        }


def frame_drop_error(
    estimate_before: np.ndarray,
    estimate_after: np.ndarray,
    truth_before: np.ndarray,
    truth_after: np.ndarray,
    scale: float = 1.0,
) -> FrameDropError:
    """The error of the motion over a frame drop, from the 4x4 T_world_cam of the frames before and after it.

    Translation = ||F_i - F_j|| between camera centres; Rotation = cos^-1(2 <q_i, q_j>^2 - 1), the geodesic
    angle between the unit quaternions, i.e. the angle of R_i^T R_j (FDMO sec. 5.3.2). A monocular estimate has
    no metric scale, so its distance is multiplied by ``scale``: pass the Sim(3) alignment scale of the whole
    run (``Alignment.scale``). One global scale, rather than one fitted around the drop, keeps the scale drift
    the drop caused inside the error, which is what the experiment measures."""
    return FrameDropError(
        translation=scale * float(np.linalg.norm(estimate_after[:3, 3] - estimate_before[:3, 3])),
        true_translation=float(np.linalg.norm(truth_after[:3, 3] - truth_before[:3, 3])),
        rotation_deg=_quaternion_angle_deg(estimate_before[:3, :3], estimate_after[:3, :3]),
        true_rotation_deg=_quaternion_angle_deg(truth_before[:3, :3], truth_after[:3, :3]),
    )


def frame_drop_error_at(
    estimate: Trajectory,
    ground_truth: Trajectory,
    before_s: float,
    after_s: float,
    scale: float = 1.0,
    max_dt: float = DEFAULT_MAX_DT_S,
) -> FrameDropError:
    """``frame_drop_error`` of the frames at ``before_s`` and ``after_s`` (the last frame before a drop and the
    first after it), each pose the one of its trajectory nearest in time within ``max_dt``."""
    times = (before_s, after_s)
    poses = [_pose_at(trajectory, time, max_dt) for trajectory in (estimate, ground_truth) for time in times]
    return frame_drop_error(*poses, scale=scale)


def _pose_at(trajectory: Trajectory, time_s: float, max_dt: float) -> np.ndarray:
    match = associate_timestamps(np.array([time_s]), trajectory.timestamps, max_dt)
    if len(match) == 0:
        raise InputError(f"no pose within {max_dt} s of {time_s:.6f} s")
    return trajectory.poses[match.second[0]]


def _quaternion_angle_deg(R_i: np.ndarray, R_j: np.ndarray) -> float:
    """cos^-1(2 <q_i, q_j>^2 - 1) in degrees (FDMO sec. 5.3.2); the sign of q does not matter."""
    q_i, q_j = Rotation.from_matrix(np.stack([R_i, R_j])).as_quat()
    cosine = np.clip(2.0 * float(q_i @ q_j) ** 2 - 1.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosine)))


def _percent_error(measured: float, truth: float) -> float:
    """100 |measured - truth| / truth; infinite when the truth is 0 (no motion to compare with)."""
    if truth == 0.0:
        return 0.0 if measured == 0.0 else float("inf")
    return 100.0 * abs(measured - truth) / truth


# -------------------------------------------------------------------------------------------- evaluate


def evaluate(
    estimate: Trajectory,
    ground_truth: Trajectory,
    align: str = "sim3",
    max_dt: float = DEFAULT_MAX_DT_S,
    config: EvalConfig = EvalConfig(),
) -> dict[str, Any]:
    """All metrics of ``estimate`` against ``ground_truth`` as a JSON-serializable dict.

    Poses are matched by timestamp (``max_dt`` s, one-to-one), the estimate aligned (``align``: "sim3", "se3" or
    "none") on all matched positions, then: ATE statistics (m), RPE statistics (translation m, rotation deg),
    and the TUM monoVO drifts where the ground truth (or ``config``) gives start and end segments."""
    matched_estimate, matched_truth = associate(estimate, ground_truth, max_dt)
    alignment = fit_alignment(matched_estimate, matched_truth, align)
    aligned = alignment.apply(matched_estimate)
    first, second = rpe_pairs(matched_truth, config.rpe_delta, config.rpe_unit)
    result: dict[str, Any] = {
        "estimated_poses": len(estimate),
        "ground_truth_poses": len(ground_truth),
        "matched_poses": len(matched_estimate),
        "max_dt": max_dt,
        "align": align,
        "scale": alignment.scale,
        "alignment": alignment.transform.tolist(),
        "ate": error_statistics(ate_errors(aligned, matched_truth)),
        "rpe": _rpe_summary(aligned, matched_truth, first, second, config),
    }
    drift = _drift(estimate, ground_truth, matched_estimate, matched_truth, config)
    if drift is not None:
        result["drift"] = drift.as_dict()
    return result


def _rpe_summary(aligned, matched_truth, first, second, config: EvalConfig) -> dict[str, Any]:
    summary: dict[str, Any] = {"delta": config.rpe_delta, "unit": config.rpe_unit, "pairs": len(first)}
    if len(first):
        translation, rotation = rpe_errors(aligned, matched_truth, first, second)
        summary["translation"] = error_statistics(translation)
        summary["rotation_deg"] = error_statistics(np.degrees(rotation))
    return summary


def _drift(estimate, ground_truth, matched_estimate, matched_truth, config: EvalConfig) -> Drift | None:
    segments = _matched_segments(matched_estimate, matched_truth, ground_truth.timestamps, config)
    return None if segments is None else _drift_between(estimate, *segments)
