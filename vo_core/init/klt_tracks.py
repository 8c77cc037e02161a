"""Feature tracks of the initializer (paper 004 section 3.1): corners detected in the reference frame and
followed frame to frame by pyramidal Lucas-Kanade, each step checked forward and backward (1 -> 2 -> 1).

A track that fails one step is dropped for good, so every surviving track has a position in every frame of
the window: the geometric bundle adjustment uses all of them.
"""

from __future__ import annotations

import numpy as np

from vo_core.geometry.klt import KltTracker, detect_corners
from vo_core.init.config import FeatureTrackConfig


class FeatureTracks:
    def __init__(self, config: FeatureTrackConfig, reference_image: np.ndarray, reference_index: int):
        self.config = config
        self.tracker = KltTracker(config.klt)
        corners = detect_corners(reference_image, config.corners, np.empty((0, 2)), config.corners.max_corners)
        self.frame_indices = [reference_index]
        self.uv = [corners.astype(float)]  # per frame (N, 2), rows aligned with the reference corners
        self.alive = np.ones(len(corners), bool)
        self.last_image = reference_image

    @property
    def num_frames(self) -> int:
        return len(self.frame_indices)

    @property
    def num_alive(self) -> int:
        return int(self.alive.sum())

    def add(self, frame_index: int, image: np.ndarray) -> int:
        """Track the living corners into ``image``; returns how many survive."""
        previous = self.uv[-1]
        current = np.full_like(previous, np.nan)
        living = np.flatnonzero(self.alive)
        moved, valid = self.tracker.track(self.last_image, image, previous[living].astype(np.float32))
        current[living[valid]] = moved[valid]
        self.alive[living[~valid]] = False
        self.uv.append(current)
        self.frame_indices.append(frame_index)
        self.last_image = image
        return self.num_alive

    def window(self) -> np.ndarray:
        """(frames, alive tracks, 2) positions of the surviving tracks in every frame so far."""
        return np.stack(self.uv)[:, self.alive]
