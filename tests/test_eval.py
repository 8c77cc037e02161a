"""Evaluation: association, Umeyama alignment, ATE and RPE (checked against evo), TUM monoVO drifts, frame drops."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vo_core.errors import InputError
from vo_core.eval import (
    EvalConfig,
    associate,
    ate_per_map,
    associate_timestamps,
    evaluate,
    fit_alignment,
    frame_drop_error,
    frame_drop_error_at,
    rpe_pairs,
    tum_mono_drift,
)
from vo_core.geometry.lie import se3, sim3, sim3_inverse, so3_exp, so3_geodesic_angle
from vo_core.trajectory import Trajectory, read_trajectory, write_trajectory

GROUND_TRUTH_RATE_HZ = 100.0  # motion capture
CAMERA_RATE_HZ = 30.0


def smooth_ground_truth(duration_s: float = 6.0, start_s: float = 1341841873.4151) -> Trajectory:
    """A handheld-like 3D path with turning orientation, at the rate of a motion-capture system."""
    t = np.arange(0.0, duration_s, 1.0 / GROUND_TRUTH_RATE_HZ)
    positions = np.column_stack([np.sin(0.9 * t), 0.6 * np.cos(0.7 * t), 0.3 * np.sin(1.7 * t)])
    rotation_vectors = np.column_stack([0.3 * np.sin(0.5 * t), 0.8 * np.sin(0.3 * t), 0.2 * t])
    return Trajectory(start_s + t, [se3(so3_exp(w), p) for w, p in zip(rotation_vectors, positions)])


def seen_through(trajectory: Trajectory, S_est_gt: np.ndarray) -> Trajectory:
    """The trajectory expressed in another world frame with another scale (as a monocular estimate is)."""
    scale = np.cbrt(np.linalg.det(S_est_gt[:3, :3]))
    poses = trajectory.poses.copy()
    poses[:, :3, :3] = S_est_gt[:3, :3] / scale @ trajectory.poses[:, :3, :3]
    poses[:, :3, 3] = trajectory.positions @ S_est_gt[:3, :3].T + S_est_gt[:3, 3]
    return Trajectory(trajectory.timestamps, poses)


def noisy_estimate(ground_truth: Trajectory, S_est_gt: np.ndarray, seed: int = 3) -> Trajectory:
    """Camera-rate poses at jittered times between the ground truth's, with position and rotation noise."""
    rng = np.random.default_rng(seed)
    times = np.arange(ground_truth.timestamps[0] + 0.05, ground_truth.timestamps[-1] - 0.05, 1.0 / CAMERA_RATE_HZ)
    times = times + rng.uniform(-0.004, 0.004, size=len(times))
    nearest = np.abs(ground_truth.timestamps[None, :] - times[:, None]).argmin(axis=1)
    truth = ground_truth.subset(nearest)
    poses = truth.poses.copy()
    poses[:, :3, 3] += rng.normal(scale=0.02, size=(len(times), 3))
    poses[:, :3, :3] = np.array([so3_exp(rng.normal(scale=0.01, size=3)) @ R for R in poses[:, :3, :3]])
    return seen_through(Trajectory(times, poses), S_est_gt)


SIMILARITY = sim3(0.37, so3_exp(np.array([0.4, -1.1, 2.0])), np.array([3.0, -2.0, 0.5]))


# ----------------------------------------------------------------------------------------- association


def test_association_is_one_to_one_by_smallest_difference():
    # 0.011 is closer to 0.01 than 0.0 is: it gets the pair, 0.0 stays unmatched (not both on the same pose).
    matches = associate_timestamps(np.array([0.0, 0.011, 0.05]), np.array([0.01, 0.049]), max_dt=0.02)
    assert matches.first.tolist() == [1, 2] and matches.second.tolist() == [0, 1]


def test_association_respects_max_difference_and_offset():
    first, second = np.array([1.0, 2.0, 3.0]), np.array([1.5, 2.55, 3.45])
    assert len(associate_timestamps(first, second, max_dt=0.02)) == 0
    shifted = associate_timestamps(first, second, max_dt=0.06, offset=-0.5)  # second + offset is compared
    assert shifted.first.tolist() == [0, 1, 2] and shifted.second.tolist() == [0, 1, 2]


def test_no_overlap_is_an_input_error():
    truth = smooth_ground_truth()
    later = Trajectory(truth.timestamps + 100.0, truth.poses)
    with pytest.raises(InputError, match="no estimated timestamp within 0.02 s"):
        evaluate(later, truth)


# ------------------------------------------------------------------------------------------- alignment


def test_sim3_alignment_recovers_the_similarity_and_se3_keeps_the_scale():
    truth = smooth_ground_truth()
    estimate = seen_through(truth, SIMILARITY)
    alignment = fit_alignment(estimate, truth, "sim3")
    np.testing.assert_allclose(alignment.transform, sim3_inverse(SIMILARITY), atol=1e-9)
    assert alignment.scale == pytest.approx(1 / 0.37)
    np.testing.assert_allclose(alignment.apply(estimate).poses, truth.poses, atol=1e-9)
    assert fit_alignment(estimate, truth, "se3").scale == 1.0
    assert evaluate(estimate, truth, align="none")["ate"]["rmse"] > 1.0


def test_aligning_the_first_poses_only_leaves_the_later_error_visible():
    truth = smooth_ground_truth()
    estimate = seen_through(truth, SIMILARITY)
    poses = estimate.poses.copy()
    poses[300:, :3, 3] += [0.0, 0.0, 0.1]  # the estimate jumps after pose 300
    jumped = Trajectory(estimate.timestamps, poses)
    alignment = fit_alignment(jumped, truth, "sim3", first_n=300)
    errors = np.linalg.norm(alignment.apply(jumped).positions - truth.positions, axis=1)
    np.testing.assert_allclose(errors[:300], 0.0, atol=1e-9)
    np.testing.assert_allclose(errors[300:], 0.1 / 0.37, rtol=1e-9)


def test_sim3_of_a_camera_that_does_not_move_is_refused():
    truth = smooth_ground_truth()
    still = Trajectory(truth.timestamps, np.broadcast_to(np.eye(4), truth.poses.shape))
    with pytest.raises(InputError, match="do not move"):
        fit_alignment(still, truth, "sim3")


# -------------------------------------------------------------------------------------- ATE and RPE


def test_ate_of_a_known_offset():
    truth = smooth_ground_truth()
    poses = truth.poses.copy()
    poses[::2, :3, 3] += [0.3, 0.0, 0.0]
    poses[1::2, :3, 3] += [0.0, 0.1, 0.0]
    ate = evaluate(Trajectory(truth.timestamps, poses), truth, align="none")["ate"]
    assert ate["max"] == pytest.approx(0.3) and ate["min"] == pytest.approx(0.1)
    assert ate["rmse"] == pytest.approx(np.sqrt((0.09 + 0.01) / 2)) and ate["mean"] == pytest.approx(0.2)


def test_a_run_of_two_maps_is_judged_map_by_map():
    """A run that began a second map 3 s in, at another place and scale (a monocular restart): one Sim(3) over both
    leaves metres of error, one per map leaves each map's own (here none); the maps' errors pooled into one RMSE."""
    truth = smooth_ground_truth()
    second = truth.timestamps >= truth.timestamps[0] + 3.0
    poses = seen_through(truth, SIMILARITY).poses
    poses[second] = seen_through(truth.subset(np.flatnonzero(second)),
                                 sim3(2.5, so3_exp(np.array([0.0, 0.5, 0.0])), np.array([1.0, 0.0, 0.0]))).poses
    estimate = Trajectory(truth.timestamps, poses)
    start = [truth.timestamps[np.argmax(second)]]
    assert evaluate(estimate, truth)["ate"]["rmse"] > 0.1
    ate, maps, poses_judged = ate_per_map(estimate, truth, np.array(start))
    assert ate == pytest.approx(0.0, abs=1e-9) and maps == 2 and poses_judged == len(truth)
    assert ate_per_map(estimate, truth, np.array([]))[0] == pytest.approx(evaluate(estimate, truth)["ate"]["rmse"])
    # A map too short to align (2 poses) is left out.
    _, maps, poses_judged = ate_per_map(estimate, truth, np.array([truth.timestamps[-2]]))
    assert maps == 1 and poses_judged == len(truth) - 2


def test_rpe_pairs_in_frames_and_metres():
    steps = np.arange(20) * 0.1  # a straight line, 0.1 m per pose
    line = Trajectory(np.arange(20.0), [se3(np.eye(3), np.array([x, 0.0, 0.0])) for x in steps])
    first, second = rpe_pairs(line, 3, "frames")
    assert first.tolist() == list(range(17)) and (second - first).tolist() == [3] * 17
    first, second = rpe_pairs(line, 0.45, "m")
    assert first.tolist() == list(range(15)) and (second - first).tolist() == [5] * 15


def test_rpe_of_a_constant_rotation_error_per_frame():
    truth = smooth_ground_truth(duration_s=1.0)
    extra_turn = se3(so3_exp(np.array([0.0, 0.0, np.radians(0.5)])), np.zeros(3))
    poses = truth.poses.copy()
    for i in range(1, len(poses)):  # each step is the true motion, then 0.5 degrees more
        poses[i] = poses[i - 1] @ np.linalg.inv(truth.poses[i - 1]) @ truth.poses[i] @ extra_turn
    rpe = evaluate(Trajectory(truth.timestamps, poses), truth, align="se3")["rpe"]
    assert rpe["pairs"] == len(truth) - 1
    np.testing.assert_allclose([rpe["rotation_deg"]["min"], rpe["rotation_deg"]["max"]], 0.5, atol=1e-9)


@pytest.mark.parametrize("align", ["sim3", "se3"])
def test_ate_and_rpe_agree_with_evo_on_the_same_files(tmp_path, align):
    pytest.importorskip("evo.core.metrics", reason="evo is not installed")
    from evo.core import metrics, sync
    from evo.tools import file_interface

    truth = smooth_ground_truth()
    estimate = noisy_estimate(truth, SIMILARITY if align == "sim3" else sim3(1.0, SIMILARITY[:3, :3] / 0.37, [1, 2, 3]))
    write_trajectory(tmp_path / "gt.tum", truth, "tum")
    write_trajectory(tmp_path / "est.tum", estimate, "tum")
    ours = evaluate(read_trajectory(tmp_path / "est.tum"), read_trajectory(tmp_path / "gt.tum"), align=align)

    reference = file_interface.read_tum_trajectory_file(tmp_path / "gt.tum")
    theirs = file_interface.read_tum_trajectory_file(tmp_path / "est.tum")
    reference, theirs = sync.associate_trajectories(reference, theirs, max_diff=0.02)
    theirs.align(reference, correct_scale=align == "sim3")
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((reference, theirs))
    evo_ate = ape.get_all_statistics()

    assert ours["matched_poses"] == theirs.num_poses > 150
    for statistic in ("rmse", "mean", "median", "std", "min", "max"):
        assert ours["ate"][statistic] == pytest.approx(evo_ate[statistic], abs=1e-6), statistic
    for relation, key in ((metrics.PoseRelation.translation_part, "translation"),
                          (metrics.PoseRelation.rotation_angle_deg, "rotation_deg")):
        rpe = metrics.RPE(relation, delta=1, all_pairs=True)
        rpe.process_data((reference, theirs))
        assert ours["rpe"][key]["rmse"] == pytest.approx(rpe.get_statistic(metrics.StatisticsType.rmse), abs=1e-6)


# ------------------------------------------------------------------------------------ TUM monoVO drifts


def test_drifts_recover_the_similarity_between_start_and_end():
    truth = smooth_ground_truth()
    half = len(truth) // 2
    S_start = sim3(2.0, so3_exp(np.array([0.1, 0.2, 0.3])), np.array([1.0, 0.0, 0.0]))
    S_end = sim3(2.5, so3_exp(np.array([0.0, 0.0, np.radians(10)])) @ S_start[:3, :3] / 2.0, np.array([1.0, 0.4, 0.0]))
    # The estimate is the truth seen through S_start^-1 over the first half and S_end^-1 over the second.
    estimate = Trajectory(truth.timestamps, np.concatenate([
        seen_through(truth.subset(np.arange(half)), sim3_inverse(S_start)).poses,
        seen_through(truth.subset(np.arange(half, len(truth))), sim3_inverse(S_end)).poses,
    ]))
    start, end = np.arange(0, 100), np.arange(len(truth) - 100, len(truth))
    drift = tum_mono_drift(estimate, (estimate.subset(start), truth.subset(start)),
                           (estimate.subset(end), truth.subset(end)))
    assert drift.scale_drift == pytest.approx(2.5 / 2.0)
    assert drift.rotation_drift_deg == pytest.approx(10.0)
    T_drift = S_end @ sim3_inverse(S_start)
    assert drift.translation_drift == pytest.approx(np.linalg.norm(T_drift[:3, 3]))
    gap = (estimate.positions @ (S_start - S_end)[:3, :3].T + (S_start - S_end)[:3, 3])
    assert drift.alignment_error == pytest.approx(np.sqrt(np.mean(np.sum(gap**2, axis=1))))


def test_evaluate_takes_the_segments_of_a_ground_truth_with_a_gap():
    truth = smooth_ground_truth()
    estimate = seen_through(truth, SIMILARITY)
    poses = estimate.poses.copy()
    poses[len(truth) // 2:, :3, 3] += [0.05, 0.0, 0.0]  # the end is off by a translation (in estimate units)
    estimate = Trajectory(truth.timestamps, poses)
    # TUM monoVO style: ground truth only over the first and last second.
    ends = np.flatnonzero((truth.timestamps < truth.timestamps[0] + 1) | (truth.timestamps > truth.timestamps[-1] - 1))
    drift = evaluate(estimate, truth.subset(ends), config=EvalConfig())["drift"]
    assert drift["scale_drift"] == pytest.approx(1.0) and drift["rotation_drift_deg"] == pytest.approx(0.0, abs=1e-6)
    assert drift["alignment_error"] == pytest.approx(0.05 / 0.37)


# ---------------------------------------------------------------------------------------- frame drops


def test_frame_drop_error_in_percent_after_the_alignment_scale():
    truth_before = se3(np.eye(3), np.zeros(3))
    truth_after = se3(so3_exp(np.array([0.0, np.radians(20), 0.0])), np.array([1.0, 0.0, 0.0]))
    estimate_before = se3(so3_exp(np.array([0.3, 0.0, 0.0])), np.array([5.0, 5.0, 5.0]))
    turn = so3_exp(np.array([0.0, 0.0, np.radians(22)]))  # 22 degrees about another axis: only the angle counts
    estimate_after = se3(estimate_before[:3, :3] @ turn, np.array([5.0, 5.45, 5.0]))
    error = frame_drop_error(estimate_before, estimate_after, truth_before, truth_after, scale=2.0)
    assert error.translation == pytest.approx(0.9) and error.translation_percent == pytest.approx(10.0)
    assert error.true_rotation_deg == pytest.approx(20.0) and error.rotation_percent == pytest.approx(10.0)


def test_frame_drop_error_looks_up_the_poses_by_time():
    truth = smooth_ground_truth()
    estimate = seen_through(truth, SIMILARITY)
    before, after = truth.timestamps[100], truth.timestamps[160]
    error = frame_drop_error_at(estimate, truth, before, after + 0.001, scale=1 / 0.37)
    assert error.translation_percent == pytest.approx(0.0, abs=1e-9) and error.rotation_percent < 1e-6
    assert error.true_translation == pytest.approx(np.linalg.norm(truth.positions[160] - truth.positions[100]))
    with pytest.raises(InputError, match="no pose within 0.02 s"):
        frame_drop_error_at(estimate, truth, before, truth.timestamps[-1] + 1.0)


def test_quaternion_angle_is_the_geodesic_angle():
    rng = np.random.default_rng(1)
    for _ in range(20):
        R_i, R_j = so3_exp(rng.normal(size=3)), so3_exp(rng.normal(size=3))
        pose_i, pose_j = se3(R_i, np.zeros(3)), se3(R_j, np.zeros(3))
        angle = frame_drop_error(pose_i, pose_j, pose_i, pose_j).rotation_deg
        assert angle == pytest.approx(np.degrees(so3_geodesic_angle(R_i, R_j)), abs=1e-5)


# ------------------------------------------------------------------------------------------ the report


def test_evaluate_gives_json_with_what_metrics_json_reports():
    truth = smooth_ground_truth()
    result = evaluate(noisy_estimate(truth, SIMILARITY), truth)
    assert json.loads(json.dumps(result)) == result
    assert result["align"] == "sim3" and result["scale"] == pytest.approx(1 / 0.37, rel=0.02)
    assert result["matched_poses"] == result["estimated_poses"] and result["ground_truth_poses"] == len(truth)
    assert 0.015 < result["ate"]["rmse"] < 0.06  # noise of 0.02 m per axis: ~0.035 m
    assert set(result["rpe"]) >= {"translation", "rotation_deg", "pairs"}
    assert "drift" not in result  # ground truth over the whole run: no segments unless asked for
    lost_a_while = noisy_estimate(truth, SIMILARITY).subset(np.r_[0:50, 120:170])
    assert "drift" not in evaluate(lost_a_while, truth)  # a gap in the estimate is not a TUM monoVO segment
    segments_asked = evaluate(noisy_estimate(truth, SIMILARITY), truth, config=EvalConfig(drift_segment_fraction=0.3))
    assert segments_asked["drift"]["scale_drift"] == pytest.approx(1.0, abs=0.1)
    matched_estimate, matched_truth = associate(noisy_estimate(truth, SIMILARITY), truth)
    assert len(matched_estimate) == len(matched_truth) == result["matched_poses"]
