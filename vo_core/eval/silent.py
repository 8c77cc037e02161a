"""Silent failures: stretches of a run whose scale is not the run's, where the odometry reported nothing.

A monocular run is judged after one Sim(3) alignment, and a stretch at another scale (a wrong start kept, a scale
that collapsed) only raises its ATE. Whether the odometry said something there is what tells a failure a user was
warned of from one that looked like a result. The run's associated poses are cut into consecutive segments; each
is aligned on its own (Umeyama, Sim(3)), and a segment whose scale differs from its map's (the median of its
segments' scales: what most of the map agrees on) by more than
``max_scale_change`` with no reported failure between the start of the segment before it and its last pose is
silent. Each map of a run (after a reinitialization, a new scale) is judged on its own. A segment whose true
motion is too small to carry a scale, or that is no similarity of the truth (its true positions spread less than
``min_spread_ates`` times its own aligned error), is not judged. The settings are the project's own (the real-data issue's definition: 20 %).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vo_core.errors import InputError
from vo_core.eval.align import umeyama
from vo_core.eval.associate import DEFAULT_MAX_DT_S, associate
from vo_core.eval.metrics import maps_of
from vo_core.trajectory import Trajectory


@dataclass(frozen=True)
class SilentConfig:
    segment_poses: int = 50  # the run's associated poses cut into consecutive segments of about this many poses
    max_scale_change: float = 0.2  # a segment's scale over the run's, beyond 1 +- this, is a failure
    min_spread_ates: float = 10.0  # a segment whose true positions spread less than this many of its own aligned
    # errors is not judged


@dataclass(frozen=True)
class Segment:
    start_s: float  # timestamps of its first and last pose
    end_s: float
    scale_ratio: float | None  # its own Sim(3) scale over the whole run's; None where not judged
    reported: bool  # a failure was reported between its first and last pose

    def silent(self, config: SilentConfig) -> bool:
        return (self.scale_ratio is not None and not self.reported
                and abs(self.scale_ratio - 1.0) > config.max_scale_change)


def scale_segments(estimate: Trajectory, ground_truth: Trajectory, reported_s: np.ndarray, map_starts_s: np.ndarray,
                   config: SilentConfig = SilentConfig(), max_dt: float = DEFAULT_MAX_DT_S) -> list[Segment]:
    """The run's segments with their scales against the whole map's and whether a failure was reported in them or
    in the segment before (a scale that changed at a reported failure shows from the next segment on).
    ``reported_s``: the timestamps of the reported failures; ``map_starts_s``: where a new map began (a new scale,
    judged on its own)."""
    segments = []
    for matched, truth in maps_of(*associate(estimate, ground_truth, max_dt), map_starts_s):
        segments += _map_segments(matched, truth, np.asarray(reported_s, float), config)
    return segments


def _map_segments(matched: Trajectory, truth: Trajectory, reported_s: np.ndarray,
                  config: SilentConfig) -> list[Segment]:
    count = max(1, round(len(matched) / config.segment_poses))
    pieces = [rows for rows in np.array_split(np.arange(len(matched)), count) if len(rows) >= 3]
    scales = [_own_scale(matched.positions[rows], truth.positions[rows], config) for rows in pieces]
    judged = [scale for scale in scales if scale is not None and np.isfinite(scale)]
    if not judged:
        return []
    reference = float(np.median(judged))  # the map's scale: what most of its stretches agree on
    segments, previous_start = [], matched.timestamps[0]
    for rows, scale in zip(pieces, scales):
        times = matched.timestamps[rows]
        reported = bool(np.any((reported_s >= previous_start) & (reported_s <= times[-1])))
        previous_start = times[0]
        segments.append(Segment(float(times[0]), float(times[-1]), None if scale is None else scale / reference,
                                reported))
    return segments


def _own_scale(estimate: np.ndarray, truth: np.ndarray, config: SilentConfig) -> float | None:
    """A segment's own Sim(3) scale; None where the segment is no similarity of the truth (its true positions spread
    less than ``min_spread_ates`` times its own aligned error: too little motion for a scale, or a scale that
    changes inside it)."""
    spread = float(np.sqrt(np.mean(np.sum((truth - truth.mean(axis=0)) ** 2, axis=1))))
    try:
        R, t, scale = umeyama(estimate, truth, with_scale=True)
    except InputError:
        return float("inf") if spread > 0 else None  # the estimate stood still where the camera moved
    error = float(np.sqrt(np.mean(np.sum((scale * estimate @ R.T + t - truth) ** 2, axis=1))))
    return scale if spread >= config.min_spread_ates * error else None
