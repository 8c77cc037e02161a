"""The scale watch: the motion's own variation passes, a jump or a collapse of the map's scale is reported."""

from __future__ import annotations

import numpy as np
import pytest

from vo_core.config import load_config
from vo_core.direct.config import ScaleWatchConfig
from vo_core.direct.marginalization import MarginalizationPrior
from vo_core.direct.scale_watch import ScaleWatch
from vo_core.events import EventKind
from vo_core.synthetic import make_sequence
from vo_core.system import Odometry


def jumps(steps, inverse_depths) -> list[int]:
    watch = ScaleWatch(ScaleWatchConfig())
    return [k for k, (step, depth) in enumerate(zip(steps, inverse_depths)) if watch.observe(step, depth).jump]


def test_the_motions_own_variation_is_no_jump():
    rng = np.random.default_rng(0)
    steps = 0.04 * np.exp(rng.normal(0.0, 0.3, 60))  # keyframe speeds vary by +-30 % (teddy: steps 0.024 - 0.058)
    depths = 1.0 + 0.05 * np.sin(np.arange(60) / 5.0)
    assert jumps(steps, depths) == []
    assert jumps(np.tile([0.05, 0.1], 30), np.ones(60)) == []  # KITTI: a keyframe every frame or every other one
    rotation_only = np.r_[np.full(10, 0.04), np.full(10, 0.002), np.full(10, 0.04)]
    assert jumps(rotation_only, np.ones(30)) == []  # short steps, the same depths: the camera turns


def test_walking_up_to_a_wall_is_no_jump():
    """Steps a tenth of the depth (a flow-triggered keyframe): both shrink together, but slowly."""
    depth, steps, inverse_depths = 3.0, [], []
    while depth > 0.5:
        steps.append(0.1 * depth)
        inverse_depths.append(1.0 / depth)
        depth -= 0.1 * depth
    assert jumps(steps, inverse_depths) == []


def test_a_sudden_factor_of_two_is_a_jump():
    steps = np.r_[np.full(8, 0.04), np.full(8, 0.02)]
    depths = np.r_[np.full(8, 1.0), np.full(8, 2.0)]
    assert jumps(steps, depths) == [8]
    watch = ScaleWatch(ScaleWatchConfig())
    readings = [watch.observe(step, depth) for step, depth in zip(steps, depths)]
    assert readings[8].factor == pytest.approx(2.0)
    assert readings[8].step_ratio == pytest.approx(0.5) and readings[8].depth_ratio == pytest.approx(2.0)


def test_a_collapse_of_170x_over_30_frames_is_reported():
    """A keyframe every 3 frames: 10 keyframes, the map shrinking by 170^(1/10) = 1.67 at each."""
    shrink = 170.0 ** (1.0 / 10.0)
    steps = np.r_[np.full(6, 0.04), 0.04 / shrink ** np.arange(1, 11)]
    depths = np.r_[np.full(6, 1.0), shrink ** np.arange(1, 11)]
    found = jumps(steps, depths)
    assert found and found[0] <= 8  # within three keyframes of the collapse's start
    assert len(found) >= 2  # and again while it goes on


# ---------------------------------------------------------------------------------------- in a run


def shrink_map(direct, factor: float) -> None:
    """The window's translations and depths scaled by ``factor`` about the newest keyframe, as a window
    optimization sliding along the scale direction would; the prior that held the old scale goes too."""
    centre = direct.keyframes[-1].T_world_cam[:3, 3].copy()
    for keyframe in direct.keyframes:
        keyframe.T_world_cam = keyframe.T_world_cam.copy()
        keyframe.T_world_cam[:3, 3] = centre + factor * (keyframe.T_world_cam[:3, 3] - centre)
        keyframe.active_idepth = keyframe.active_idepth / factor
        if keyframe.immature is not None:
            for name in ("idepth_min", "idepth_max"):
                setattr(keyframe.immature, name, getattr(keyframe.immature, name) / factor)
    for tracked in direct.history:
        tracked.T_world_cam = tracked.T_world_cam.copy()
        tracked.T_world_cam[:3, 3] = centre + factor * (tracked.T_world_cam[:3, 3] - centre)
    direct.prior = MarginalizationPrior()
    direct._set_tracking_reference(direct.keyframes[-1])


def scale_events(shrink_at: int | None):
    sequence = make_sequence("smooth", 60, 0, 320, 240)
    odometry = Odometry(load_config(overrides=["method=direct"]), sequence.camera)
    events, results = [], []
    for frame in sequence:
        result = odometry.track(frame)
        results.append(result)
        events += [e for e in result.events if e.kind is EventKind.SCALE_JUMP]
        if frame.index == shrink_at:
            shrink_map(odometry.direct, 0.5)
    return events, results


def test_a_run_reports_its_scale_at_keyframes_and_no_jump():
    events, results = scale_events(None)
    assert events == []
    keyframes = [r for r in results if r.is_keyframe]
    assert all(r.mean_inverse_depth > 0 for r in keyframes)
    ratios = [r.scale_ratio for r in keyframes if r.scale_ratio is not None]
    assert len(ratios) >= 3 and all(0.3 < ratio < 3.0 for ratio in ratios)
    assert all(r.scale_ratio is None and r.mean_inverse_depth is None for r in results if not r.is_keyframe)


def test_a_map_shrunk_by_half_mid_run_raises_the_scale_event():
    events, _ = scale_events(shrink_at=35)
    assert events, "the shrunk map went unreported"
    details = events[0].details
    assert events[0].frame_index > 35
    assert details["factor"] > 1.6 and details["depth_ratio"] > 1.25 and details["step_ratio"] < 1.0
