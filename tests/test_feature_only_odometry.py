"""``--method features`` (ORB-SLAM2's tracking and local mapping as odometry) on rendered sequences: accuracy against
the truth, its events, a new map's probation, relocalization after a jump back to a seen place; and the sparse Schur
complement of the local bundle adjustment against the dense one."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from bundle_adjustment_window import CAMERA as BA_CAMERA
from bundle_adjustment_window import make_window
from posed import posed_trajectory

from vo_core.config import load_config
from vo_core.eval.metrics import evaluate
from vo_core.events import EventKind
from vo_core.geometry.bundle_adjustment import BundleAdjustmentSettings, adjust_window
from vo_core.init.epipolar_check import EpipolarCheck
from vo_core.synthetic import make_sequence
from vo_core.system import IMPLEMENTED_METHODS, Odometry
from vo_core.trajectory import Trajectory

WIDTH, HEIGHT = 320, 240


def run(frames, camera, overrides=()):
    odometry = Odometry(load_config(overrides=["method=features", *overrides]), camera)
    return [odometry.track(frame) for frame in frames], odometry


def ate(results, ground_truth) -> float:
    estimate = posed_trajectory(results)
    return evaluate(estimate, ground_truth)["ate"]["rmse"]


def path_length(sequence) -> float:
    return float(np.sum(np.linalg.norm(np.diff(sequence.ground_truth.positions, axis=0), axis=1)))


def kinds(results) -> list[EventKind]:
    return [event.kind for result in results for event in result.events]


def test_features_is_an_implemented_method():
    assert "features" in IMPLEMENTED_METHODS


@pytest.fixture(scope="module")
def smooth():
    sequence = make_sequence("smooth", 50, seed=0, width=WIDTH, height=HEIGHT)
    results, odometry = run(list(sequence), sequence.camera)
    return sequence, results, odometry


def test_smooth_sequence_is_tracked_within_a_small_share_of_its_path(smooth):
    sequence, results, _ = smooth
    posed = [r for r in results if r.T_world_cam is not None]
    first = posed[0].frame_index
    assert first <= 20
    assert all(r.T_world_cam is not None for r in results[first:])  # nothing lost once started
    assert ate(results, sequence.ground_truth) < 0.02 * path_length(sequence)  # measured: 1.1 % of 0.87 m


def test_the_run_reports_its_start_keyframes_local_mapping_and_culling(smooth):
    _, results, odometry = smooth
    happened = kinds(results)
    for kind in (EventKind.INITIALIZATION_STARTED, EventKind.INITIALIZER_MODEL, EventKind.INITIALIZATION_SUCCEEDED,
                 EventKind.KEYFRAME_ADDED, EventKind.WINDOW_OPTIMIZED):
        assert kind in happened
    assert EventKind.TRACKING_FAILED not in happened
    keyframes = [r for r in results if r.is_keyframe]
    assert len(keyframes) >= 5 and all("local_mapping" in r.timings_ms for r in keyframes)
    added = [e.details for r in results for e in r.events if e.kind is EventKind.KEYFRAME_ADDED]
    assert sum(d["new_points"] for d in added) > 500  # triangulation with the covisible keyframes
    snapshot = odometry.map_snapshot()
    assert len(snapshot.feature_points_world) > 300 and len(snapshot.keyframe_poses) >= 3


def test_a_right_start_passes_its_probation(smooth):
    """The start witness measured the new map's first keyframes and found nothing against them."""
    _, results, odometry = smooth
    assert EventKind.INITIALIZATION_REJECTED not in kinds(results)
    assert odometry.front_end.probation is None  # over: the witness answered
    assert sum(r.is_keyframe for r in results) >= 6


def test_a_start_the_witness_refuses_is_taken_back(smooth, monkeypatch):
    """Where the witness contradicts the start at the new map's sixth keyframe, the map goes: every pose it gave is
    retracted (the first frame's by ``first_frame``), that frame has none, and a new start begins there and
    poses the frames after it."""
    sequence, _, _ = smooth
    answers = []

    def refuse_the_first_start(self, keyframes, camera):
        answers.append([k.frame_index for k in keyframes])
        reason = "the ORB matches of 3 of 3 keyframe pairs contradict the start's motion" if len(answers) == 1 else None
        return reason, {"epipolar_pairs": 3, "epipolar_disagreeing": 3 if reason else 0}

    monkeypatch.setattr(EpipolarCheck, "disagreement", refuse_the_first_start)
    results, _ = run(list(sequence), sequence.camera)
    rejected = [e for r in results for e in r.events if e.kind is EventKind.INITIALIZATION_REJECTED]
    assert len(rejected) == 1 and "contradict" in rejected[0].details["reason"]
    refused_at = rejected[0].frame_index
    # the map's first six keyframes but those culled as redundant meanwhile, its first and this one among them
    assert 3 <= len(answers[0]) <= 6 and answers[0][-1] == refused_at
    started = [e for r in results for e in r.events if e.kind is EventKind.INITIALIZATION_SUCCEEDED]
    assert answers[0][0] == started[0].details["first_frame"]
    assert rejected[0].details["first_frame"] == started[0].details["first_frame"]
    posed_in_it = [r.timestamp for r in results if started[0].frame_index <= r.frame_index < refused_at]
    assert all(r.T_world_cam is not None for r in results[started[0].frame_index:refused_at])
    assert rejected[0].details["retracted"] == posed_in_it
    assert results[refused_at].T_world_cam is None
    assert len(started) == 2 and started[1].details["first_frame"] == refused_at
    assert all(r.T_world_cam is not None for r in results[started[1].frame_index:])
    assert rejected[0].details["epipolar_disagreeing"] == 3  # the witness's measures join the event


def test_a_young_map_lost_is_taken_back_with_its_poses(smooth):
    """The view goes dark (a little sensor noise) two keyframes after the start: the map is lost with 4 keyframes,
    fewer than ORB-SLAM2 keeps when lost, so it starts over, and every pose it gave is retracted, as ORB-SLAM2's reset
    clears its trajectory with the map (the first frame's by ``first_frame``)."""
    sequence, clean, _ = smooth
    frames = list(sequence)
    started = next(e for r in clean for e in r.events if e.kind is EventKind.INITIALIZATION_SUCCEEDED)
    keyframes_after = [r.frame_index for r in clean if r.is_keyframe and r.frame_index > started.frame_index]
    dark_from = keyframes_after[1] + 1
    rng = np.random.default_rng(0)
    dark = [dataclasses.replace(f, image=rng.integers(0, 3, f.image.shape, dtype=np.uint8))
            for f in frames[dark_from:dark_from + 3]]
    results, _ = run(frames[:dark_from] + dark, sequence.camera)
    lost_at = next(r.frame_index for r in results if EventKind.TRACKING_FAILED in kinds([r]))
    rejected = [e for r in results for e in r.events if e.kind is EventKind.INITIALIZATION_REJECTED]
    assert lost_at == dark_from and len(rejected) == 1 and rejected[0].frame_index == lost_at
    assert "lost with few keyframes" in rejected[0].details["reason"] and rejected[0].details["keyframes"] < 6
    assert rejected[0].details["first_frame"] == started.details["first_frame"]
    assert rejected[0].details["retracted"] == [r.timestamp for r in results[started.frame_index:lost_at]]
    assert all(r.T_world_cam is not None for r in results[started.frame_index:lost_at])
    assert EventKind.REINITIALIZATION in kinds(results[lost_at:lost_at + 1])


def test_same_input_same_trajectory(smooth):
    sequence, results, _ = smooth
    again, _ = run(list(sequence)[:30], sequence.camera)
    for first, second in zip(results[:30], again):
        assert (first.T_world_cam is None) == (second.T_world_cam is None)
        if first.T_world_cam is not None:
            np.testing.assert_array_equal(first.T_world_cam, second.T_world_cam)


@pytest.mark.parametrize("preset, share", [("planar", 0.05), ("forward", 0.05)])
def test_planar_and_forward_sequences_are_tracked(preset, share):
    """60 frames: moving forward, the homography's and the essential matrix's motions point up to 55 degrees apart
    until frame 22 (the epipole in the image leaves the translation weakly determined), and the start waits for
    views that decide (two_view.max_motion_disagreement_deg)."""
    sequence = make_sequence(preset, 60, seed=0, width=WIDTH, height=HEIGHT)
    results, _ = run(list(sequence), sequence.camera)
    posed = [r for r in results if r.T_world_cam is not None]
    assert len(posed) >= 30
    assert ate(results, sequence.ground_truth) < share * path_length(sequence)


def test_a_jump_back_to_a_seen_place_is_relocalized(smooth):
    """After 50 frames the view goes black (tracking is lost), then comes back at frame 20's place: the global
    bag-of-words search brings tracking back there, in the same map."""
    sequence, _, _ = smooth
    frames = list(sequence)
    black = [dataclasses.replace(f, image=np.zeros_like(f.image)) for f in frames[47:50]]
    played = frames[:47] + black + frames[20:30]
    results, _ = run([f if i < 50 else _played_again(f, 50 - 20) for i, f in enumerate(played)], sequence.camera)
    happened = kinds(results[47:])
    assert EventKind.TRACKING_FAILED in happened and EventKind.RECOVERY_SUCCEEDED in happened
    assert EventKind.REINITIALIZATION not in happened
    assert sum(r.T_world_cam is not None for r in results[50:]) >= 7
    # Every posed frame, the revisited ones included, one Sim(3) away from the truth of the place it shows.
    posed = [(r.T_world_cam, f.T_world_cam) for r, f in zip(results, played) if r.T_world_cam is not None]
    times = np.arange(len(posed), dtype=float)
    estimate = Trajectory(times, np.array([estimated for estimated, _ in posed]))
    truth = Trajectory(times, np.array([true for _, true in posed]))
    assert evaluate(estimate, truth)["ate"]["rmse"] < 0.02 * path_length(sequence)  # measured: 1.5 %


def test_a_map_lost_for_longer_than_the_relocalization_time_is_left_for_a_new_one(smooth):
    """After 30 frames the view goes dark for 8 frames (0.27 s), then comes back at frame 35's place. Allowed 0.2 s of
    relocalization (ORB-SLAM3 allows 3 s), the odometry begins a new map at the last pose, reported, and poses the
    frames that follow it, consistent with one another; allowed the default 3 s, the same frames are relocalized in
    the old map instead."""
    sequence, _, _ = smooth
    frames = list(sequence)
    # Dark frames as a sensor gives them (a little noise): black ones repeat bit for bit, and a repeated image is no
    # frame to relocalize on (Odometry._repeats_previous).
    rng = np.random.default_rng(0)
    black = [dataclasses.replace(f, image=rng.integers(0, 3, f.image.shape, dtype=np.uint8)) for f in frames[30:38]]
    played = frames[:30] + black + frames[38:]
    results, _ = run(played, sequence.camera, ["features.odometry.tracking.new_map_after_lost_s=0.2"])
    new_maps = [e for r in results for e in r.events if e.kind is EventKind.REINITIALIZATION]
    assert len(new_maps) == 1 and "a new map" in new_maps[0].details["reason"]
    begun = new_maps[0].frame_index
    assert 30 + 6 <= begun < 38  # after 0.2 s of failed relocalizations, on a dark frame
    after = [r for r in results if r.frame_index > begun and r.T_world_cam is not None]
    assert len(after) >= 8
    estimate = posed_trajectory(after)
    truth = Trajectory(estimate.timestamps, np.array([sequence.ground_truth.poses[r.frame_index] for r in after]))
    assert evaluate(estimate, truth)["ate"]["rmse"] < 0.02 * path_length(sequence)
    waited, _ = run(played, sequence.camera)
    assert EventKind.REINITIALIZATION not in kinds(waited) and EventKind.RECOVERY_SUCCEEDED in kinds(waited[38:])


def test_a_stalled_camera_gets_no_pose_and_says_so(smooth):
    """Frames that repeat the previous image bit for bit (a stalled driver) get no pose and a ``frame_repeated``
    event, as in fdmo; tracking goes on with the next new image."""
    sequence, _, _ = smooth
    frames = list(sequence)
    stalled = [dataclasses.replace(frames[29], index=frames[29].index + 1000 + k,
                                   timestamp=frames[29].timestamp + (k + 1) / 90.0) for k in range(2)]
    results, _ = run(frames[:30] + stalled + frames[30:40], sequence.camera)
    assert results[29].T_world_cam is not None
    for result in results[30:32]:
        assert result.T_world_cam is None and [e.kind for e in result.events] == [EventKind.FRAME_REPEATED]
    assert all(r.T_world_cam is not None for r in results[32:])


def _played_again(frame, frames_later: int):
    """The same image shown again ``frames_later`` frames later (a jump back to a seen place, time going on)."""
    return dataclasses.replace(frame, index=frame.index + 1000, timestamp=frame.timestamp + frames_later / 30.0)


@pytest.mark.parametrize("level_weights", [False, True])
def test_the_sparse_schur_complement_takes_the_dense_step(level_weights):
    """The local adjustment's compiled step (``sparse_schur``) is the dense Schur complement's, held poses and each
    observation's pyramid-level information included."""
    _, _, problem, _ = make_window(seed=1, outliers=40)
    if level_weights:
        levels = np.random.default_rng(0).integers(0, 8, len(problem.observation_uv))
        problem.observation_information = 1.2 ** (-2.0 * levels)
    assert problem.fixed.any() and not problem.fixed.all()
    dense = adjust_window(BA_CAMERA, problem, BundleAdjustmentSettings())
    sparse = adjust_window(BA_CAMERA, problem, BundleAdjustmentSettings(sparse_schur=True))
    np.testing.assert_allclose(sparse.poses_world_cam, dense.poses_world_cam, atol=1e-9)
    np.testing.assert_allclose(sparse.points_world, dense.points_world, atol=1e-8)
