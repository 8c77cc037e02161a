"""Photometric bundle adjustment of the initial map (vo_core/init/photometric_ba.py, paper 004 section 3.4) on
rendered sequences (vo_core.synthetic), alone and inside the feature-based initializer."""

from __future__ import annotations

import numpy as np
import pytest

import vo_core.init.feature_initializer as feature_initializer
from test_init_feature_initializer import run_initializer
from vo_core.direct.config import DirectConfig
from vo_core.direct.pixel_selector import PixelSelector
from vo_core.direct.pyramid import ImagePyramid
from vo_core.geometry.lie import se3_exp, se3_inverse, so3_log
from vo_core.init.config import InitConfig, PhotometricBAConfig
from vo_core.init.photometric_ba import make_photometric_ba, photometric_bundle_adjustment
from vo_core.synthetic import make_sequence


def pose_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(rotation error, angle between the translation directions), degrees: the scale is free."""
    rotation = np.degrees(np.linalg.norm(so3_log(truth[:3, :3].T @ estimate[:3, :3])))
    a, b = estimate[:3, 3], truth[:3, 3]
    cosine = a @ b / np.linalg.norm(a) / np.linalg.norm(b)
    return float(rotation), float(np.degrees(np.arccos(min(cosine, 1.0))))


def relative_depth_error(inverse_depths: np.ndarray, true_inverse_depths: np.ndarray) -> float:
    """Median relative error after the best scale (the map's scale is free)."""
    scale = np.median(true_inverse_depths / inverse_depths)
    return float(np.median(np.abs(inverse_depths * scale - true_inverse_depths) / true_inverse_depths))


def true_inverse_depths(sequence, first: int, uv: np.ndarray) -> np.ndarray:
    pixels = np.round(uv).astype(int)
    return 1.0 / sequence[first].depth[pixels[:, 1], pixels[:, 0]]


def test_the_adjustment_brings_perturbed_poses_and_depths_back_to_the_truth():
    sequence = make_sequence("smooth", num_frames=5, seed=1, width=320, height=240)
    config = DirectConfig()
    pyramids = [ImagePyramid(frame.image.astype(np.float32), sequence.camera, config.pyramid) for frame in sequence]
    window = [(frame.index, pyramid, None) for frame, pyramid in zip(sequence, pyramids)]
    world_first = se3_inverse(sequence.ground_truth.poses[0])
    truth = np.array([world_first @ T for T in sequence.ground_truth.poses])  # the reference is the origin
    uv = PixelSelector(config.selector, 0).select(pyramids[0].levels, 1500).uv.astype(float)
    idepth_true = true_inverse_depths(sequence, 0, uv)
    rng = np.random.default_rng(4)
    poses = truth.copy()
    for k in range(1, len(poses)):  # about a pixel or two off
        poses[k] = se3_exp(np.r_[rng.normal(0, 0.002, 3), rng.normal(0, np.radians(0.2), 3)]) @ poses[k]
    idepth = idepth_true * rng.uniform(0.9, 1.1, len(uv))

    adjusted = photometric_bundle_adjustment(
        make_photometric_ba(config, PhotometricBAConfig()), window, poses, uv, idepth
    )

    report = adjusted.report
    assert report.energy_after < 0.5 * report.energy_before  # measured: 3.7e6 -> 5.1e5
    np.testing.assert_allclose(adjusted.poses_world_cam[0], poses[0], atol=1e-12)  # the reference is the gauge
    assert adjusted.kept.sum() == len(adjusted.inverse_depths) == len(uv) - report.removed_points
    assert report.removed_points < 0.2 * len(uv)  # measured: 70 of 1448 (occlusion edges, points out of view)
    before, after = pose_errors(poses[-1], truth[-1]), pose_errors(adjusted.poses_world_cam[-1], truth[-1])
    assert after[0] < 0.5 * before[0] and after[1] < 0.5 * before[1]  # measured: 0.16 -> 0.01 deg, 0.9 -> 0.3 deg
    kept_truth = idepth_true[adjusted.kept]
    assert relative_depth_error(adjusted.inverse_depths, kept_truth) < 0.5 * relative_depth_error(
        idepth[adjusted.kept], kept_truth
    )  # measured: 5.1% -> 1.8%


@pytest.fixture(scope="module")
def smooth_runs():
    """The initializer on the smooth preset without and with the photometric bundle adjustment."""
    runs = {}
    for enabled in (False, True):
        config = InitConfig()
        config.photometric_ba.enabled = enabled
        runs[enabled] = run_initializer("smooth", init_config=config)
    return runs


def test_the_initializer_result_is_closer_to_the_truth_with_the_adjustment(smooth_runs):
    errors = {}
    for enabled, (result, status, sequence, first, second) in smooth_runs.items():
        assert result is not None, status
        truth = se3_inverse(sequence.ground_truth.poses[first]) @ sequence.ground_truth.poses[second]
        idepth_true = true_inverse_depths(sequence, first, result.points_uv)
        depth_error = relative_depth_error(result.inverse_depths, idepth_true)
        errors[enabled] = (*pose_errors(result.T_first_second, truth), depth_error)
        assert np.mean(result.inverse_depths) == pytest.approx(1.0)  # still DSO's scale
    assert errors[True][0] < 0.6 * errors[False][0]  # rotation: measured 0.24 -> 0.08 deg
    assert errors[True][1] < 0.6 * errors[False][1]  # translation direction: measured 5.1 -> 1.5 deg
    assert errors[True][2] < 0.6 * errors[False][2]  # inverse depths: measured 9% -> 4%


def test_both_adjustments_lower_the_photometric_energy(smooth_runs):
    _, status, *_ = smooth_runs[True]
    for name in ("photometric_ba", "final_photometric_ba"):
        assert status[f"{name}_energy_after"] < status[f"{name}_energy_before"]
    # The filter's outliers leave before the final adjustment: it starts from a lower energy.
    assert status["final_photometric_ba_energy_before"] < status["photometric_ba_energy_after"]
    assert "photometric_ba_energy_before" not in smooth_runs[False][1]


def test_points_removed_by_the_filter_are_not_in_the_result(monkeypatch):
    removed = []
    filter_points = feature_initializer.photometric_inliers

    def recording_filter(reference, uv, inverse_depths, frames, config):
        keep, scales = filter_points(reference, uv, inverse_depths, frames, config)
        removed.append(uv[~keep])
        return keep, scales

    monkeypatch.setattr(feature_initializer, "photometric_inliers", recording_filter)
    result, status, *_ = run_initializer("smooth")
    assert result is not None, status
    assert len(removed) == 1 and len(removed[0]) == status["photometric_outliers"] > 0
    in_result = {tuple(p) for p in result.points_uv}
    assert not any(tuple(p) in in_result for p in removed[0])
    assert len(result.points_uv) == status["points_handed_over"]
