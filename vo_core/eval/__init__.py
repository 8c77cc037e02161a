"""Trajectory evaluation: timestamp association, Umeyama alignment, ATE, RPE, TUM monoVO drifts (also at the end
of each loop of a sequence played several times) and the FDMO frame-drop error. Depends on geometry and
trajectory only; the CLI and the benchmarks combine it with runs."""

from vo_core.eval.align import ALIGNMENTS, Alignment, fit_alignment, umeyama
from vo_core.eval.associate import DEFAULT_MAX_DT_S, Association, associate, associate_timestamps
from vo_core.eval.metrics import (
    Drift,
    EvalConfig,
    FrameDropError,
    ate_errors,
    ate_per_map,
    drift_segments,
    error_statistics,
    evaluate,
    frame_drop_error,
    frame_drop_error_at,
    ground_truth_gap_end,
    loop_drifts,
    rpe_errors,
    rpe_pairs,
    tum_mono_drift,
)

__all__ = [
    "ALIGNMENTS",
    "DEFAULT_MAX_DT_S",
    "Alignment",
    "Association",
    "Drift",
    "EvalConfig",
    "FrameDropError",
    "associate",
    "associate_timestamps",
    "ate_errors",
    "ate_per_map",
    "drift_segments",
    "error_statistics",
    "evaluate",
    "fit_alignment",
    "frame_drop_error",
    "frame_drop_error_at",
    "ground_truth_gap_end",
    "loop_drifts",
    "rpe_errors",
    "rpe_pairs",
    "tum_mono_drift",
    "umeyama",
]
