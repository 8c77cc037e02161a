"""The system's per-frame flow (vo_core/system.py) on real frames: what a refactor of the flow must not change."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from posed import posed_trajectory

from vo_core.config import load_config
from vo_core.datasets import open_sequence
from vo_core.eval.metrics import evaluate
from vo_core.events import EventKind
from vo_core.system import Odometry
from vo_core.trajectory import read_trajectory

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "assets" / "rgbd_dataset_freiburg3_teddy_first80"
# The bundled run of --method direct (written by `fdmo run --method direct --no-rrd --out ...`, 9 decimals): the
# move of the flowchart into system.py left it bit-identical; a change that moves it says why and writes it anew
# (last: the start's motion comes from a five-point essential matrix of the fundamental matrix's inliers instead of
# the projection of K^T F K, so the start's first poses move by up to 0.3 mm and the run by up to 2 mm, ATE
# 0.00430 -> 0.00459 m on this machine).
STORED_DIRECT_RUN = ROOT / "tests" / "data" / "bundled_direct_trajectory.tum"
# Written on an Intel Xeon (2026-11-28). The first frames, up to the first window optimization, match
# it to 1e-9 on any CPU; after that, another CPU rounds differently inside BLAS, numpy's SIMD reductions and the
# compiled kernels, and a discrete choice (a point activated or not) flips: measured against the file written on the
# machines before, the first difference is 2e-5 at frame 7, growing to 1.9e-3 by frame 75. So the poses are
# compared tightly up to that optimization, and over the whole run within 2.5x that CPU-to-CPU spread: a change of
# the flow that moves the run further (a hypothesis tried in another order, a step skipped) still fails.
TIGHT_TOLERANCE = 1e-6
TIGHT_FRAMES = 4  # the frames posed before the first window optimization
TOLERANCE = 5e-3


@pytest.mark.skipif(not BUNDLED.is_dir(), reason="the bundled sequence is not in this checkout")
def test_the_bundled_direct_run_is_unchanged():
    sequence = open_sequence(BUNDLED)
    odometry = Odometry(load_config(overrides=["method=direct"]), sequence.camera)
    results = [odometry.track(frame) for frame in sequence]
    posed = [r for r in results if r.T_world_cam is not None]
    stored = read_trajectory(STORED_DIRECT_RUN)
    assert len(posed) == len(stored)
    np.testing.assert_allclose([r.timestamp for r in posed], stored.timestamps, atol=TIGHT_TOLERANCE)
    positions = np.array([r.T_world_cam[:3, 3] for r in posed])
    np.testing.assert_allclose(positions[:TIGHT_FRAMES], stored.positions[:TIGHT_FRAMES], atol=TIGHT_TOLERANCE)
    np.testing.assert_allclose(positions, stored.positions, atol=TOLERANCE)


@pytest.mark.skipif(not BUNDLED.is_dir(), reason="the bundled sequence is not in this checkout")
@pytest.mark.parametrize("seed, why", [(2, None), (0, "too few to restart from")])
def test_frames_missed_after_the_start_do_not_trade_the_window_for_a_young_feature_map(seed, why):
    """Live under load, frames 4-16 and 18-22 were missed right after the start. The frame after the gap is suspect.
    Restarted on the feature map's ~75 two-view points (the start's two keyframes, 3 frames apart), the direct map's
    scale collapsed 10x, unreported, and the run ended 0.09-0.13 m off. The same window goes on instead (0.005 m): at
    seed 2 the feature map confirms the direct pose (it explains the majority of the recovery's inliers, 69 %),
    ``why`` None; at seed 0 it disagrees and the alignment from the recovered pose fits better, but none of
    the points in view is seen by 3 keyframes, too few to restart from (which seed takes which path moves with the
    start's arithmetic)."""
    sequence = open_sequence(BUNDLED)
    odometry = Odometry(load_config(overrides=["method=fdmo", f"seed={seed}"]), sequence.camera)
    missed = set(range(4, 17)) | set(range(18, 23))
    results = [odometry.track(frame) for frame in sequence if frame.index not in missed]
    events = [e for r in results for e in r.events]
    resumed = [e for e in events if e.kind is EventKind.DIRECT_RESUMED]
    if why is None:
        assert not resumed and any(e.kind is EventKind.TRACKING_CHECKED and e.frame_index == 17 for e in events)
    else:
        assert resumed and why in resumed[0].details["why"]
    assert not {EventKind.DIRECT_RESTARTED, EventKind.REINITIALIZATION} & {e.kind for e in events}
    estimate = posed_trajectory(results)
    assert evaluate(estimate, sequence.ground_truth)["ate"]["rmse"] < 0.02
