"""The experiments of FDMO section 5 (app/experiments): the frame-drop protocol and its % errors on scripted methods
with known motion, the end of a sweep at a failure, the two-loop drifts of exact and drifted trajectories, a TUM
monoVO folder's start and end segments, and the same numbers from the same command run twice."""

from __future__ import annotations

import numpy as np
import pytest

from app.cli import main
from app.experiments.common import Setup, truth_at_frames
from app.experiments.frame_drop import Protocol, sweep
from app.experiments.timing import process_samples, table
from app.experiments.two_loop import estimated_trajectory, loop_shift, loop_spans, looped_truth
from app.pipeline import open_source
from vo_core.config import DatasetConfig, load_config
from vo_core.eval import EvalConfig, ground_truth_gap_end, loop_drifts
from vo_core.events import Event, EventKind, FrameResult
from vo_core.geometry.lie import se3, sim3, sim3_inverse, so3_exp
from vo_core.synthetic import make_sequence
from vo_core.trajectory import Trajectory

TINY = {"width": 64, "height": 48}  # the scripted methods never look at the images
S_EST_GT = sim3(0.37, so3_exp(np.array([0.4, -1.1, 2.0])), np.array([3.0, -2.0, 0.5]))  # a monocular world


def seen_through(T_world_cam: np.ndarray, S: np.ndarray) -> np.ndarray:
    """The pose in the world frame and scale of the similarity S (positions S p, orientations R_S R)."""
    scale = np.cbrt(np.linalg.det(S[:3, :3]))
    return se3(S[:3, :3] / scale @ T_world_cam[:3, :3], S[:3, :3] @ T_world_cam[:3, 3] + S[:3, 3])


def original_number(frame) -> int:
    """A rendered frame's number in its sequence (the experiment renumbers frames; the path keeps it)."""
    return int(frame.path.rsplit("/", 1)[1])


def scripted(stretch: float = 1.0, fails_beyond: int | None = None, recovers: bool = False):
    """A method that reports the true poses seen through S_EST_GT, but after a jump moves ``stretch`` times as far
    from the jump frame as the camera did; with ``fails_beyond``, a jump over more frames is a tracking failure:
    no pose (or, if it ``recovers``, the right pose and a recovery)."""

    def track(config, camera, frames):
        results, jump_centre, previous = [], None, None
        for frame in frames:
            number = original_number(frame)
            result = FrameResult(frame.index, frame.timestamp, seen_through(frame.T_world_cam, S_EST_GT), True)
            if previous is not None and number != previous[0] + 1:
                jump_centre = previous[1]
                if fails_beyond is not None and abs(number - previous[0]) > fails_beyond:
                    result.events.append(Event(EventKind.TRACKING_FAILED, frame.index, frame.timestamp))
                    if recovers:
                        result.events.append(Event(EventKind.RECOVERY_SUCCEEDED, frame.index, frame.timestamp))
                    else:
                        result.T_world_cam, result.tracked = None, False
            if jump_centre is not None and result.T_world_cam is not None:
                stretched = jump_centre + stretch * (frame.T_world_cam[:3, 3] - jump_centre)
                result.T_world_cam = seen_through(se3(frame.T_world_cam[:3, :3], stretched), S_EST_GT)
            previous = (number, frame.T_world_cam[:3, 3])
            results.append(result)
        return results

    return track


@pytest.fixture(scope="module")
def smooth():
    sequence = make_sequence("smooth", 60, seed=0, **TINY)
    return Setup("frame-drop", sequence, {"scripted": load_config()}, None, quiet=True), truth_at_frames(sequence)


PROTOCOL = Protocol(step=5, warmup=10, after=3)


# ------------------------------------------------------------------------------------------------- frame drops


@pytest.mark.parametrize("stretch, outcome", [(1.2, "survived"), (0.6, "survived"), (1.6, "error")])
def test_percent_error_of_a_jump_with_known_motion(smooth, stretch, outcome):
    setup, truth = smooth
    rows = sweep(setup, truth, "scripted", 30, "forward", PROTOCOL, tracker=scripted(stretch))
    first = rows[0]
    assert (first["start_frame"], first["next_frame"], first["measured_frame"]) == (20, 36, 36)  # skips 31..35
    positions = setup.sequence.trajectory.poses[:, :3, 3]
    assert first["gt_translation_m"] == pytest.approx(np.linalg.norm(positions[36] - positions[30]))
    assert first["scale"] == pytest.approx(1 / 0.37)  # the Sim(3) of the frames before the jump
    assert first["translation_error_pct"] == pytest.approx(100 * abs(stretch - 1))
    assert first["rotation_error_pct"] == pytest.approx(0.0, abs=1e-4)
    assert first["outcome"] == outcome
    if outcome == "survived":  # the sweep goes on until the frames run out: 30 + N + 1 + 2 <= 59
        assert [row["frames"] for row in rows] == [5, 10, 15, 20, 25]
        assert all(row["translation_error_pct"] == pytest.approx(100 * abs(stretch - 1)) for row in rows)
    else:
        assert len(rows) == 1


def test_backward_jumps_play_earlier_frames_again(smooth):
    setup, truth = smooth
    rows = sweep(setup, truth, "scripted", 30, "backward", PROTOCOL, tracker=scripted(1.2))
    assert [(row["frames"], row["next_frame"]) for row in rows] == [(5, 25), (10, 20)]  # not before frame 20
    positions = setup.sequence.trajectory.poses[:, :3, 3]
    assert rows[1]["gt_translation_m"] == pytest.approx(np.linalg.norm(positions[20] - positions[30]))
    assert all(row["translation_error_pct"] == pytest.approx(20.0) for row in rows)


def test_a_failure_ends_the_sweep_unless_the_method_recovers(smooth):
    setup, truth = smooth
    rows = sweep(setup, truth, "scripted", 30, "forward", PROTOCOL, tracker=scripted(fails_beyond=12))
    assert [(row["frames"], row["outcome"]) for row in rows] == [(5, "survived"), (10, "survived"),
                                                                  (15, "unrecovered")]
    # The frames after the failed one got poses again, from nowhere: the pose measured is the first of them.
    assert rows[-1]["tracking_failures"] == 1 and rows[-1]["measured_frame"] == rows[-1]["next_frame"] + 1
    recovered = sweep(setup, truth, "scripted", 30, "forward", PROTOCOL,
                      tracker=scripted(fails_beyond=12, recovers=True))
    assert [row["outcome"] for row in recovered] == ["survived"] * 5
    assert recovered[-1]["recoveries"] == 1


# ----------------------------------------------------------------------------------------------------- two loops


def looped(frames: int = 60):
    sequence = make_sequence("loop", frames, seed=1, **TINY)
    shift = loop_shift(sequence)
    return sequence, looped_truth(sequence, shift), loop_spans(sequence, shift)


def estimate_of(truth: Trajectory, S_first: np.ndarray, S_second: np.ndarray, split: float) -> Trajectory:
    """The truth seen through S_first up to time ``split``, through S_second after it."""
    return Trajectory(truth.timestamps, [seen_through(T, S_first if t <= split else S_second)
                                         for t, T in zip(truth.timestamps, truth.poses)])


def test_second_pass_is_timed_after_the_first_by_its_duration_and_one_frame():
    sequence, truth, spans = looped()
    assert spans[1][0] - spans[0][1] == pytest.approx(1 / 30)  # one frame after the last frame of the first pass
    assert np.all(np.diff(truth.timestamps) > 0) and len(truth) == 2 * len(sequence)
    np.testing.assert_array_equal(truth.poses[len(sequence):], truth.poses[:len(sequence)])


def test_two_loop_drifts_of_an_exact_trajectory_are_zero():
    _, truth, spans = looped()
    estimate = estimate_of(truth, S_EST_GT, S_EST_GT, spans[0][1])
    for drift in loop_drifts(estimate, truth, spans, EvalConfig(drift_segment_fraction=0.2)):
        assert drift.alignment_error == pytest.approx(0.0, abs=1e-9)
        assert drift.rotation_drift_deg == pytest.approx(0.0, abs=1e-5)
        assert drift.scale_drift == pytest.approx(1.0) and drift.translation_drift == pytest.approx(0.0, abs=1e-9)


def test_two_loop_drifts_equal_a_drift_injected_in_the_second_loop():
    _, truth, spans = looped()
    D = sim3(1.25, so3_exp(np.array([0.0, np.radians(7.0), 0.0])), np.array([0.1, -0.05, 0.2]))
    # The second pass drifted by D: its poses are the truth moved by D, then seen in the estimate's frame.
    estimate = estimate_of(truth, S_EST_GT, S_EST_GT @ D, spans[0][1])
    first, second = loop_drifts(estimate, truth, spans, EvalConfig(drift_segment_fraction=0.2))
    assert first.alignment_error == pytest.approx(0.0, abs=1e-9)
    # S_s = S_EST_GT^-1 and S_e = (S_EST_GT D)^-1, so T_drift = S_e S_s^-1 = D^-1.
    assert second.scale_drift == pytest.approx(1 / 1.25)
    assert second.rotation_drift_deg == pytest.approx(7.0)
    np.testing.assert_allclose(second.end.transform @ sim3_inverse(second.start.transform), sim3_inverse(D),
                               atol=1e-9)
    # e_align over every frame of both loops: the first loop lands at D^-1 p under S_e, the second at D p under S_s.
    p = truth.positions
    in_first = truth.timestamps <= spans[0][1]
    gaps = np.where(in_first[:, None], p - (p @ sim3_inverse(D)[:3, :3].T + sim3_inverse(D)[:3, 3]),
                    (p @ D[:3, :3].T + D[:3, 3]) - p)
    assert second.alignment_error == pytest.approx(np.sqrt(np.mean(np.sum(gaps**2, axis=1))))


def write_tum_mono(root, frames: int = 40, segment: int = 6):
    """A TUM monoVO folder whose groundtruthSync.txt has poses for the first and last ``segment`` frames only."""
    import cv2

    (root / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    times = 1000.0 + np.arange(frames) / 20.0
    lines = []
    for i, time in enumerate(times):
        cv2.imwrite(str(root / "images" / f"{i:05d}.png"), rng.integers(0, 255, (48, 64), dtype=np.uint8))
        known = i < segment or i >= frames - segment
        pose = f"{0.1 * i} {0.02 * i * i} 0 0 {np.sin(0.05 * i)} 0 {np.cos(0.05 * i)}" if known else " ".join(
            ["nan"] * 7)
        lines.append(f"{time:.6f} {pose}\n")
    (root / "times.txt").write_text("".join(f"{i:05d} {t:.6f} 10\n" for i, t in enumerate(times)))
    (root / "camera.txt").write_text("Pinhole 50 50 31.5 23.5 0\n64 48\nnone\n")
    (root / "groundtruthSync.txt").write_text("".join(lines))
    return root


def test_the_estimate_is_the_trajectory_files_one_a_refused_starts_poses_taken_back_a_starts_first_frame_posed():
    """As trajectory.tum: a start found wrong leaves no pose (its frames', its first frame's), and the start that
    holds poses its first frame once it succeeds."""
    def posed(index):
        return FrameResult(index, float(index), se3(np.eye(3), np.array([index, 0.0, 0.0])), tracked=True)

    def started(index, first):
        result = posed(index)
        result.events.append(Event(EventKind.INITIALIZATION_SUCCEEDED, index, float(index),
                                   {"first_frame": first,
                                    "first_T_world_cam": se3(np.eye(3), np.full(3, float(first))).tolist()}))
        return result

    def unposed(index):
        return FrameResult(index, float(index), None, tracked=False)

    refused = unposed(5)
    refused.events.append(Event(EventKind.INITIALIZATION_REJECTED, 5, 5.0, {"first_frame": 1, "retracted": [3.0, 4.0]}))
    results = [unposed(1), unposed(2), started(3, 1), posed(4), refused, unposed(6), started(7, 5), posed(8)]
    estimate = estimated_trajectory(results)
    assert estimate.timestamps.tolist() == [5.0, 7.0, 8.0]
    assert estimate.poses[0][:3, 3].tolist() == [5.0, 5.0, 5.0]


def test_tum_mono_start_and_end_segments_are_read_as_they_are(tmp_path):
    sequence = open_source(str(write_tum_mono(tmp_path / "sequence_01")), DatasetConfig())
    assert sequence.layout == "tum_mono" and len(sequence) == 40
    assert sorted(truth_at_frames(sequence)) == [*range(6), *range(34, 40)]  # the NaN lines are no poses
    shift = loop_shift(sequence)
    truth, spans = looped_truth(sequence, shift), loop_spans(sequence, shift)
    config = EvalConfig(drift_segment_fraction=0.2)
    assert ground_truth_gap_end(truth.within(*spans[0]).timestamps, config) == pytest.approx(1001.7)  # no ATE
    exact = loop_drifts(estimate_of(truth, S_EST_GT, S_EST_GT, spans[0][1]), truth, spans, config)
    assert all(drift.alignment_error == pytest.approx(0.0, abs=1e-9) for drift in exact)
    # The segments are the ground truth's own six frames, not a share of the matched ones: an estimate off by
    # a similarity after the gap of each loop drifts by exactly that similarity in the first loop.
    D = sim3(0.8, so3_exp(np.array([np.radians(4.0), 0.0, 0.0])), np.zeros(3))
    in_end = np.array([1001.7 <= t <= spans[0][1] for t in truth.timestamps])
    poses = [seen_through(T, S_EST_GT @ D if end else S_EST_GT) for T, end in zip(truth.poses, in_end)]
    first = loop_drifts(Trajectory(truth.timestamps, poses), truth, spans, config)[0]
    assert first.scale_drift == pytest.approx(1 / 0.8) and first.rotation_drift_deg == pytest.approx(4.0)


# --------------------------------------------------------------------------------------------------- timings


def timed(index: int, **timings_ms: float) -> FrameResult:
    return FrameResult(index, index / 30, np.eye(4), True, timings_ms=timings_ms)


def test_table_2_samples_each_process_in_the_frames_it_ran_in():
    results = [timed(0, pyramid=1.0, track=4.0, total=5.0),
               timed(1, pyramid=1.0, track=5.0, recovery=20.0, total=26.0),
               timed(2, pyramid=1.0, track=3.0, keyframe=40.0, feature_mapping=150.0, total=194.0)]
    samples = process_samples("fdmo", results)
    assert samples["tracking (per frame)"] == [5.0, 26.0, 4.0]  # FDMO counts its recovery as tracking
    assert samples["direct mapping (per keyframe)"] == [40.0]
    assert samples["feature mapping (per keyframe)"] == [150.0]
    assert samples["recovery (per attempt)"] == [20.0]
    assert samples["whole frame"] == [5.0, 26.0, 194.0]
    direct = process_samples("direct", results[:1])
    assert "feature mapping (per keyframe)" not in direct and direct["direct mapping (per keyframe)"] == []
    lines = table({"fdmo": samples, "direct": direct}).splitlines()
    assert lines[0] == "| process (ms) | fdmo | direct |"
    assert "| direct mapping (per keyframe) | 40.00 +- 0.00 (1) | never ran |" in lines
    assert "| feature mapping (per keyframe) | 150.00 +- 0.00 (1) | - |" in lines


# --------------------------------------------------------------------------------------------- the commands


def run_twice(tmp_path, capsys, *argv) -> tuple[str, str]:
    outputs = []
    for name in ("first", "second"):
        assert main(["experiment", *argv, "--out", str(tmp_path / name), "--quiet"]) == 0
        outputs.append(capsys.readouterr().out)
    return outputs


def test_frame_drop_gives_the_same_numbers_when_run_again(tmp_path, capsys):
    first, second = run_twice(tmp_path, capsys, "frame-drop", "synthetic:smooth:40:320x240", "--methods", "fdmo",
                              "--at", "20", "--direction", "forward", "--step", "8", "--warmup", "15", "--after", "3")
    trials = (tmp_path / "first" / "trials.csv").read_text()
    assert trials == (tmp_path / "second" / "trials.csv").read_text() and first.split("results in")[0] in second
    assert trials.splitlines()[0].startswith("method,direction,at_frame,frames,")
    for name in ("frame_drop.png", "table.md", "config_fdmo.yaml", "experiment.yaml"):
        assert (tmp_path / "first" / name).is_file()


def test_two_loop_gives_the_same_numbers_when_run_again(tmp_path, capsys):
    first, _ = run_twice(tmp_path, capsys, "two-loop", "synthetic:loop:24:320x240", "--methods", "direct")
    loops = (tmp_path / "first" / "loops.csv").read_text()
    assert loops == (tmp_path / "second" / "loops.csv").read_text()
    assert [line.split(",")[:2] for line in loops.splitlines()[1:]] == [["direct", "1"], ["direct", "2"]]
    assert "| direct | 2 |" in first


@pytest.mark.parametrize("argv, message", [
    (["frame-drop", "synthetic:smooth:20:64x48", "--methods", "fdmo,orb"], "--methods fdmo,orb: expected"),
    (["frame-drop", "synthetic:smooth:20:64x48", "--at", "20"], "--at 20: not a frame"),
    (["two-loop", "synthetic:loop:x", "--segment", "0.2"], "expected synthetic:PRESET"),
    (["two-loop", "synthetic:loop:20:64x48", "--segment", "0.7"], "--segment 0.7: must be in"),
])
def test_bad_experiment_arguments_are_one_line_errors(tmp_path, capsys, argv, message):
    assert main(["experiment", *argv, "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert message in error and len(error.strip().splitlines()) == 1
