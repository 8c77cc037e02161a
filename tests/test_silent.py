"""Silent failures (vo_core.eval.silent): a stretch at another scale than its map's, with nothing reported."""

from __future__ import annotations

import numpy as np

from vo_core.eval.silent import SilentConfig, scale_segments
from vo_core.trajectory import Trajectory

TIMES = np.arange(300) * 0.1


def along_a_curve(scale_of_step: np.ndarray) -> tuple[Trajectory, Trajectory]:
    """A camera moving along a curve, and an estimate whose steps are scaled by ``scale_of_step``."""
    steps = np.stack([np.cos(TIMES), np.sin(2 * TIMES), 0.3 * np.ones_like(TIMES)], axis=1) * 0.1
    truth = np.cumsum(steps, axis=0)
    estimate = np.cumsum(steps * scale_of_step[:, None], axis=0)

    def trajectory(positions):
        poses = np.tile(np.eye(4), (len(TIMES), 1, 1))
        poses[:, :3, 3] = positions
        return Trajectory(TIMES.copy(), poses)

    return trajectory(estimate), trajectory(truth)


def test_a_stretch_at_half_the_scale_is_silent_unless_something_was_reported_there():
    scale = np.ones(len(TIMES))
    scale[100:200] = 0.5
    estimate, truth = along_a_curve(scale)
    config = SilentConfig()
    silent = [s for s in scale_segments(estimate, truth, np.array([]), np.array([]), config) if s.silent(config)]
    assert silent and all(10.0 - 5.0 <= s.start_s <= 20.0 for s in silent)
    warned = scale_segments(estimate, truth, np.array([10.0]), np.array([]), config)
    assert not any(s.silent(config) for s in warned)


def test_a_run_at_one_scale_has_no_silent_stretch_and_a_new_map_is_judged_on_its_own():
    estimate, truth = along_a_curve(np.full(len(TIMES), 3.0))
    config = SilentConfig()
    assert not any(s.silent(config) for s in scale_segments(estimate, truth, np.array([]), np.array([]), config))
    scale = np.where(TIMES < 15.0, 1.0, 4.0)  # a second map, begun at 15 s, at its own scale
    estimate, truth = along_a_curve(scale)
    positions = estimate.poses[:, :3, 3]
    positions[150:] -= positions[150] - truth.poses[150, :3, 3]  # its own origin: the new map starts anew
    judged = scale_segments(estimate, truth, np.array([]), np.array([15.0]), config)
    assert judged and not any(s.silent(config) for s in judged)
    assert any(s.silent(config) for s in scale_segments(estimate, truth, np.array([]), np.array([]), config))
