"""Corners and their tracking from frame to frame: Shi-Tomasi (or Harris) corners and pyramidal KLT with a
forward-backward check (paper 003 II-A.2; Kalal et al. 2010 for the forward-backward error), with their settings.

Below the two that track corners: the KLT baseline (vo_core/front_ends/klt/) and the feature initializer's tracks
(vo_core/init/klt_tracks.py). The defaults are the baseline's (paper 003's values, cited by section or table).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class CornerConfig:
    """Corner detection (paper 003 II-A.2, Tables II and III)."""

    max_corners: int = 1000  # Tables II/III: maximum number of keypoints
    min_distance: float = 11.0  # Tables II/III: non-maximum suppression radius (px)
    block_size: int = 7  # structure-tensor window; the paper's 15 px patch blurs corners at 320x240
    quality_level: float = 0.01  # OpenCV's relative cornerness threshold (paper: Harris threshold tuned)
    use_harris: bool = False  # Shi-Tomasi min-eigenvalue by default; the paper used Harris (II-A.2)
    harris_k: float = 0.04  # Table II: kappa 0.04 (KITTI, Malaga); Table III: 0.1 (parking)
    border: int = 8  # corners closer to the image border than this are not tracked well by KLT


@dataclass
class KltTrackerConfig:
    """Pyramidal Lucas-Kanade (paper 003 II-A.2: a pyramidal point tracker, vision.PointTracker)."""

    window_size: int = 21  # MATLAB PointTracker BlockSize [31 31] scaled to OpenCV's usual 21
    pyramid_levels: int = 3  # PointTracker NumPyramidLevels = 3
    max_iterations: int = 30  # PointTracker MaxIterations = 30
    epsilon: float = 0.01  # PointTracker: stop when the update is below 0.01 px
    max_forward_backward_error: float = 1.0  # PointTracker MaxBidirectionalError (px); ours 1 px


def detect_corners(image: np.ndarray, config: CornerConfig, existing: np.ndarray, count: int) -> np.ndarray:
    """Up to ``count`` new corners (K, 2) float32, at least ``min_distance`` away from ``existing`` (N, 2).

    The existing points are painted out of the detection mask so that new corners fill the empty parts of
    the image instead of piling onto what is already tracked."""
    if count <= 0:
        return np.empty((0, 2), np.float32)
    height, width = image.shape
    mask = np.zeros((height, width), np.uint8)
    b = config.border
    mask[b : height - b, b : width - b] = 255
    radius = int(round(config.min_distance))
    for u, v in np.round(existing).astype(int):
        cv2.circle(mask, (int(u), int(v)), radius, 0, -1)
    corners = cv2.goodFeaturesToTrack(
        image,
        maxCorners=count,
        qualityLevel=config.quality_level,
        minDistance=config.min_distance,
        mask=mask,
        blockSize=config.block_size,
        useHarrisDetector=config.use_harris,
        k=config.harris_k,
    )
    return np.empty((0, 2), np.float32) if corners is None else corners.reshape(-1, 2)


class KltTracker:
    """Pyramidal Lucas-Kanade between consecutive images, keeping only tracks that come back to where they
    started when tracked in reverse (forward-backward error below a threshold)."""

    def __init__(self, config: KltTrackerConfig):
        self.config = config
        self.params = dict(
            winSize=(config.window_size, config.window_size),
            maxLevel=config.pyramid_levels,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, config.max_iterations, config.epsilon),
        )

    def track(
        self, previous: np.ndarray, current: np.ndarray, points: np.ndarray, predicted: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(new positions (N, 2) float32, valid (N,) bool) of ``points`` from ``previous`` into ``current``.

        ``predicted`` (N, 2), where given, starts the search (e.g. landmarks projected with a motion model);
        large motions then need fewer pyramid levels to converge."""
        if len(points) == 0:
            return np.empty((0, 2), np.float32), np.zeros(0, bool)
        start = np.ascontiguousarray(points, np.float32).reshape(-1, 1, 2)
        flags = 0
        guess = None
        if predicted is not None:
            guess = np.ascontiguousarray(predicted, np.float32).reshape(-1, 1, 2).copy()
            flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        forward, status, _ = cv2.calcOpticalFlowPyrLK(previous, current, start, guess, flags=flags, **self.params)
        backward, status_back, _ = cv2.calcOpticalFlowPyrLK(
            current, previous, forward, start.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self.params
        )
        error = np.linalg.norm((backward - start).reshape(-1, 2), axis=1)
        forward = forward.reshape(-1, 2)
        height, width = current.shape
        inside = (
            (forward[:, 0] >= 0) & (forward[:, 1] >= 0) & (forward[:, 0] <= width - 1) & (forward[:, 1] <= height - 1)
        )
        valid = (
            (status.ravel() == 1)
            & (status_back.ravel() == 1)
            & (error < self.config.max_forward_backward_error)
            & inside
        )
        return forward, valid
