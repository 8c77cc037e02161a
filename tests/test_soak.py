"""The soak in short (issue 17; the long one is benchmarks/soak.py): 1,000 frames of the synthetic loop, round and
round, through fdmo with the Rerun recording on. The maps stay bounded by their culling, every frame is played and
nearly every one posed, the recording grows by the frame, and the process's memory stays flat.

The point budgets are a quarter of the defaults' (the soak is about what grows, not about accuracy): ~2 minutes of
CPU on one core."""

from __future__ import annotations

import pytest

from app.soak import rss_samples_text, soak
from vo_core.config import load_config

FRAMES, LOOP_FRAMES, EVERY = 1000, 100, 100
WIDTH, HEIGHT = 320, 240
POINT_DENSITY = 500
OVERRIDES = [f"direct.point_density={POINT_DENSITY}", f"direct.immature.density={POINT_DENSITY}"]
MIN_POSED = 0.95  # of the frames played: the loop is tracked, not lost and restarted
# Bounds the culling keeps: the direct window's active points are at most the budget (and a margin for the
# points of the newest keyframe), the feature map's keyframes and points in the second half at most 1.5x the most
# seen in the first. A map that grew with the frames would double there, as the direct keyframes made do (181 by
# frame 500, 366 by 1000); a culled one settles, give or take a few keyframes: 13-16 early here and 19-22 from frame
# 900 to 2,000 (15-22 over benchmarks/soak.py's 10,000 frames).
DIRECT_POINTS_MARGIN = 2.0
FEATURE_GROWTH = 1.5


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    return soak(FRAMES, WIDTH, HEIGHT, tmp_path_factory.mktemp("soak"), load_config(overrides=OVERRIDES),
                sample_every=EVERY, loop_frames=LOOP_FRAMES)


def test_every_frame_is_played_and_nearly_every_one_posed(report):
    metrics = report.summary.metrics
    assert metrics["processed_frames"] == FRAMES and len(report.samples) == FRAMES // EVERY
    assert metrics["posed_frames"] >= MIN_POSED * FRAMES, metrics


def test_the_maps_stay_bounded(report):
    samples = report.samples
    assert all(0 < s.direct_points <= DIRECT_POINTS_MARGIN * POINT_DENSITY for s in samples), rss_samples_text(report)
    first, second = samples[: len(samples) // 2], samples[len(samples) // 2:]
    for field in ("feature_keyframes", "feature_points"):
        most_early = max(getattr(s, field) for s in first)
        assert max(getattr(s, field) for s in second) <= FEATURE_GROWTH * most_early, rss_samples_text(report)


def test_the_recording_grows_with_the_frames(report):
    sizes = [sample.recording_bytes for sample in report.samples]
    assert all(later > earlier for earlier, later in zip(sizes, sizes[1:])), sizes
    assert report.recording_bytes >= sizes[-1] and report.bytes_per_frame > 0


def test_memory_stays_flat(report):
    # issue 17: the rerun SDK's file sink indexes every chunk in memory until the recording closes (the .rrd
    # footer); RerunSink batched into a chunk per entity per frame and per keyframe and grew ~0.09 MiB a frame
    # here (19 % drift); with fewer, larger chunks 0.02-0.03 MiB a frame (~7 %).
    assert report.rss_flat, rss_samples_text(report)
