"""The coarse tracker, pixel selector and immature points on a rendered scene with known depth."""

from __future__ import annotations

import numpy as np
import pytest

from test_direct_support import PlaneScene, pose, small_camera
from vo_core.direct.config import DirectConfig
from vo_core.direct.coarse_tracker import CoarseTracker, _merged_per_pixel
from vo_core.direct.immature_point import (
    ActivationCandidates, ActivationTargets, ImmaturePoints, optimize_for_activation,
)
from vo_core.direct.pixel_selector import PixelSelector, block_thresholds
from vo_core.direct.pyramid import ImagePyramid
from vo_core.geometry.lie import se3_exp, se3_inverse, se3_log

CONFIG = DirectConfig()
GAIN, OFFSET = 1.1, 5.0  # brightness change of the second image


@pytest.fixture(scope="module")
def pair():
    """Reference and current images (with a brightness change), reference depth, true T_cur_ref."""
    camera = small_camera(320, 240)
    scene = PlaneScene(seed=1)
    T_world_ref = pose()
    T_world_cur = pose((0.01, -0.02, 0.005), (0.08, -0.03, 0.05))
    image_ref, depth_ref = scene.render(camera, T_world_ref)
    image_cur, _ = scene.render(camera, T_world_cur, gain=GAIN, offset=OFFSET)
    return (
        camera,
        ImagePyramid(image_ref, camera, CONFIG.pyramid),
        ImagePyramid(image_cur, camera, CONFIG.pyramid),
        depth_ref,
        se3_inverse(T_world_cur) @ T_world_ref,
    )


@pytest.fixture(scope="module")
def tracker(pair):
    _, reference, _, depth, _ = pair
    selection = PixelSelector(CONFIG.selector, seed=0).select(reference, 2000)
    tracker = CoarseTracker(CONFIG.tracker)
    idepth = 1.0 / depth[selection.uv[:, 1], selection.uv[:, 0]]
    tracker.set_reference(reference, selection.uv, idepth, np.zeros(2), None)
    return tracker


def test_tracking_recovers_pose_and_brightness_from_a_few_pixels_off(pair, tracker):
    _, _, current, _, T_true = pair
    # About 3 px of rotation and 2 px of translation flow away from the truth.
    start = se3_exp(np.array([0.02, -0.01, 0.01, 0.004, 0.008, 0.0])) @ T_true
    result = tracker.track(current, start, np.zeros(2), None)
    error = se3_log(result.T_frame_ref @ se3_inverse(T_true))
    assert result.success
    assert np.linalg.norm(error[:3]) < 2e-3  # metres, scene at 1-4 m
    assert np.linalg.norm(error[3:]) < 5e-4  # radians
    # I_cur = e^a I_ref + b: the predicted intensities match the applied gain and offset.
    gain, offset = np.exp(result.affine[0]), result.affine[1]
    for intensity in (60.0, 128.0, 200.0):
        assert gain * intensity + offset == pytest.approx(GAIN * intensity + OFFSET, abs=2.0)
    assert result.rmse_after < 0.3 * result.rmse_before


def test_coarse_levels_hold_each_pixel_once_and_the_finest_every_pattern_pixel(pair, tracker):
    """Level 0: DSO's 8-pixel pattern of every point. Coarser: overlapping patterns meet in the same pixels, each one
    residual, at the mean inverse depth of the points whose patterns cover it."""
    _, reference, _, _, _ = pair
    finest = tracker.levels[0]
    assert len(finest.idepth) == 8 * len(finest.centre_idepth)
    for level in range(1, len(tracker.levels)):
        points = tracker.levels[level]
        camera = reference[level].camera
        pixels = np.round(camera.project(points.rays.astype(float))).astype(int)
        assert len(np.unique(pixels, axis=0)) == len(pixels)
        assert len(pixels) < 8 * len(points.centre_idepth)  # the patterns did overlap
        # A pixel's inverse depth lies within the range of the point centres' around it.
        assert points.idepth.min() >= points.centre_idepth.min() - 1e-6
        assert points.idepth.max() <= points.centre_idepth.max() + 1e-6


def test_tracking_from_far_off_fails_detectably(pair, tracker):
    _, _, current, _, T_true = pair
    good = tracker.track(current, T_true, np.zeros(2), None)
    far = tracker.track(current, se3_exp(np.array([0.0, 0.0, 0.0, 0.0, 0.35, 0.0])) @ T_true, np.zeros(2), None)
    # Converged: the error drops to the noise level. From 20 degrees off: no real improvement.
    assert good.success and good.rmse_after < 0.5 * good.rmse_before  # here the brightness change dominates "before"
    assert not far.success or far.rmse_after > 0.6 * far.rmse_before
    assert not far.success or far.rmse_after > 3.0 * good.rmse_after


def test_a_guess_that_meets_an_earlier_one_at_the_coarsest_level_is_dropped_there(pair, tracker):
    """DSO tries up to 31 motion guesses on a hard frame; those ending in the coarse optimum an earlier guess reached
    would repeat its finer levels: they fail at once (no finer level run), a guess that ends elsewhere does not."""
    _, _, current, _, T_true = pair
    optima: list[np.ndarray] = []
    start = se3_exp(np.array([0.02, -0.01, 0.01, 0.004, 0.008, 0.0])) @ T_true
    first = tracker.track(current, start, np.zeros(2), None, coarse_optima=optima)
    nearby = tracker.track(current, se3_exp(np.array([0.0, 0.01, 0.0, 0.0, 0.004, 0.0])) @ start, np.zeros(2), None,
                           coarse_optima=optima)
    assert first.success and len(optima) == 1
    assert not nearby.success and np.isnan(nearby.rmse_per_level[0]) and len(optima) == 1
    far = tracker.track(current, se3_exp(np.array([0.0, 0.0, 0.0, 0.0, 0.35, 0.0])) @ T_true, np.zeros(2), None,
                        coarse_optima=optima)
    assert np.isfinite(far.rmse_per_level[-1]) and len(optima) == 2


@pytest.mark.parametrize("density", [500, 1000, 2000])
def test_pixel_selection_reaches_the_requested_density(pair, density):
    _, reference, _, _, _ = pair
    selector = PixelSelector(CONFIG.selector, seed=0)
    counts = [len(selector.select(reference, density).uv) for _ in range(2)]  # the cell size adapts
    assert counts[-1] == pytest.approx(density, rel=0.15)
    selection = selector.select(reference, density)
    h, w = reference[0].intensity.shape
    assert np.all((selection.uv >= 4) & (selection.uv < [w - 4, h - 4]))
    assert len(np.unique(selection.uv, axis=0)) == len(selection.uv)


def test_pixel_selection_spreads_over_the_image(pair):
    _, reference, _, _, _ = pair
    selection = PixelSelector(CONFIG.selector, seed=0).select(reference, 1000)
    h, w = reference[0].intensity.shape
    occupied = np.unique((selection.uv[:, 1] * 4 // h) * 4 + selection.uv[:, 0] * 4 // w)
    assert len(occupied) == 16  # every cell of a 4x4 grid has points


def test_pixel_selection_reaches_past_the_last_whole_threshold_block(pair):
    """Pixels in the partial blocks at the bottom edge are judged by the last whole block's threshold."""
    _, reference, _, _, _ = pair
    h = reference[0].intensity.shape[0]
    block = CONFIG.selector.block_size
    assert h % block  # the test image has a partial row of blocks
    selection = PixelSelector(CONFIG.selector, seed=0).select(reference, 1000)
    assert np.any(selection.uv[:, 1] >= h // block * block)


def test_pyramid_levels_are_block_means_with_central_difference_gradients():
    image = np.random.default_rng(3).uniform(0, 255, (61, 83)).astype(np.float32)  # odd: last row/column dropped
    pyramid = ImagePyramid(image, small_camera(83, 61), CONFIG.pyramid)
    expected = image
    for level in pyramid.levels:
        np.testing.assert_allclose(level.intensity, expected, rtol=1e-6)
        gx, gy = level.packed[..., 1], level.packed[..., 2]
        np.testing.assert_allclose(gx[1:-1, 1:-1], 0.5 * (expected[1:-1, 2:] - expected[1:-1, :-2]), atol=1e-4)
        np.testing.assert_allclose(gy[1:-1, 1:-1], 0.5 * (expected[2:, 1:-1] - expected[:-2, 1:-1]), atol=1e-4)
        assert not gx[:, [0, -1]].any() and not gy[[0, -1], :].any()
        h, w = expected.shape[0] // 2 * 2, expected.shape[1] // 2 * 2
        expected = expected[:h, :w].reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))


def test_gradient_thresholds_are_smoothed_block_medians():
    config = CONFIG.selector
    grad_sq = np.random.default_rng(4).gamma(1.0, 300.0, (100, 140)).astype(np.float32)  # partial last blocks
    magnitude = np.minimum(np.sqrt(grad_sq).astype(int), config.hist_max_gradient)
    block = config.block_size
    medians = np.empty((100 // block, 140 // block))
    for row in range(medians.shape[0]):
        for col in range(medians.shape[1]):
            values = magnitude[row * block : (row + 1) * block, col * block : (col + 1) * block]
            values = values[(row == 0) :, (col == 0) :]  # the image's first row and column are skipped
            ordered = np.sort(values.ravel())
            medians[row, col] = ordered[min(int(len(ordered) * config.hist_quantile + 0.5), len(ordered) - 1)]
    rows, cols = medians.shape

    def sum_3x3(values):
        padded = np.pad(values, 1)
        return sum(padded[dy : dy + rows, dx : dx + cols] for dy in range(3) for dx in range(3))

    smoothed = sum_3x3(medians + config.hist_add) / sum_3x3(np.ones_like(medians))
    thresholds = block_thresholds(grad_sq, config)
    assert thresholds.shape == medians.shape  # the partial blocks at the edges belong to the last whole ones
    assert np.allclose(thresholds, smoothed**2)


@pytest.fixture(scope="module")
def traced_points():
    """Immature points of a plane scene traced through five frames: (points, true inverse depths, frames)."""
    camera = small_camera(320, 240)
    scene = PlaneScene(seed=1)
    image, depth = scene.render(camera, pose())
    host = ImagePyramid(image, camera, CONFIG.pyramid)
    selection = PixelSelector(CONFIG.selector, seed=0).select(host, 1000)
    points = ImmaturePoints.create(host, selection.uv, selection.kind, CONFIG.immature)
    true_idepth = 1.0 / depth[points.uv[:, 1].astype(int), points.uv[:, 0].astype(int)]
    frames = []
    for i in range(1, 6):
        T_world_frame = pose((0.0, 0.003 * i, 0.0), (0.03 * i, 0.005 * i, 0.01 * i))
        frame = ImagePyramid(scene.render(camera, T_world_frame)[0], camera, CONFIG.pyramid)
        points.trace(frame[0], se3_inverse(T_world_frame), (1.0, 0.0), CONFIG.immature)
        frames.append((frame, T_world_frame))
    return points, true_idepth, frames


def test_immature_point_depths_converge_to_the_truth(traced_points):
    points, true_idepth, _ = traced_points
    ready = points.activatable(CONFIG.immature)
    relative_error = np.abs(points.idepth[ready] - true_idepth[ready]) / true_idepth[ready]
    assert ready.sum() > 0.5 * len(points)
    assert np.median(relative_error) < 0.01
    assert np.percentile(relative_error, 90) < 0.05
    # The truth lies inside the final interval for most points.
    low, high, truth = points.idepth_min[ready], points.idepth_max[ready], true_idepth[ready]
    inside = (low <= truth * 1.01) & (truth * 0.99 <= high)
    assert inside.mean() > 0.8


def test_activation_pulls_inverse_depths_to_the_truth_from_five_percent_off(traced_points):
    points, true_idepth, frames = traced_points
    ready = np.flatnonzero(points.activatable(CONFIG.immature))
    start = points.subset(np.ones(len(points), dtype=bool))
    start.idepth_min, start.idepth_max = 1.05 * points.idepth_min, 1.05 * points.idepth_max
    targets = ActivationTargets(
        frames[0][0][0].camera, np.stack([frame[0].intensity for frame, _ in frames]), np.arange(len(frames)),
        np.array([se3_inverse(T_world_frame) for _, T_world_frame in frames]), np.tile([1.0, 0.0], (len(frames), 1)))
    [(idepth, usable, _)] = optimize_for_activation([ActivationCandidates(start, ready, targets)], CONFIG.immature)
    assert usable.mean() > 0.9
    relative_error = np.abs(idepth[usable] - true_idepth[ready][usable]) / true_idepth[ready][usable]
    assert np.median(relative_error) < 0.01
    assert np.percentile(relative_error, 90) < 0.03


def test_activation_says_in_which_targets_each_points_residual_is_in(traced_points):
    """optimizeImmaturePoint's residual states: a point gets residuals only in the targets where its residual ended
    in (odometry._drop_residuals_not_in); a target whose image shows something else has hardly any of them in."""
    points, _, frames = traced_points
    ready = np.flatnonzero(points.activatable(CONFIG.immature))
    images = np.stack([frame[0].intensity for frame, _ in frames])
    images[-1] = np.random.default_rng(0).uniform(0, 255, images[-1].shape)  # the last target sees noise
    targets = ActivationTargets(
        frames[0][0][0].camera, images, np.arange(len(frames)),
        np.array([se3_inverse(T_world_frame) for _, T_world_frame in frames]), np.tile([1.0, 0.0], (len(frames), 1)))
    [(_, usable, inliers)] = optimize_for_activation([ActivationCandidates(points, ready, targets)], CONFIG.immature)
    assert inliers.shape == (len(ready), len(frames))
    assert inliers[usable, :-1].mean() > 0.9
    assert inliers[:, -1].mean() < 0.1


def test_activation_of_several_hosts_at_once_gives_each_host_what_it_gets_alone(traced_points):
    """All hosts' candidates run in one compiled call, in blocks on numba's threads: each point must still see its
    own host's targets (here the second host's transfer is 20 levels brighter) and nothing of the other points."""
    points, _, frames = traced_points
    ready = np.flatnonzero(points.activatable(CONFIG.immature))
    images = np.stack([frame[0].intensity for frame, _ in frames])
    T_target_host = np.array([se3_inverse(T_world_frame) for _, T_world_frame in frames])
    plain = ActivationTargets(frames[0][0][0].camera, images, np.arange(len(frames)), T_target_host,
                              np.tile([1.0, 0.0], (len(frames), 1)))
    brighter = ActivationTargets(frames[0][0][0].camera, images, np.arange(len(frames)), T_target_host,
                                 np.tile([1.0, 20.0], (len(frames), 1)))
    hosts = [ActivationCandidates(points, ready[::2], plain), ActivationCandidates(points, ready[1::2], brighter)]
    together = optimize_for_activation(hosts, CONFIG.immature)
    alone = [optimize_for_activation([host], CONFIG.immature)[0] for host in hosts]
    for (idepth, usable, inliers), (idepth_alone, usable_alone, inliers_alone) in zip(together, alone):
        np.testing.assert_array_equal(idepth, idepth_alone)
        np.testing.assert_array_equal(usable, usable_alone)
        np.testing.assert_array_equal(inliers, inliers_alone)
    # The transfers really differ: the second host's points in the first host's targets end elsewhere.
    in_plain_targets = optimize_for_activation([ActivationCandidates(points, ready[1::2], plain)], CONFIG.immature)[0]
    assert np.abs(in_plain_targets[0] - together[1][0]).max() > 1e-3 * np.abs(together[1][0]).max()


def test_a_coarse_level_holds_each_pixel_once_at_the_mean_inverse_depth_of_its_points():
    """makeCoarseDepthL0's merge: points rounded to pixels (halves to even, as np.round), one per pixel in raster
    order, at the mean inverse depth of the points that fell into it (points up to half a pixel outside too)."""
    rng = np.random.default_rng(4)
    uv = np.concatenate([rng.uniform(-0.5, 32.0, (300, 2)), [[2.5, 3.5], [3.5, 3.5], [2.4, 4.4], [-0.5, 0.5]]])
    idepth = rng.uniform(0.1, 2.0, len(uv))
    width = 32
    by_pixel: dict[tuple[int, int], list[float]] = {}
    for (u, v), d in zip(np.round(uv).astype(int), idepth):
        by_pixel.setdefault((v, u), []).append(d)
    raster = sorted(by_pixel)
    merged_uv, merged_idepth = _merged_per_pixel(uv, idepth, width)
    assert merged_uv.tolist() == [[float(u), float(v)] for v, u in raster]
    np.testing.assert_allclose(merged_idepth, [np.mean(by_pixel[key]) for key in raster], rtol=1e-12)
    assert [2.0, 4.0] in merged_uv.tolist() and [-0.0, 0.0] in merged_uv.tolist()  # 2.5 -> 2, 3.5 -> 4, -0.5 -> -0
