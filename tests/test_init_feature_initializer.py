"""The feature-based initializer on rendered sequences (vo_core.synthetic presets) and inside DirectOdometry."""

from __future__ import annotations

import re

import numpy as np
import pytest

from test_direct_odometry import smooth_pose
from test_direct_support import PlaneScene, aligned_ate, render_frame, small_camera
from vo_core.config import load_config
from vo_core.direct.config import DirectConfig
from vo_core.direct.pyramid import ImagePyramid
from vo_core.events import EventKind
from vo_core.geometry.lie import se3_inverse, so3_log
from vo_core.geometry.klt import CornerConfig
from vo_core.init.config import FeatureTrackConfig, InitConfig
from vo_core.init.feature_initializer import FeatureInitializer
from vo_core.init.registry import make_initializer
from vo_core.synthetic import make_sequence
from vo_core.system import Odometry

FRAMES = 12


def run_initializer(preset: str, frames: int = FRAMES, init_config: InitConfig | None = None):
    """Feed the preset's frames until a result; returns (result or None, status, sequence, first and second
    positions)."""
    sequence = make_sequence(preset, num_frames=frames, width=320, height=240)
    config = DirectConfig()
    initializer = make_initializer(
        DirectConfig(initializer="features"), init_config or InitConfig(), sequence.camera, 0
    )
    assert isinstance(initializer, FeatureInitializer)
    first = 0
    for position, frame in enumerate(sequence):
        pyramid = ImagePyramid(frame.image.astype(np.float32), sequence.camera, config.pyramid)
        if not initializer.started:
            initializer.set_first(frame.index, pyramid, None)
            first = position
            continue
        result = initializer.track(frame.index, pyramid, None)
        if result is not None:
            return result, initializer.status(), sequence, first, position
    return None, initializer.status(), sequence, first, None


@pytest.mark.parametrize("preset, model", [("planar", "H"), ("smooth", "F")])
def test_initial_pose_and_model_on_rendered_scenes(preset, model):
    result, status, sequence, first, second = run_initializer(preset)
    assert result is not None, status
    assert result.details["model"] == model and status["stage"] == "succeeded"
    truth = se3_inverse(sequence.ground_truth.poses[first]) @ sequence.ground_truth.poses[second]
    estimate = result.T_first_second
    rotation_error = np.degrees(np.linalg.norm(so3_log(truth[:3, :3].T @ estimate[:3, :3])))
    cosine = truth[:3, 3] @ estimate[:3, 3] / np.linalg.norm(truth[:3, 3]) / np.linalg.norm(estimate[:3, 3])
    assert rotation_error < 0.5  # measured 0.03 (planar) and 0.36 (smooth) degrees
    assert np.degrees(np.arccos(min(cosine, 1.0))) < 8.0  # measured 0.5 and 4.7 degrees (1.1 deg of parallax)
    assert np.mean(result.inverse_depths) == pytest.approx(1.0)  # DSO's scale
    assert len(result.points_uv) == len(result.inverse_depths) > 1000  # features plus selected pixels
    assert result.second_frame_index - result.first_frame_index <= 10


@pytest.mark.parametrize("preset, reason", [("rotation", "parallax|explains|ambiguous"), ("static", "no motion")])
def test_no_initialization_without_translation(preset, reason):
    result, status, *_ = run_initializer(preset, frames=10)
    assert result is None
    assert status["stage"] == "rejected"
    assert re.search(reason, status["reason"])


def test_a_reference_is_kept_while_a_start_can_come_from_it():
    """70 corners, fewer than the 80 tracks this initializer once asked for, but more than the 50 points a start
    needs (VAMR parking has about 100, of which 50-80 survive at a third of its frame rate): the start comes from
    them; with fewer than 50 it cannot, and the reference is given up for that reason."""
    def corners(count: int) -> InitConfig:
        return InitConfig(tracks=FeatureTrackConfig(corners=CornerConfig(max_corners=count, min_distance=10.0)))

    result, status, *_ = run_initializer("smooth", init_config=corners(70))
    assert result is not None, status
    assert 50 <= result.details["points"] <= 70
    result, status, *_ = run_initializer("smooth", init_config=corners(45))
    assert result is None and "fewer than the 50 a start needs" in status["reason"]


def test_direct_odometry_tracks_after_the_feature_initializer():
    camera = small_camera(320, 240)
    scene = PlaneScene(seed=2)
    odometry = Odometry(load_config(overrides=["method=direct", "direct.initializer=features"]), camera)
    poses = [smooth_pose(i) for i in range(30)]
    results = [odometry.track(render_frame(scene, camera, i, T)) for i, T in enumerate(poses)]
    first = next(i for i, r in enumerate(results) if r.tracked)
    assert first <= 8  # the coarse initializer needs 10 frames here
    tracked = [r for r in results if r.T_world_cam is not None]
    assert len(tracked) == len(results) - first
    estimated = np.array([r.T_world_cam[:3, 3] for r in tracked])
    truth = np.array([poses[r.frame_index][:3, 3] for r in tracked])
    path = np.sum(np.linalg.norm(np.diff(truth, axis=0), axis=1))
    assert aligned_ate(estimated, truth) < 0.02 * path
    succeeded = [e for r in results for e in r.events if e.kind is EventKind.INITIALIZATION_SUCCEEDED]
    assert len(succeeded) == 1 and succeeded[0].details["model"] in ("H", "F")
    assert succeeded[0].details["points"] >= 50


def test_epipolar_search_improves_the_depths_of_the_selected_pixels():
    errors = {}
    for enabled in (False, True):
        config = InitConfig()
        config.semi_dense.enabled = enabled
        config.photometric_ba.enabled = False  # the depths as the search leaves them (the adjustment refines both)
        result, status, sequence, first, _ = run_initializer("smooth", init_config=config)
        uv = np.round(result.points_uv).astype(int)
        true = 1.0 / sequence[first].depth[uv[:, 1], uv[:, 0]]
        features = status["features_handed_over"]  # the features come first, then the selected pixels
        scale = np.median(true[:features] / result.inverse_depths[:features])
        relative = np.abs(result.inverse_depths * scale - true) / true
        errors[enabled] = np.percentile(relative[features:], 90)
        assert result.inverse_depth_variances is not None and np.all(result.inverse_depth_variances > 0)
    assert errors[True] < 0.75 * errors[False]  # measured: 90th percentile 0.43 -> 0.25
