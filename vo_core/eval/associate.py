"""Timestamp association of two trajectories, as TUM RGB-D's associate.py (Sturm et al. 2012) and evo do it.

Every pair of timestamps (a_i, b_j) with |a_i - (b_j + offset)| <= max_dt is a candidate; candidates are taken
in order of increasing time difference, each timestamp at most once. The result is one-to-one, and for
trajectories sampled faster than 2 * max_dt it is each pose's nearest neighbour.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vo_core.errors import InputError
from vo_core.trajectory import Trajectory

DEFAULT_MAX_DT_S = 0.02  # TUM RGB-D associate.py's --max_difference


@dataclass(frozen=True)
class Association:
    """Indices of matched poses: ``first[k]`` of the first trajectory goes with ``second[k]`` of the second,
    in increasing time."""

    first: np.ndarray
    second: np.ndarray

    def __len__(self) -> int:
        return len(self.first)


def associate_timestamps(
    first: np.ndarray, second: np.ndarray, max_dt: float = DEFAULT_MAX_DT_S, offset: float = 0.0
) -> Association:
    """One-to-one nearest-timestamp matches of two increasing timestamp arrays; ``offset`` is added to ``second``."""
    first = np.asarray(first, dtype=float)
    shifted = np.asarray(second, dtype=float) + offset
    # Candidates: for each first[i], the window of second within max_dt (both arrays are sorted).
    lower = np.searchsorted(shifted, first - max_dt, side="left")
    upper = np.searchsorted(shifted, first + max_dt, side="right")
    counts = upper - lower
    candidates_i = np.repeat(np.arange(len(first)), counts)
    candidates_j = np.repeat(lower - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())
    differences = np.abs(first[candidates_i] - shifted[candidates_j])
    order = np.lexsort((candidates_j, candidates_i, differences))  # smallest difference first, ties stable
    used_first = np.zeros(len(first), dtype=bool)
    used_second = np.zeros(len(shifted), dtype=bool)
    matches = []
    for i, j in zip(candidates_i[order], candidates_j[order]):
        if not used_first[i] and not used_second[j]:
            used_first[i] = used_second[j] = True
            matches.append((i, j))
    matches.sort()
    pairs = np.array(matches, dtype=int).reshape(-1, 2)
    return Association(pairs[:, 0], pairs[:, 1])


def associate(
    estimate: Trajectory, ground_truth: Trajectory, max_dt: float = DEFAULT_MAX_DT_S, offset: float = 0.0
) -> tuple[Trajectory, Trajectory]:
    """The matched poses of both trajectories, pose k of one with pose k of the other; ``offset`` (s) is added
    to the ground truth's timestamps for the matching only. Raises InputError when nothing matches."""
    matches = associate_timestamps(estimate.timestamps, ground_truth.timestamps, max_dt, offset)
    if len(matches) == 0:
        raise InputError(
            f"no estimated timestamp within {max_dt} s of a ground-truth one (estimate "
            f"{_span(estimate)}, ground truth {_span(ground_truth)}, offset {offset} s)"
        )
    return estimate.subset(matches.first), ground_truth.subset(matches.second)


def _span(trajectory: Trajectory) -> str:
    if len(trajectory) == 0:
        return "empty"
    return f"{trajectory.timestamps[0]:.3f}..{trajectory.timestamps[-1]:.3f} s"
