"""DirectOdometry end to end on rendered sequences: initialization, tracking accuracy, failure reporting."""

from __future__ import annotations

import numpy as np
import pytest

from test_direct_support import PlaneScene, aligned_ate, pose, render_frame, small_camera
from vo_core.config import load_config
from vo_core.direct.config import DirectConfig
from vo_core.direct.coarse_initializer import CoarseInitializer
from vo_core.direct.immature_point import host_pattern
from vo_core.direct.odometry import DirectOdometry
from vo_core.direct.pyramid import ImagePyramid
from vo_core.errors import InputError
from vo_core.events import EventKind, FrameResult
from vo_core.synthetic import make_sequence
from vo_core.system import Odometry

CAMERA = small_camera(320, 240)


def smooth_pose(i: int) -> np.ndarray:
    """A hand-held-like sway in front of the wall: 0.6 m of path over 50 frames."""
    s = i / 30.0
    return pose(
        (0.03 * np.sin(2.0 * s), 0.05 * np.sin(1.3 * s), 0.01 * s),
        (0.4 * np.sin(1.5 * s), 0.1 * np.sin(2.1 * s), 0.3 * np.sin(s)),
    )


def direct_system(seed=0) -> Odometry:
    return Odometry(load_config(overrides=["method=direct", f"seed={seed}"]), CAMERA)


def run(poses, seed=0):
    scene = PlaneScene(seed=2)
    odometry = direct_system(seed)
    results = [odometry.track(render_frame(scene, CAMERA, i, T)) for i, T in enumerate(poses)]
    return odometry.direct, results


@pytest.fixture(scope="module")
def smooth_run():
    poses = [smooth_pose(i) for i in range(50)]
    odometry, results = run(poses)
    return poses, odometry, results


def test_smooth_sequence_is_tracked_with_small_ate(smooth_run):
    poses, odometry, results = smooth_run
    tracked = [r for r in results if r.T_world_cam is not None]
    first = next(i for i, r in enumerate(results) if r.tracked)
    assert first <= 15  # DSO snaps after enough translation, then waits 5 frames
    assert len(tracked) == len(results) - first  # no frame lost after initialization
    estimated = np.array([r.T_world_cam[:3, 3] for r in tracked])
    truth = np.array([poses[r.frame_index][:3, 3] for r in tracked])
    path = np.sum(np.linalg.norm(np.diff(truth, axis=0), axis=1))
    assert aligned_ate(estimated, truth) < 0.02 * path  # measured: 0.6% of the path
    kinds = [e.kind for r in results for e in r.events]
    assert kinds.count(EventKind.INITIALIZATION_STARTED) == 1
    assert kinds.count(EventKind.INITIALIZATION_SUCCEEDED) == 1
    assert EventKind.TRACKING_FAILED not in kinds
    assert sum(r.is_keyframe for r in results) >= 3


def test_frame_results_carry_what_the_system_needs(smooth_run):
    _, odometry, results = smooth_run
    tracked = [r for r in results[-10:] if r.tracked]
    assert all(r.rmse_before is not None and r.rmse_after <= r.rmse_before * 1.1 for r in tracked)
    assert all(len(r.points_2d) > 500 and CAMERA.in_image(r.points_2d).all() for r in tracked)
    assert all("track" in r.timings_ms for r in tracked)
    keyframe = odometry.newest_keyframe
    assert keyframe.image.dtype == np.uint8 and len(keyframe.reference_idepth) > 500
    assert keyframe.immature is not None and len(keyframe.immature) > 500
    snapshot = odometry.map_snapshot()
    assert len(snapshot.direct_points_world) == len(snapshot.direct_inverse_depths) > 500
    assert keyframe.frame_index in snapshot.keyframe_poses


def test_only_the_newest_keyframe_keeps_its_gradient_images(smooth_run):
    """Issue 17: the older keyframes keep their intensities; their points carry the host pattern the window reads."""
    _, odometry, _ = smooth_run
    *older, newest = odometry.keyframes
    assert older and not any(level.holds_packed for keyframe in older for level in keyframe.pyramid.levels)
    assert newest.pyramid[0].holds_packed
    for keyframe in older:  # the newest hosts only immature points yet
        color, grad_sq = host_pattern(keyframe.pyramid[0], keyframe.active_uv)  # makes the packed image again
        assert len(keyframe.active_idepth) > 0
        np.testing.assert_array_equal(keyframe.active_color, color)
        np.testing.assert_array_equal(keyframe.active_grad_sq, grad_sq)


def test_a_jump_is_reported_not_silently_tracked():
    poses = [smooth_pose(i) for i in range(18)]
    # The camera is teleported: turned by 25 degrees and moved sideways.
    poses += [pose((0.0, 0.45, 0.0), (0.6, 0.0, 0.2)) @ smooth_pose(i) for i in range(18, 20)]
    _, results = run(poses)
    assert all(r.tracked for r in results[12:18])  # tracking before the jump
    jump = results[18]
    diverged = jump.rmse_before is not None and jump.rmse_after is not None and jump.rmse_after / jump.rmse_before > 1.1
    failed = any(e.kind is EventKind.TRACKING_FAILED for e in jump.events)
    assert failed or diverged
    if failed:
        assert jump.T_world_cam is None
        assert any(e.kind is EventKind.REINITIALIZATION for e in jump.events)


def test_coarse_initializer_recovers_motion_direction_and_depth():
    scene = PlaneScene(seed=1)
    config = DirectConfig()
    initializer = CoarseInitializer(config.coarse_init, config.selector, 9.0, 144.0, 2000, seed=0)
    poses = [pose((0.0, 0.002 * i, 0.0), (0.02 * i, 0.0, 0.005 * i)) for i in range(20)]
    image, depth = scene.render(CAMERA, poses[0])
    initializer.set_first(0, ImagePyramid(image, CAMERA, config.pyramid), None)
    for i in range(1, 20):
        result = initializer.track(i, ImagePyramid(scene.render(CAMERA, poses[i])[0], CAMERA, config.pyramid), None)
        if result is not None:
            break
    assert result is not None and result.second_frame_index <= 15
    assert np.mean(result.inverse_depths) == pytest.approx(1.0, rel=0.05)  # DSO's scale: mean inverse depth 1
    uv = result.points_uv.astype(int)
    true_idepth = 1.0 / depth[uv[:, 1], uv[:, 0]]
    scale = np.median(true_idepth / result.inverse_depths)
    assert np.median(np.abs(result.inverse_depths * scale - true_idepth) / true_idepth) < 0.03
    t_est, t_true = result.T_first_second[:3, 3], poses[result.second_frame_index][:3, 3]
    assert np.dot(t_est, t_true) / np.linalg.norm(t_est) / np.linalg.norm(t_true) > 0.99
    assert np.linalg.norm(t_est / scale - t_true) < 0.05 * np.linalg.norm(t_true)


def test_system_runs_the_direct_half_and_rejects_unknown_initializer():
    odometry = direct_system()
    assert odometry.front_end is None and isinstance(odometry.direct, DirectOdometry)
    with pytest.raises(InputError, match="direct.initializer"):
        Odometry(load_config(overrides=["method=direct", "direct.initializer=magic"]), CAMERA)


def test_wrong_image_size_is_an_input_error():
    frame = render_frame(PlaneScene(seed=0), small_camera(160, 120), 0, pose())
    with pytest.raises(InputError, match="frame 0"):
        direct_system().track(frame)


def test_tracking_changes_nothing_until_the_frame_is_accepted(smooth_run):
    _, odometry, results = smooth_run
    frame = odometry.prepare(render_frame(PlaneScene(seed=2), CAMERA, 50, smooth_pose(50)))
    history, last_rmse = list(odometry.history), odometry.last_rmse.copy()
    first, second = odometry.track(frame), odometry.track(frame)
    np.testing.assert_array_equal(first.T_world_cam, second.T_world_cam)
    assert odometry.history == history and np.array_equal(odometry.last_rmse, last_rmse, equal_nan=True)
    assert first.converged and first.rmse_after <= first.rmse_before and first.hypotheses_tried >= 1


def test_tracking_from_a_given_prior_continues_the_trajectory(smooth_run):
    poses, odometry, results = smooth_run
    frame = odometry.prepare(render_frame(PlaneScene(seed=2), CAMERA, 50, smooth_pose(50)))
    last = results[-1].T_world_cam
    tracking = odometry.track(frame, last)
    assert tracking.from_prior and tracking.hypotheses_tried == 1
    result = FrameResult(50, frame.timestamp, None, tracked=False)
    odometry.accept(frame, tracking, result)
    assert result.tracked and np.array_equal(odometry.last_pose, result.T_world_cam)
    step_estimated = np.linalg.norm(result.T_world_cam[:3, 3] - last[:3, 3])
    step_true = np.linalg.norm(poses[49][:3, 3] - smooth_pose(50)[:3, 3])
    scale = np.linalg.norm(results[-1].T_world_cam[:3, 3] - results[-10].T_world_cam[:3, 3]) / np.linalg.norm(
        poses[49][:3, 3] - poses[40][:3, 3]
    )
    assert step_estimated == pytest.approx(step_true * scale, rel=0.3)
    assert result.rmse_after <= result.rmse_before


def test_window_energies_are_photometric_and_the_priors_term_is_reported_apart():
    """A sum of robust squared residuals is never negative; the marginalization prior's term (a quadratic about its
    linearization point, its constant dropped as DSO drops it) may be, and is reported apart once keyframes have
    been marginalized."""
    sequence = make_sequence("smooth", num_frames=70, seed=0, width=320, height=240)
    odometry = Odometry(load_config(overrides=["method=direct"]), sequence.camera)
    events = [(r.frame_index, e) for r in map(odometry.track, sequence) for e in r.events]
    optimized = [(frame, e.details) for frame, e in events if e.kind is EventKind.WINDOW_OPTIMIZED]
    assert optimized and all(d["energy_before"] >= 0 and d["energy_after"] >= 0 for _, d in optimized)
    marginalized = [frame for frame, e in events if e.kind is EventKind.KEYFRAME_MARGINALIZED]
    assert marginalized
    assert any(d["prior_energy_after"] != 0 for frame, d in optimized if frame > marginalized[0])
