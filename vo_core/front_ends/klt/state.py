"""The pipeline's state, the paper's S^i = (P^i, X^i, C^i, F^i, T^i) (paper 003 II-B, eq. 1), plus keyframes.

Every corner followed by KLT is a row of ``Tracks`` with a point id. Its id has a world position in
``Landmarks`` once triangulated: those rows are the keypoints P with their landmarks X. The other rows are
the candidates C, with their first observation F (``first_uv``) and the keyframe whose pose is T
(``first_keyframe``). Candidates are born at keyframes, so T is always a keyframe pose, which the bundle
adjustment keeps up to date, and F is a keyframe observation the adjustment can use once the candidate
becomes a landmark.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

INITIAL_CAPACITY = 4096  # point ids before the first growth


class Landmarks:
    """World positions indexed by point id; ids are handed out for candidates too and become landmarks when
    a position is set. Storage grows by doubling, so handing out ids stays cheap on long sequences."""

    def __init__(self) -> None:
        self.count = 0
        self._positions = np.zeros((INITIAL_CAPACITY, 3))
        self._alive = np.zeros(INITIAL_CAPACITY, bool)

    def new_ids(self, count: int) -> np.ndarray:
        needed = self.count + count
        if needed > len(self._positions):
            capacity = max(needed, 2 * len(self._positions))
            self._positions = np.vstack([self._positions, np.zeros((capacity - len(self._positions), 3))])
            self._alive = np.concatenate([self._alive, np.zeros(capacity - len(self._alive), bool)])
        ids = np.arange(self.count, needed)
        self.count = needed
        return ids

    @property
    def positions(self) -> np.ndarray:
        """(count, 3), indexed by id; rows of candidates are meaningless."""
        return self._positions[: self.count]

    def set(self, ids: np.ndarray, positions: np.ndarray) -> None:
        self._positions[ids] = positions
        self._alive[ids] = True

    def cull(self, ids: np.ndarray) -> None:
        self._alive[ids] = False

    def is_landmark(self, ids: np.ndarray) -> np.ndarray:
        return self._alive[ids]

    @property
    def world_points(self) -> np.ndarray:
        return self._positions[: self.count][self._alive[: self.count]]


@dataclass
class Tracks:
    """Corners followed from frame to frame (structure of arrays, one row per corner)."""

    ids: np.ndarray  # (N,) point ids in Landmarks
    uv: np.ndarray  # (N, 2) position in the current frame
    first_uv: np.ndarray  # (N, 2) F: position in the keyframe where the corner was detected
    first_keyframe: np.ndarray  # (N,) frame index of that keyframe, whose pose is T
    keyframe_uv: np.ndarray  # (N, 2) position in the newest keyframe, for the keyframe parallax test

    @classmethod
    def empty(cls) -> "Tracks":
        return cls.born(np.zeros(0, int), np.zeros((0, 2), np.float32), keyframe_index=-1)

    @classmethod
    def born(cls, ids: np.ndarray, uv: np.ndarray, keyframe_index: int) -> "Tracks":
        """New corners detected in keyframe ``keyframe_index``."""
        uv = np.asarray(uv, np.float32).reshape(-1, 2)
        return cls(ids, uv, uv.copy(), np.full(len(ids), keyframe_index), uv.copy())

    def __len__(self) -> int:
        return len(self.ids)

    def select(self, keep: np.ndarray) -> "Tracks":
        return Tracks(self.ids[keep], self.uv[keep], self.first_uv[keep], self.first_keyframe[keep],
                      self.keyframe_uv[keep])

    def extend(self, other: "Tracks") -> "Tracks":
        return Tracks(*(np.concatenate([a, b]) for a, b in zip(self._columns(), other._columns())))

    def _columns(self) -> tuple[np.ndarray, ...]:
        return self.ids, self.uv, self.first_uv, self.first_keyframe, self.keyframe_uv


@dataclass
class Keyframe:
    """A frame kept for the bundle adjustment: its pose and the corners (landmarks and candidates) it saw."""

    frame_index: int
    T_world_cam: np.ndarray
    ids: np.ndarray  # (K,) point ids observed
    uv: np.ndarray  # (K, 2) where
