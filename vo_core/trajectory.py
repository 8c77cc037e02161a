"""Timestamped poses: the one trajectory type used for estimates and ground truth alike.

Poses are ``T_world_cam`` (camera-to-world, 4x4); timestamps are in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Trajectory:
    timestamps: np.ndarray  # (N,) seconds, strictly increasing
    poses: np.ndarray  # (N, 4, 4) T_world_cam

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=float).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=float).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise ValueError(f"{len(self.timestamps)} timestamps but {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) camera centres in the world frame."""
        return self.poses[:, :3, 3]

    def subset(self, indices: np.ndarray) -> "Trajectory":
        return Trajectory(self.timestamps[indices], self.poses[indices])
